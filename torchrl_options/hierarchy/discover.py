"""One-call discovery of a multi-level hierarchy of options: DDO level by level (Fox et al., 2017, section 4.3)."""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

from torchrl_options.checkpoints import restores_global_rng
from torchrl_options.checks import check_int
from torchrl_options.discovery.batch import discovery_batch, infer_in_features, minibatch
from torchrl_options.discovery.fit import fit_ddo
from torchrl_options.discovery.networks import check_networks, Networks, resolve_settings
from torchrl_options.discovery.settings import check_stopping_rule, DEFAULT_RESTARTS, DiscoverySettings, obs_key_list
from torchrl_options.discovery.stages import best_of_starts, run_discovery, Start
from torchrl_options.discovery.tabulated import expected_counts, tabulate_states
from torchrl_options.hierarchy.hierarchy import OptionHierarchy
from torchrl_options.hierarchy.loss import HierarchicalDDOLoss
from torchrl_options.modules import MetaControlMLP, OptionsMLP

__all__ = ["discover_hierarchy", "HierarchyDiscoveryResult"]

logger = logging.getLogger(__name__)

@dataclass
class HierarchyDiscoveryResult:
    """What :func:`discover_hierarchy` returns with ``return_info=True``.

    Attributes:
        hierarchy (OptionHierarchy): the discovered levels (with the meta-controls used to discover them).
        history (list of list of dict): per level, per iteration, ``loss_ddo`` and the loss diagnostics (of the
            start that was kept, with ``restarts``).
        restart_log_likelihoods (list of list of float): per level, with ``restarts > 1``, each start's
            log-likelihood per step after its ``restart_iterations`` (empty lists otherwise).
    """

    hierarchy: OptionHierarchy
    history: list[list[dict]] = field(default_factory=list)
    restart_log_likelihoods: list[list[float]] = field(default_factory=list)


def _per_level(value, num_levels: int, name: str) -> list:
    if isinstance(value, (list, tuple)):
        if len(value) != num_levels:
            raise ValueError(f"{name} has {len(value)} entries, one per level is needed ({num_levels} levels).")
        return list(value)
    return [value] * num_levels


@restores_global_rng
def discover_hierarchy(
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    num_options: Sequence[int],
    *,
    meta_control: str | Sequence[str] = "uniform",
    hierarchy: OptionHierarchy | None = None,
    num_actions: int | None = None,
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] = 8,
    activation: str = "tanh",
    architecture: str = "separate",
    init: str = "random",
    num_iterations: int | Sequence[int] = 1000,
    m_steps: int | Sequence[int] = 5,
    tol: float | None = 1e-4,
    patience: int = 20,
    restarts: int | None | Sequence[int | None] = None,
    restart_iterations: int = 40,
    batch_size: int | None = None,
    optimizer: Callable[..., torch.optim.Optimizer] | None = None,
    lr: float = 0.03,
    device: torch.device | str | None = None,
    seed: int | None = None,
    progress: bool = True,
    return_info: bool = False,
    log_every: int = 50,
    desc: str = "DDO",
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
        init (str): level-1 initialisation, one of :data:`~torchrl_options.discovery.INITS` (see
            :func:`~torchrl_options.discover_options`). Defaults to ``"random"`` (the planted two-level benchmark
            was measured with it).
        num_iterations (int or sequence of int): the most iterations (E-steps), for all levels or per level.
            Defaults to 1000 (the stopping rule usually ends a level sooner).
        m_steps (int or sequence of int): optimizer steps per E-step, for all levels or per level: 1 is the paper's
            Expectation-Gradient, more (default 5) a generalised EM (see :func:`~torchrl_options.discover_options`).
        tol (float, optional): stopping rule of every level: stop once its log-likelihood per step has gained less
            than ``tol`` nats over the last ``patience`` iterations. Defaults to 1e-4; ``None`` runs all
            iterations.
        patience (int): the stopping rule's window, in iterations. Defaults to 20.
        restarts (int or sequence of int): every level (or each level, from a list) is fitted from ``restarts``
            random initialisations, each trained for at most ``restart_iterations`` iterations; the one with the
            highest training log-likelihood (label-free model selection) then gets the rest of its
            ``num_iterations``. Likelihood training has local optima (an option left unused, two merged), which
            restarts avoid. ``None`` (default): 4 starts where a level's ``num_iterations`` is at least 4 x
            ``restart_iterations``, else 1.
        restart_iterations (int): the iterations given to each start when ``restarts > 1`` (capped at the level's
            ``num_iterations``). Defaults to 40.
        batch_size (int, optional): trajectories per minibatch; ``None`` uses all.
        optimizer: a factory called as ``optimizer(params, lr=lr)``, once per level and start. Defaults to Adam.
        lr (float): learning rate. Defaults to 0.03.
        device: where to train. Defaults to the data's device.
        seed (int, optional): seeds initialisation and minibatch order; the global random states are restored on
            return, so the caller's random numbers do not change.
        progress (bool): tqdm progress bars. Defaults to ``True``.
        return_info (bool): return a :class:`HierarchyDiscoveryResult` with the training history.
        log_every (int): log (and record) the full diagnostics every this many iterations; other iterations
            record ``loss`` and ``log_likelihood_per_step`` only (the diagnostics cost a backward pass).
        desc (str): the progress bars' label, followed by the level (``"<desc> level 2"``). Defaults to ``"DDO"``.

    Returns:
        The :class:`OptionHierarchy` (or a :class:`HierarchyDiscoveryResult` with ``return_info=True``).

    Raises:
        ValueError: naming the argument, for empty or non-positive ``num_options``, a per-level list of the wrong
            length, non-positive ``m_steps``, ``restarts`` or ``patience``, a negative ``tol``, or a ``num_actions``
            that disagrees with the hierarchy.

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
    m_steps = _per_level(m_steps, levels, "m_steps")
    restarts = _per_level(restarts, levels, "restarts")
    for n in iterations:
        check_int(n, "num_iterations", minimum=0)
    # None: several short starts (as discover_options) where the level's iterations leave room for them
    restarts = [
        (DEFAULT_RESTARTS if n_iter >= DEFAULT_RESTARTS * restart_iterations else 1) if n is None else n
        for n, n_iter in zip(restarts, iterations)
    ]
    for m in m_steps:
        check_int(m, "m_steps", minimum=1)
    check_stopping_rule(tol, patience)
    for n in restarts:
        check_int(n, "restarts", minimum=1)
        if n > 1:
            check_int(restart_iterations, "restart_iterations", minimum=1)
    obs_keys = obs_key_list(obs_keys)
    generator = torch.Generator()
    if seed is not None:
        torch.manual_seed(seed)
        generator.manual_seed(seed)

    # the door: the trajectories batched and checked once, on the device; every level trains on this batch
    if isinstance(trajectories, ReplayBuffer):
        raise TypeError("discover_hierarchy needs the trajectories as tensordicts (a [B, T] batch or a list), got a ReplayBuffer.")
    door = DiscoverySettings(num_options[0], num_actions=num_actions, obs_keys=obs_keys, action_key=action_key,
                             device=device)  # fmt: skip
    batch = discovery_batch(trajectories, door, infer_num_actions=False)
    data = batch.data
    if hierarchy is not None:
        if num_actions is not None and num_actions != hierarchy.num_actions:
            raise ValueError(f"num_actions={num_actions} but the given hierarchy has num_actions={hierarchy.num_actions}.")
        num_actions = hierarchy.num_actions
    if num_actions is None:
        num_actions = int(data.get(action_key)[batch.mask].max()) + 1
        logger.info("num_actions not given: using max(action) + 1 = %d", num_actions)
    batch.num_actions = num_actions
    hierarchy = OptionHierarchy(num_actions) if hierarchy is None else hierarchy
    hierarchy = hierarchy.to(batch.device)
    history: list[list[dict]] = []
    restart_lls: list[list[float]] = []
    for d, (K, meta, n_iter, m, n_restarts) in enumerate(zip(num_options, metas, iterations, m_steps, restarts)):
        level = hierarchy.num_levels + 1
        settings = DiscoverySettings(
            K, meta_control=meta, num_actions=num_actions, obs_keys=obs_keys, action_key=action_key,
            num_cells=num_cells, activation=activation, architecture=architecture, init=init, num_iterations=n_iter,
            m_steps=m, tol=tol, patience=patience, restarts=n_restarts,
            restart_iterations=min(restart_iterations, n_iter), batch_size=batch_size, lr=lr,
            seed=None if seed is None else seed + d, progress=progress, log_every=log_every, desc=desc,
        )  # fmt: skip
        if level == 1:
            options, meta_module, records, lls = _first_level(batch, settings, optimizer)
        else:
            options, meta_module, records, lls = _upper_level(batch, settings, hierarchy, level, optimizer, generator)
        hierarchy.append(options, meta_control=meta_module)
        history.append(records)
        restart_lls.append(lls)
    if return_info:
        return HierarchyDiscoveryResult(hierarchy=hierarchy, history=history, restart_log_likelihoods=restart_lls)
    return hierarchy


def _first_level(batch, settings: DiscoverySettings, optimizer) -> tuple:
    """Level 1: DDO over the primitive actions, the stages of :func:`~torchrl_options.discover_options` on the
    checked batch, seeded by the level's seed (the global RNG runs on from there to the next level)."""
    networks = Networks(optimizer=optimizer)
    settings = resolve_settings(settings, networks)
    check_networks(settings, networks)
    generator = torch.Generator()
    if settings.seed is not None:
        torch.manual_seed(settings.seed)
        generator.manual_seed(settings.seed)
    result = run_discovery(batch, settings.replace(desc="DDO"), networks, generator)
    return result.options, result.meta_control, result.history, result.restart_log_likelihoods


def _upper_level(batch, settings: DiscoverySettings, hierarchy: OptionHierarchy, level: int, optimizer,
                 generator: torch.Generator) -> tuple:  # fmt: skip
    """Level ``level`` over the actions and the options below (fixed): :class:`HierarchicalDDOLoss`, the same
    choice among starts (:func:`~torchrl_options.discovery.stages.best_of_starts`)."""
    data, obs_keys, K = batch.data, settings.obs_key_list, settings.num_options
    in_features = infer_in_features(data, obs_keys)

    def make(r: int) -> Start:
        options = OptionsMLP(
            in_features, hierarchy.action_space_sizes[-1], K, num_cells=settings.num_cells,
            activation=settings.activation, architecture=settings.architecture, in_keys=obs_keys,
        ).to(batch.device)  # fmt: skip
        meta_module = None
        if settings.meta_control == "learned":
            meta_module = MetaControlMLP(in_features, K, num_cells=settings.num_cells, activation=settings.activation,
                                         in_keys=obs_keys).to(batch.device)  # fmt: skip
        loss_module = HierarchicalDDOLoss(options, hierarchy, meta_module, diagnostics=False)
        loss_module.set_keys(action=settings.action_key)
        params = list(options.parameters()) + (list(meta_module.parameters()) if meta_module is not None else [])
        opt = torch.optim.Adam(params, lr=settings.lr, foreach=True) if optimizer is None else optimizer(params, lr=settings.lr)
        return Start(loss_module, opt)

    def train(start: Start, n: int, label: str, final: bool) -> list[dict]:
        return _train(start.loss_module, start.optimizer, data, n, settings.batch_size, generator, settings.progress,
                      settings.log_every, level, m_steps=settings.m_steps, tol=settings.tol,
                      patience=settings.patience, desc=label)  # fmt: skip

    start, records, lls = best_of_starts(
        make, train, restarts=settings.restarts, restart_iterations=settings.restart_iterations,
        num_iterations=settings.num_iterations, tol=settings.tol, patience=settings.patience, desc=settings.desc,
        what=f"level {level}",
    )  # fmt: skip
    return start.loss_module.options, start.loss_module.meta_control, records, lls


class HierarchicalEStep:
    """The E-step of :class:`HierarchicalDDOLoss` for :func:`~torchrl_options.discovery.fit.fit_ddo`, with a
    G-step objective that several optimizer steps can reuse (a generalised EM).

    ``estep(batch)`` runs the exact hierarchical forward-backward once and returns ``(record, objective)``:
    ``record`` holds ``loss_ddo`` and ``log_likelihood_per_step`` (and, when ``loss_module.diagnostics`` is on, the
    loss's other diagnostics); ``objective()`` is ``-sum(g * p(theta)) / n_steps`` over the trained level's
    log-probabilities ``p`` (control, termination, continuation and, if learned, meta-control), with ``g`` their
    gradients at the E-step: the posterior expected counts of each choice. Its gradient at the E-step's parameters
    is the gradient of the log-likelihood (Fox et al., 2017, section 4.2) and, since the likelihood is a sum over
    call-stack histories of products of these probabilities, every step that increases it increases the
    likelihood at least as much.

    Args:
        loss_module (HierarchicalDDOLoss): the loss (reduction ``"mean"``).

    Examples:
        >>> import torch
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.hierarchy import OptionHierarchy
        >>> from torchrl_options.testing.planted_hierarchy import planted_two_level_demonstrations
        >>> data = planted_two_level_demonstrations(4, 20)
        >>> loss = HierarchicalDDOLoss(OptionsMLP(2, 8, 2), OptionHierarchy(4, [OptionsMLP(2, 4, 4)]))
        >>> record, objective = HierarchicalEStep(loss)(data)
        >>> torch.allclose(record["loss_ddo"], loss(data)["loss_ddo"])
        True
        >>> objective().backward()
    """

    def __init__(self, loss_module: HierarchicalDDOLoss) -> None:
        if loss_module.reduction != "mean":
            raise ValueError(f"loss_module must use reduction='mean', got {loss_module.reduction!r}.")
        self.loss_module = loss_module

    def __call__(self, batch: TensorDictBase) -> tuple[dict, Callable[[], torch.Tensor]]:
        loss = self.loss_module
        keys = loss.tensor_keys
        options, meta_control = loss.options, loss.meta_control
        with torch.no_grad():
            p = loss.log_probabilities(batch)  # the batch's one check (one synchronisation)
        mask = p["mask"]
        trained = [p["log_pi"][-1], p["log_term"][-1], p["log_cont"][-1]]
        if meta_control is not None:
            trained.append(p["log_eta"])
        leaves = [x.detach().requires_grad_() for x in trained]
        log_eta = leaves[3] if meta_control is not None else p["log_eta"]
        with torch.enable_grad():
            # one recursion gives the gradients (the expected counts) and, when logged, the loss's diagnostics
            post = loss._posterior(
                p, marginals=loss.diagnostics, log_pi=[*p["log_pi"][:-1], leaves[0]],
                log_term=[*p["log_term"][:-1], leaves[1]], log_cont=[*p["log_cont"][:-1], leaves[2]], log_eta=log_eta,
            )  # fmt: skip
            grads = torch.autograd.grad(post.log_likelihood.sum(), leaves)
        record = {k: v.detach() for k, v in loss.loss_outputs(p, post).items()}
        n = mask.sum()

        # the trained level's networks run once per distinct state of the batch
        batch = batch if batch.ndim == 2 else batch.unsqueeze(0)
        option_keys = list(options.in_keys)
        current = batch.select(*option_keys)
        following = batch.get("next").select(*option_keys)
        table, state_index, next_index = tabulate_states(option_keys, mask, current, following)
        U = table.batch_size[0]
        n_pi = expected_counts(state_index, grads[0], mask, U)
        n_term = expected_counts(next_index, grads[1], mask, U)
        n_cont = expected_counts(next_index, grads[2], mask, U)
        if meta_control is not None:
            meta_keys = list(meta_control.in_keys)
            meta_table, meta_index, _ = tabulate_states(meta_keys, mask, batch.select(*meta_keys))
            n_eta = expected_counts(meta_index, grads[3], mask, meta_table.batch_size[0])

        def objective() -> torch.Tensor:
            out = options(table.clone(False))
            log_pi = out.get(keys.option_logits).log_softmax(-1)
            term_logits = out.get(keys.termination_logits)
            # zero counts times -inf (a choice an option cannot make) contribute nothing
            q = torch.where(n_pi != 0, n_pi * log_pi, 0.0).sum()
            q = q + (n_term * torch.nn.functional.logsigmoid(term_logits)).sum()
            q = q + (n_cont * torch.nn.functional.logsigmoid(-term_logits)).sum()
            if meta_control is not None:
                q = q + (n_eta * meta_control(meta_table.clone(False)).get(keys.meta_logits).log_softmax(-1)).sum()
            return -q / n

        return record, objective


def _train(
    loss_module, opt, data, num_iterations, batch_size, generator, progress, log_every, level, *, m_steps=1, tol=None,
    patience=20, desc="DDO",
) -> list[dict]:
    def set_diagnostics(full: bool) -> None:
        loss_module.diagnostics = full

    records = fit_ddo(
        loss_module, opt, lambda it: minibatch(data, batch_size, generator), num_iterations,
        e_step=HierarchicalEStep(loss_module), m_steps=m_steps, tol=tol, patience=patience,
        desc=f"{desc} level {level}", progress=progress, log_every=log_every, set_diagnostics=set_diagnostics,
    )  # fmt: skip
    loss_module.diagnostics = True
    return records
