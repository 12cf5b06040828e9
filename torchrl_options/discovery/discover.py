"""One-call option discovery: DDO (Fox et al., 2017) trained with :class:`~torchrl_options.DDOLoss`."""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import pad_sequence, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

from torchrl_options.discovery.initialization import pretrain_on_clusters
from torchrl_options.modules import GaussianOptionsMLP, MetaControlMLP, OptionsMLP
from torchrl_options.objectives import DDOLoss

__all__ = ["DiscoveryResult", "discover_options", "as_trajectory_batch"]

logger = logging.getLogger(__name__)

_MASK = ("collector", "mask")


@dataclass
class DiscoveryResult:
    """What :func:`discover_options` returns with ``return_info=True``.

    Attributes:
        options: the trained options module.
        meta_control: the trained meta-control module, ``None`` for the uniform one.
        history (list of dict): per iteration, ``loss`` and the diagnostics of :class:`DDOLoss`.
    """

    options: TensorDictModuleBase
    meta_control: TensorDictModuleBase | None
    history: list[dict] = field(default_factory=list)

    @property
    def final_log_likelihood_per_step(self) -> float:
        return self.history[-1]["log_likelihood_per_step"] if self.history else float("nan")


def as_trajectory_batch(
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    *,
    trajectory_key: NestedKey | None = None,
    mask_key: NestedKey = _MASK,
) -> TensorDictBase:
    """Brings trajectories into the ``[B, T]`` layout with a validity mask that :class:`DDOLoss` reads.

    Accepts a ``[B, T]`` tensordict (a missing mask means all steps valid), a single ``[T]`` trajectory, a list
    of ``[T_i]`` trajectories of different lengths (padded at the end), or, with ``trajectory_key``, a flat
    ``[N]`` replay-buffer sample of trajectory slices (e.g. from a ``SliceSampler``). Slices are cut where the
    trajectory id changes or a step is ``("next", "done")`` or ``("next", "truncated")`` (the sampler marks
    each slice's end so): unlike ``split_trajectories``, two slices of one trajectory in a sample stay apart.

    Keyword Args:
        trajectory_key (NestedKey, optional): the trajectory ids of a flat sample.
        mask_key (NestedKey): where to write the mask. Defaults to ``("collector", "mask")``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> trajs = [TensorDict({"observation": torch.randn(t, 2)}, [t]) for t in (3, 5)]
        >>> batch = as_trajectory_batch(trajs)
        >>> batch.batch_size, batch["collector", "mask"].sum(1)
        (torch.Size([2, 5]), tensor([3, 5]))
        >>> flat = TensorDict({"observation": torch.randn(7, 2), "ids": torch.tensor([4, 4, 4, 1, 1, 4, 4])}, [7])
        >>> as_trajectory_batch(flat, trajectory_key="ids")["collector", "mask"].sum(1)
        tensor([3, 2, 2])
    """
    if isinstance(trajectories, TensorDictBase):
        td = trajectories
        if td.numel() == 0:
            raise ValueError("trajectories is empty: discovery needs at least one step.")
        if td.ndim == 1 and trajectory_key is not None:
            return as_trajectory_batch(_split_slices(td, trajectory_key), mask_key=mask_key)
        if td.ndim == 1:
            td = td.unsqueeze(0)
        if td.ndim != 2:
            raise ValueError(f"trajectories must be [B, T] (or one [T] trajectory), got batch_size {tuple(td.batch_size)}.")
        if mask_key not in td.keys(include_nested=True):
            td = td.clone(False)
            td.set(mask_key, torch.ones(td.batch_size, dtype=torch.bool, device=td.device))
        return td
    trajectories = list(trajectories)
    if not trajectories:
        raise ValueError("trajectories is an empty list: discovery needs at least one trajectory.")
    for i, t in enumerate(trajectories):
        if not isinstance(t, TensorDictBase) or t.ndim != 1 or t.numel() == 0:
            raise ValueError(f"trajectories[{i}] must be a non-empty [T] tensordict, got {type(t).__name__}.")
    lengths = torch.tensor([t.numel() for t in trajectories])
    td = pad_sequence(trajectories)
    td.set(mask_key, (torch.arange(td.shape[1])[None] < lengths[:, None]).to(td.device))
    return td


def _split_slices(flat: TensorDictBase, trajectory_key: NestedKey) -> list[TensorDictBase]:
    ids = flat.get(trajectory_key, None)
    if ids is None:
        raise KeyError(f"the sample has no {trajectory_key!r} entry (trajectory_key).")
    ids = ids.reshape(-1)
    cut = torch.zeros_like(ids, dtype=torch.bool)
    cut[1:] = ids[1:] != ids[:-1]
    for key in (("next", "done"), ("next", "truncated")):
        flag = flat.get(key, None)
        if flag is not None:
            cut[1:] |= flag.reshape(-1)[:-1].bool()
    starts = cut.nonzero().flatten().tolist()
    bounds = [0, *starts, ids.numel()]
    return [flat[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


def minibatch(data: TensorDictBase, batch_size: int | None, generator: torch.Generator) -> TensorDictBase:
    """``batch_size`` trajectories drawn without replacement (all of them when ``batch_size`` is ``None``)."""
    B = data.batch_size[0]
    if batch_size is None or batch_size >= B:
        return data
    return data[torch.randperm(B, generator=generator)[:batch_size].to(data.device)]


def fit_ddo(
    loss_module: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    next_batch: Callable[[int], TensorDictBase],
    num_iterations: int,
    *,
    desc: str = "DDO",
    progress: bool = True,
    log_every: int = 50,
    set_diagnostics: Callable[[bool], None] | None = None,
) -> list[dict]:
    """The gradient loop of discovery, one- or multi-level: ``num_iterations`` steps on ``next_batch(it)``.

    Returns per iteration the loss module's outputs as floats. Diagnostics are logged every ``log_every``
    iterations; ``set_diagnostics(full)`` is told before each step whether this one is logged (a loss whose full
    diagnostics cost extra can skip them otherwise).
    """
    records: list[dict] = []
    iterator = range(num_iterations)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(iterator, desc=desc, unit="it")
        iterator = bar
    for it in iterator:
        batch = next_batch(it)
        full = bool(log_every) and (it % log_every == 0 or it == num_iterations - 1)
        if set_diagnostics is not None:
            set_diagnostics(full)
        out = loss_module(batch)
        optimizer.zero_grad()
        out["loss_ddo"].backward()
        optimizer.step()
        record = {k: float(v.detach()) for k, v in out.items()}
        records.append(record)
        if bar is not None:
            postfix = {"ll_step": f"{record['log_likelihood_per_step']:.4f}"}
            if "option_duration" in record:
                postfix["dur"] = f"{record['option_duration']:.1f}"
            bar.set_postfix(postfix)
        if full:
            logger.info("%s iteration %d: %s", desc, it, {k: round(v, 4) for k, v in record.items()})
    if bar is not None:
        bar.close()
    return records


def _infer_in_features(td: TensorDictBase, obs_keys: Sequence[NestedKey]) -> int:
    total = 0
    for key in obs_keys:
        x = td.get(key, None)
        if x is None:
            raise KeyError(f"the trajectories have no {key!r} entry (obs_keys).")
        total += x.shape[td.ndim :].numel() if x.ndim > td.ndim else 1
    return total


def discover_options(
    trajectories: TensorDictBase | Sequence[TensorDictBase] | ReplayBuffer,
    num_options: int,
    *,
    options: TensorDictModuleBase | None = None,
    meta_control: str | TensorDictModuleBase = "uniform",
    num_actions: int | None = None,
    action_space: str = "categorical",
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] = 2,
    activation: str = "tanh",
    architecture: str = "separate",
    init: str = "random",
    num_iterations: int = 500,
    batch_size: int | None = None,
    optimizer: torch.optim.Optimizer | Callable[..., torch.optim.Optimizer] | None = None,
    lr: float = 1e-2,
    device: torch.device | str | None = None,
    seed: int | None = None,
    progress: bool = True,
    trajectory_key: NestedKey = ("collector", "traj_ids"),
    return_info: bool = False,
    log_every: int = 50,
) -> TensorDictModuleBase | DiscoveryResult:
    """Discovers ``num_options`` options from demonstration trajectories with DDO.

    Hierarchical behavioural cloning by Expectation-Gradient (Fox, Krishnan, Stoica, Goldberg, "Multi-Level
    Discovery of Deep Options", 2017, section 4): the options' control policies, termination conditions and
    (optionally) meta-control policy are trained jointly to maximise the likelihood of the demonstrations, on
    minibatches of trajectories, with :class:`~torchrl_options.DDOLoss`.

    Args:
        trajectories: a ``[B, T]`` tensordict with ``("collector", "mask")`` (missing: all valid), one ``[T]``
            trajectory, a list of ``[T_i]`` trajectories, or a TorchRL replay buffer whose ``sample()`` returns
            flat slices of trajectories (e.g. with a ``SliceSampler``), split by :func:`as_trajectory_batch`.
        num_options (int): K.

    Keyword Args:
        options (TensorDictModuleBase, optional): the options to train (any module writing the option entries,
            modified in place). Default: an :class:`OptionsMLP` (or :class:`GaussianOptionsMLP`) built from the data.
        meta_control (str or module): ``"uniform"`` (H1u, default), ``"learned"`` (an :class:`MetaControlMLP`,
            H1s) or a module writing ``meta_logits``.
        num_actions (int, optional): A for discrete actions; default: ``max(action) + 1`` over the data.
        action_space (str): ``"categorical"`` (default) or ``"continuous"``.
        obs_keys (NestedKey or list): observation entries the default modules read. Defaults to ``"observation"``.
        action_key (NestedKey): the action entry. Defaults to ``"action"``.
        num_cells, activation, architecture: for the default modules (the paper's four rooms: 2 tanh units).
        init (str): ``"random"`` (default) or ``"kmeans"`` (pre-clustering of state-action pairs, appendix B).
        num_iterations (int): gradient steps. Defaults to 500.
        batch_size (int, optional): trajectories per minibatch; ``None`` uses all (or the buffer's batch size).
        optimizer: an optimizer instance over the modules' parameters, or a factory called as
            ``optimizer(params, lr=lr)``. Defaults to Adam.
        lr (float): learning rate for the default or factory-made optimizer. Defaults to 1e-2.
        device: where to train. Defaults to the data's device.
        seed (int, optional): seeds module initialisation, minibatch order and clustering.
        progress (bool): show a tqdm progress bar. Defaults to ``True``.
        trajectory_key (NestedKey): trajectory ids used to split replay-buffer samples.
        return_info (bool): return a :class:`DiscoveryResult` (options, meta-control, history).
        log_every (int): log the diagnostics every this many iterations.

    Returns:
        The trained options module, or a :class:`DiscoveryResult` with ``return_info=True``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import discover_options
        >>> B, T = 8, 30
        >>> obs = torch.randn(B, T + 1, 2)
        >>> data = TensorDict({"observation": obs[:, :-1], "action": (obs[:, :-1, 0] > 0).long(),
        ...                    "next": {"observation": obs[:, 1:]}}, [B, T])
        >>> options = discover_options(data, num_options=2, num_iterations=20, seed=0, progress=False)
        >>> options(data[0].clone())["option_logits"].shape
        torch.Size([30, 2, 2])
    """
    if num_options < 1:
        raise ValueError(f"num_options must be positive, got {num_options}.")
    if action_space not in ("categorical", "continuous"):
        raise ValueError(f"action_space must be 'categorical' or 'continuous', got {action_space!r}.")
    obs_keys = [obs_keys] if isinstance(obs_keys, (str, tuple)) else list(obs_keys)
    generator = torch.Generator()
    if seed is not None:
        torch.manual_seed(seed)
        generator.manual_seed(seed)

    buffer = trajectories if isinstance(trajectories, ReplayBuffer) else None
    if buffer is not None:
        data = as_trajectory_batch(buffer.sample(), trajectory_key=trajectory_key)
    else:
        data = as_trajectory_batch(trajectories)
    if device is None:
        device = data.device if data.device is not None else torch.device("cpu")
    device = torch.device(device)
    data = data.to(device)
    mask = data.get(_MASK)

    if options is None:
        in_features = _infer_in_features(data, obs_keys)
        if action_space == "categorical":
            if num_actions is None:
                action = data.get(action_key)
                num_actions = int(action[mask].max()) + 1
                logger.info("num_actions not given: using max(action) + 1 = %d", num_actions)
            options = OptionsMLP(
                in_features, num_actions, num_options, num_cells=num_cells, activation=activation,
                architecture=architecture, in_keys=obs_keys,
            )
        else:
            action_dim = data.get(action_key).shape[-1]
            options = GaussianOptionsMLP(
                in_features, action_dim, num_options, num_cells=num_cells, activation=activation, in_keys=obs_keys
            )
    options = options.to(device)
    if isinstance(meta_control, str):
        if meta_control == "uniform":
            meta_module = None
        elif meta_control == "learned":
            meta_module = MetaControlMLP(
                _infer_in_features(data, obs_keys), num_options, num_cells=num_cells, activation=activation,
                in_keys=obs_keys,
            ).to(device)
        else:
            raise ValueError(f"meta_control must be 'uniform', 'learned' or a module, got {meta_control!r}.")
    else:
        meta_module = meta_control.to(device)

    loss_module = DDOLoss(options, meta_module, action_space=action_space)
    loss_module.set_keys(action=action_key)

    if init == "kmeans":
        pretrain_on_clusters(
            options, data, mask, num_options=num_options, action_key=action_key, action_space=action_space,
            num_actions=num_actions, meta_control=meta_module, lr=lr, generator=generator,
        )
    elif init != "random":
        raise ValueError(f"init must be 'random' or 'kmeans', got {init!r}.")

    params = list(loss_module.parameters())
    if isinstance(optimizer, torch.optim.Optimizer):
        opt = optimizer
    elif optimizer is None:
        opt = torch.optim.Adam(params, lr=lr)
    else:
        opt = optimizer(params, lr=lr)

    def next_batch(it: int) -> TensorDictBase:
        if buffer is not None and it > 0:
            return as_trajectory_batch(buffer.sample(), trajectory_key=trajectory_key).to(device)
        return data if buffer is not None else minibatch(data, batch_size, generator)

    history = fit_ddo(loss_module, opt, next_batch, num_iterations, desc="DDO", progress=progress, log_every=log_every)
    if return_info:
        return DiscoveryResult(options=options, meta_control=meta_module, history=history)
    return options
