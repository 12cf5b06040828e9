"""One-call discovery of a multi-level hierarchy of options: DDO level by level (Fox et al., 2017, section 4.3)."""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.discovery.discover import (
    _infer_in_features,
    as_trajectory_batch,
    discover_options,
    fit_ddo,
    minibatch,
)
from torchrl_options.hierarchy.hierarchy import OptionHierarchy
from torchrl_options.hierarchy.loss import HierarchicalDDOLoss
from torchrl_options.modules import MetaControlMLP, OptionsMLP

__all__ = ["discover_hierarchy", "HierarchyDiscoveryResult"]

logger = logging.getLogger(__name__)

_MASK = ("collector", "mask")


@dataclass
class HierarchyDiscoveryResult:
    """What :func:`discover_hierarchy` returns with ``return_info=True``.

    Attributes:
        hierarchy (OptionHierarchy): the discovered levels (with the meta-controls used to discover them).
        history (list of list of dict): per level, per iteration, ``loss`` and the loss diagnostics.
    """

    hierarchy: OptionHierarchy
    history: list[list[dict]] = field(default_factory=list)


def _per_level(value, num_levels: int, name: str) -> list:
    if isinstance(value, (list, tuple)):
        if len(value) != num_levels:
            raise ValueError(f"{name} has {len(value)} entries, one per level is needed ({num_levels} levels).")
        return list(value)
    return [value] * num_levels


def discover_hierarchy(
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    num_options: Sequence[int],
    *,
    meta_control: str | Sequence[str] = "uniform",
    hierarchy: OptionHierarchy | None = None,
    num_actions: int | None = None,
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] = 2,
    activation: str = "tanh",
    architecture: str = "separate",
    init: str = "random",
    num_iterations: int | Sequence[int] = 500,
    restarts: int = 1,
    restart_iterations: int = 50,
    batch_size: int | None = None,
    optimizer: Callable[..., torch.optim.Optimizer] | None = None,
    lr: float = 1e-2,
    device: torch.device | str | None = None,
    seed: int | None = None,
    progress: bool = True,
    return_info: bool = False,
    log_every: int = 50,
) -> OptionHierarchy | HierarchyDiscoveryResult:
    """Discovers a hierarchy of options, level by level, from demonstrations of primitive actions.

    Section 4.3 of Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options" (2017): level 1 is
    DDO over the primitive actions (:func:`~torchrl_options.discover_options`); then, for ``d = 1, 2, ...``, the
    action space is augmented with the level-``d`` options and level ``d + 1`` is trained by
    :class:`HierarchicalDDOLoss` with the levels below fixed, under the exact likelihood of the joint
    call-and-return hierarchy. ``meta_control="uniform"`` fixes every level's meta-control to uniform (H2u);
    ``"learned"`` trains an MLP meta-control with each level (H2s).

    Args:
        trajectories: a ``[B, T]`` tensordict of primitive-action demonstrations (see
            :func:`~torchrl_options.as_trajectory_batch`), or a list of ``[T_i]`` trajectories.
        num_options (sequence of int): ``[K_1, K_2, ...]``, the options of each level to discover.

    Keyword Args:
        meta_control (str or sequence of str): ``"uniform"`` (default) or ``"learned"``, for all levels or per level.
        hierarchy (OptionHierarchy, optional): levels already discovered: ``num_options`` then lists the levels
            to add on top of it (the given hierarchy is extended in place and returned).
        num_actions (int, optional): A; default: the hierarchy's, or ``max(action) + 1`` over the data.
        obs_keys, action_key, num_cells, activation, architecture: as in :func:`~torchrl_options.discover_options`,
            for every level's modules.
        init (str): level-1 initialisation, ``"random"`` or ``"kmeans"``.
        num_iterations (int or sequence of int): gradient steps, for all levels or per level. Defaults to 500.
        restarts (int): levels above 1 are fitted from ``restarts`` random initialisations, each trained for
            ``restart_iterations`` steps; the one with the highest log-likelihood then gets the remaining
            ``num_iterations - restart_iterations`` steps. Likelihood training of a level over lower options
            has local optima (an option left unused, two merged), which restarts avoid. Defaults to 1.
        restart_iterations (int): the steps given to each initialisation when ``restarts > 1``. Defaults to 50.
        batch_size (int, optional): trajectories per minibatch; ``None`` uses all.
        optimizer: a factory called as ``optimizer(params, lr=lr)``, once per level. Defaults to Adam.
        lr (float): learning rate. Defaults to 1e-2.
        device: where to train. Defaults to the data's device.
        seed (int, optional): seeds initialisation and minibatch order.
        progress (bool): tqdm progress bars. Defaults to ``True``.
        return_info (bool): return a :class:`HierarchyDiscoveryResult` with the training history.
        log_every (int): log (and record) the full diagnostics every this many iterations; other iterations
            record ``loss`` and ``log_likelihood_per_step`` only (the diagnostics cost a backward pass).

    Returns:
        The :class:`OptionHierarchy` (or a :class:`HierarchyDiscoveryResult` with ``return_info=True``).

    Raises:
        ValueError: naming the argument, for empty or non-positive ``num_options``, a ``meta_control`` or
            ``num_iterations`` list of the wrong length, or a ``num_actions`` that disagrees with the hierarchy.

    Examples:
        >>> from torchrl_options.testing.planted_hierarchy import planted_two_level_demonstrations
        >>> data = planted_two_level_demonstrations(4, 20)
        >>> h = discover_hierarchy(data, [4, 2], num_iterations=3, seed=0, progress=False)
        >>> h.num_levels, h.action_space_sizes
        (2, [4, 8, 10])
    """
    num_options = list(num_options) if isinstance(num_options, (list, tuple)) else num_options
    if not isinstance(num_options, list) or not num_options or not all(isinstance(k, int) and k >= 1 for k in num_options):
        raise ValueError(f"num_options must be a non-empty list of positive ints (one per level), got {num_options!r}.")
    levels = len(num_options)
    metas = _per_level(meta_control, levels, "meta_control")
    for m in metas:
        if m not in ("uniform", "learned"):
            raise ValueError(f"meta_control must be 'uniform' or 'learned' (or a list of them), got {m!r}.")
    iterations = _per_level(num_iterations, levels, "num_iterations")
    obs_keys = [obs_keys] if isinstance(obs_keys, (str, tuple)) else list(obs_keys)
    generator = torch.Generator()
    if seed is not None:
        torch.manual_seed(seed)
        generator.manual_seed(seed)

    data = as_trajectory_batch(trajectories)
    if device is None:
        device = data.device if data.device is not None else torch.device("cpu")
    device = torch.device(device)
    data = data.to(device)
    mask = data.get(_MASK)
    if hierarchy is not None:
        if num_actions is not None and num_actions != hierarchy.num_actions:
            raise ValueError(f"num_actions={num_actions} but the given hierarchy has num_actions={hierarchy.num_actions}.")
        num_actions = hierarchy.num_actions
    if num_actions is None:
        num_actions = int(data.get(action_key)[mask].max()) + 1
        logger.info("num_actions not given: using max(action) + 1 = %d", num_actions)
    if hierarchy is None:
        hierarchy = OptionHierarchy(num_actions)
    hierarchy = hierarchy.to(device)
    in_features = _infer_in_features(data, obs_keys)
    history: list[list[dict]] = []

    for d, (K, meta, n_iter) in enumerate(zip(num_options, metas, iterations)):
        level = hierarchy.num_levels + 1
        if level == 1:
            result = discover_options(
                data, K, meta_control=meta, num_actions=num_actions, obs_keys=obs_keys, action_key=action_key,
                num_cells=num_cells, activation=activation, architecture=architecture, init=init,
                num_iterations=n_iter, batch_size=batch_size, optimizer=optimizer, lr=lr, device=device,
                seed=None if seed is None else seed + d, progress=progress, return_info=True, log_every=log_every,
            )
            hierarchy.append(result.options, meta_control=result.meta_control)
            history.append(result.history)
            continue
        if restarts < 1 or (restarts > 1 and not 0 < restart_iterations <= n_iter):
            raise ValueError(
                f"restarts must be >= 1 and restart_iterations in [1, num_iterations], got {restarts} and "
                f"{restart_iterations}."
            )
        candidates = []
        for _ in range(restarts):
            options = OptionsMLP(
                in_features, hierarchy.action_space_sizes[-1], K, num_cells=num_cells, activation=activation,
                architecture=architecture, in_keys=obs_keys,
            ).to(device)
            meta_module = None
            if meta == "learned":
                meta_module = MetaControlMLP(
                    in_features, K, num_cells=num_cells, activation=activation, in_keys=obs_keys
                ).to(device)
            loss_module = HierarchicalDDOLoss(options, hierarchy, meta_module, diagnostics=False)
            loss_module.set_keys(action=action_key)
            params = list(options.parameters()) + (list(meta_module.parameters()) if meta_module is not None else [])
            opt = torch.optim.Adam(params, lr=lr) if optimizer is None else optimizer(params, lr=lr)
            first = restart_iterations if restarts > 1 else n_iter
            records = _train(loss_module, opt, data, first, batch_size, generator, progress, log_every, level)
            candidates.append((records[-1]["log_likelihood_per_step"], loss_module, opt, records))
        best = max(range(restarts), key=lambda i: candidates[i][0])
        _, loss_module, opt, records = candidates[best]
        if restarts > 1:
            logger.info("level %d: restart %d of %d has the best log-likelihood per step (%.4f)", level, best,
                        restarts, candidates[best][0])
            records += _train(loss_module, opt, data, n_iter - restart_iterations, batch_size, generator, progress,
                              log_every, level)
        history.append(records)
        hierarchy.append(loss_module.options, meta_control=loss_module.meta_control)
    if return_info:
        return HierarchyDiscoveryResult(hierarchy=hierarchy, history=history)
    return hierarchy


def _train(loss_module, opt, data, num_iterations, batch_size, generator, progress, log_every, level) -> list[dict]:
    def set_diagnostics(full: bool) -> None:
        loss_module.diagnostics = full

    records = fit_ddo(
        loss_module, opt, lambda it: minibatch(data, batch_size, generator), num_iterations,
        desc=f"DDO level {level}", progress=progress, log_every=log_every, set_diagnostics=set_diagnostics,
    )  # fmt: skip
    loss_module.diagnostics = True
    return records
