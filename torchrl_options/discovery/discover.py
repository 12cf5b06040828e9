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

from torchrl_options.checkpoints import restores_global_rng
from torchrl_options.discovery._validation import check_discover_options, check_positive_number, check_trajectories
from torchrl_options.discovery.diagnostics import option_diagnostics, restart_disagreement
from torchrl_options.discovery.initialization import pretrain_on_clusters, pretrain_on_segments
from torchrl_options.discovery.split_merge import check_split_merge_options, split_merge as run_split_merge
from torchrl_options.discovery.tabulated import TabulatedDDO
from torchrl_options.discovery.width import AUTO_WIDTHS, held_out_log_likelihood, select_width
from torchrl_options.modules import GaussianOptionsMLP, MetaControlMLP, OptionsMLP
from torchrl_options.modules._features import hidden_sizes
from torchrl_options.objectives import DDOLoss

__all__ = [
    "DiscoveryResult",
    "PAPER_SETTINGS",
    "as_trajectory_batch",
    "converged_at",
    "discover_options",
    "fit_ddo",
    "minibatch",
]

logger = logging.getLogger(__name__)

_MASK = ("collector", "mask")

DEFAULT_RESTARTS = 4
"""Starts drawn by :func:`discover_options` when ``restarts`` is left at ``None`` (and fresh modules can be drawn)."""

INITS = ("random", "kmeans", "segments", "auto")
"""The values of ``discover_options(init=...)``; ``"auto"`` (the default) starts fresh modules from segments."""

AUTO_RESTARTS = 6
"""Starts drawn with ``init="auto"`` when ``restarts`` is left at ``None``: of every three, two segment starts
clustered by where the segments end and one clustered by their actions."""

DEFAULT_PATIENCE = 20
"""The stopping rule's window (iterations) of :func:`discover_options` for discrete actions when ``patience`` is
left at ``None``."""

CONTINUOUS_PATIENCE = 100
"""The stopping rule's window for continuous actions (Gaussian options) when ``patience`` is left at ``None``: with
a window of 20 the planted suite's Gaussian fits stopped on a pause of the likelihood, up to 0.015 nats per step
below the truth's, and climbed past it when trained on."""

PAPER_SETTINGS: dict = dict(
    num_cells=2, termination_cells=2, activation="tanh", num_iterations=500, m_steps=1, lr=1e-2, restarts=1, tol=None,
    init="random",
)
"""The settings of the paper's four-rooms experiment (one hidden layer of 2 tanh units, plain Expectation-Gradient,
one start), as ``discover_options`` keyword arguments: ``discover_options(data, K, **PAPER_SETTINGS)``. The
GridWorld recipes use them; the defaults of :func:`discover_options` are chosen on the planted suite instead."""


@dataclass
class DiscoveryResult:
    """What :func:`discover_options` returns with ``return_info=True``.

    Attributes:
        options: the trained options module.
        meta_control: the trained meta-control module, ``None`` for the uniform one.
        history (list of dict): per iteration, ``loss_ddo`` and the diagnostics of :class:`DDOLoss` (at the
            parameters before the iteration's steps).
        converged (bool or None): with ``tol``, whether the stopping rule ended training before
            ``num_iterations``; ``None`` without ``tol``.
        restart_log_likelihoods (list of float): with ``restarts > 1``, each start's log-likelihood per step after
            its ``restart_iterations`` (the best one was kept); empty otherwise.
        option_usage (list of float): per option, the posterior share of the demonstrations' steps it is active
            at (:func:`~torchrl_options.discovery.option_diagnostics`).
        duplicate_options (list of tuple): pairs of options that act and terminate alike on the demonstrations.
        warnings (list of str): signs the run may be stuck in a local optimum (an unused option, duplicates, starts
            that disagree), also logged as warnings.
        num_cells (int or None): with ``num_cells="auto"``, the hidden-layer width chosen; ``None`` otherwise.
        width_log_likelihoods (dict): with ``num_cells="auto"``, each candidate width's log-likelihood per step on
            the held-out trajectories (:func:`~torchrl_options.discovery.width.select_width`); empty otherwise.
        split_merge_moves (list of dict): with ``split_merge > 0``, one dict per proposed move
            (:func:`~torchrl_options.discovery.split_merge.split_merge`): ``move``, ``victim``, ``donor``,
            ``log_likelihood_before`` and ``log_likelihood_after`` (training log-likelihood per step of the current
            model and of the re-fit) and ``accepted``; empty otherwise. ``options``, ``history`` (the main fit's
            iterations followed by those of each accepted re-fit), ``converged``, ``option_usage``,
            ``duplicate_options`` and ``warnings`` then describe the final model.
    """

    options: TensorDictModuleBase
    meta_control: TensorDictModuleBase | None
    history: list[dict] = field(default_factory=list)
    converged: bool | None = None
    restart_log_likelihoods: list[float] = field(default_factory=list)
    option_usage: list[float] = field(default_factory=list)
    duplicate_options: list[tuple[int, int]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    num_cells: int | None = None
    width_log_likelihoods: dict[int, float] = field(default_factory=dict)
    split_merge_moves: list[dict] = field(default_factory=list)

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
    check_trajectories(trajectories, trajectory_key=trajectory_key, mask_key=mask_key)
    if isinstance(trajectories, TensorDictBase):
        td = trajectories
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


def minibatch_rows(num_rows: int, batch_size: int | None, generator: torch.Generator) -> torch.Tensor | None:
    """The rows of a minibatch: ``batch_size`` of ``num_rows`` drawn without replacement, ``None`` for all rows."""
    if batch_size is None or batch_size >= num_rows:
        return None
    return torch.randperm(num_rows, generator=generator)[:batch_size]


def minibatch(data: TensorDictBase, batch_size: int | None, generator: torch.Generator) -> TensorDictBase:
    """``batch_size`` trajectories drawn without replacement (all of them when ``batch_size`` is ``None``)."""
    rows = minibatch_rows(data.batch_size[0], batch_size, generator)
    return data if rows is None else data[rows.to(data.device)]


def converged_at(values: Sequence[float], tol: float, patience: int) -> int | None:
    """The first iteration at which a maximised quantity stopped improving: ``tol`` over ``patience`` iterations.

    Iteration ``i >= patience`` is the convergence point when the best value up to ``i`` exceeds the best value up
    to ``i - patience`` by less than ``tol``. This is the stopping rule of :func:`fit_ddo` (on the log-likelihood per
    step, in nats): with full-batch training the log-likelihood rises monotonically (up to optimiser noise), so it
    reads "less than ``tol`` nats per step gained over the last ``patience`` iterations".

    Args:
        values (sequence of float): the quantity at each iteration (NaN counts as no improvement).
        tol (float): the smallest gain that counts as progress, ``>= 0``.
        patience (int): the window, ``>= 1``.

    Returns:
        The iteration index, or ``None`` if the values never stopped improving.

    Examples:
        >>> converged_at([-3.0, -2.0, -1.5, -1.4995, -1.4993, -1.4992], tol=1e-3, patience=2)
        4
        >>> converged_at([-3.0, -2.0, -1.0], tol=1e-3, patience=2) is None
        True
    """
    _check_tol(tol, patience)
    best = []
    running = float("-inf")
    for i, x in enumerate(values):
        if x == x and x > running:
            running = float(x)
        best.append(running)
        if i >= patience and not best[i] - best[i - patience] >= tol:
            return i
    return None


def _check_tol(tol: float | None, patience: int) -> None:
    if tol is not None and (not isinstance(tol, (int, float)) or isinstance(tol, bool) or not tol >= 0):
        raise ValueError(f"tol must be None or a number >= 0 (nats per step), got {tol!r}.")
    if not isinstance(patience, int) or isinstance(patience, bool) or patience < 1:
        raise ValueError(f"patience must be a positive int (iterations), got {patience!r}.")


def _check_split_merge(
    split_merge: int,
    split_merge_iterations: int,
    num_options: int,
    options: TensorDictModuleBase | None,
    meta_control: str | TensorDictModuleBase,
    architecture: str,
    optimizer: object,
    trajectories: object,
) -> None:
    """Refuses ``split_merge`` settings :func:`discover_options` cannot honour, before any training."""
    if not isinstance(split_merge, int) or isinstance(split_merge, bool):
        raise TypeError(f"split_merge must be an int >= 0 (the number of moves), got {split_merge!r}.")
    if split_merge < 0:
        raise ValueError(f"split_merge must be an int >= 0 (the number of moves), got {split_merge}.")
    if (
        not isinstance(split_merge_iterations, int)
        or isinstance(split_merge_iterations, bool)
        or split_merge_iterations < 1
    ):
        raise ValueError(f"split_merge_iterations must be an int >= 1, got {split_merge_iterations!r}.")
    if not split_merge:
        return
    if num_options < 2:
        raise ValueError(
            f"split_merge copies one option into another's slot: it needs num_options >= 2, got {num_options}."
        )
    if not (isinstance(meta_control, str) and meta_control == "uniform"):
        raise ValueError(
            "split_merge supports only meta_control='uniform' (a learned meta-control's choice of the copied option "
            f"is not copied), got meta_control={meta_control!r}."
        )
    if options is None and architecture != "separate":
        raise ValueError(
            "split_merge copies one option's own parameters into another's: it needs architecture='separate' "
            f"(no parameters shared between options), got architecture={architecture!r}."
        )
    if options is not None:
        check_split_merge_options(options, num_options)
    if isinstance(optimizer, torch.optim.Optimizer):
        raise ValueError(
            "split_merge re-trains each move with a fresh optimizer: give an optimizer factory (or None), not an "
            f"optimizer instance, got {type(optimizer).__name__}."
        )
    if isinstance(trajectories, ReplayBuffer):
        raise ValueError(
            "split_merge compares the training log-likelihood of the whole data before and after each move: give "
            "the trajectories as tensordicts, not a replay buffer."
        )


def _check_m_steps(m_steps: int, name: str = "m_steps") -> None:
    if not isinstance(m_steps, int) or isinstance(m_steps, bool) or m_steps < 1:
        raise ValueError(f"{name} must be a positive int (G-steps per E-step), got {m_steps!r}.")


EStep = Callable[[TensorDictBase], "tuple[dict, Callable[[], torch.Tensor]]"]


def fit_ddo(
    loss_module: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    next_batch: Callable[[int], TensorDictBase],
    num_iterations: int,
    *,
    e_step: EStep | None = None,
    m_steps: int = 1,
    tol: float | None = None,
    patience: int = 20,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
    desc: str = "DDO",
    progress: bool = True,
    log_every: int = 50,
    set_diagnostics: Callable[[bool], None] | None = None,
    keep_best: bool = False,
) -> list[dict]:
    """The gradient loop of discovery, one- or multi-level: ``num_iterations`` E-steps on ``next_batch(it)``.

    Without ``e_step``, an iteration is one Expectation-Gradient step: ``loss_module(batch)["loss_ddo"]`` is
    back-propagated and ``optimizer`` steps once. With ``e_step``, ``e_step(batch)`` returns ``(record,
    objective)``: the loss module's outputs at the current parameters and a closure whose value has the same
    gradient there (the negative expected complete-data log-likelihood, see
    :class:`~torchrl_options.discovery.TabulatedDDO`); ``optimizer`` then steps ``m_steps`` times on
    ``objective()`` (``m_steps > 1``: a generalised EM, several G-steps per E-step).

    Args:
        loss_module (nn.Module): writes ``loss_ddo`` and ``log_likelihood_per_step`` (used without ``e_step``).
        optimizer (torch.optim.Optimizer): over the trained parameters; stepped as given (its learning rate, and
            any scheduler the caller attached, are the caller's).
        next_batch (callable): ``next_batch(it)``, the ``[B, T]`` batch of iteration ``it``.
        num_iterations (int): the most iterations (E-steps).

    Keyword Args:
        e_step (callable, optional): see above.
        m_steps (int): optimizer steps per E-step; more than 1 needs ``e_step``. Defaults to 1.
        tol (float, optional): stop early once the log-likelihood per step has gained less than ``tol`` nats over
            the last ``patience`` iterations (:func:`converged_at`). ``None`` (default): run all iterations.
        patience (int): the window of the stopping rule, in iterations. Defaults to 20.
        scheduler (LRScheduler, optional): a learning-rate scheduler of ``optimizer``, stepped once per iteration
            (after its ``m_steps`` optimizer steps).
        desc (str): progress-bar and log label.
        progress (bool): show a tqdm progress bar.
        log_every (int): log the diagnostics every this many iterations (0: never).
        set_diagnostics (callable, optional): told before each step whether this one is logged (a loss whose full
            diagnostics cost extra can skip them otherwise).
        keep_best (bool): leave ``loss_module`` at the parameters of the iteration with the highest recorded
            log-likelihood per step (early stopping's "restore the best weights"; the last steps are not evaluated,
            and a generalised EM with several Adam steps per E-step is not monotone). Meant for full-batch training,
            where every record is the likelihood of the same data. Defaults to ``False``: the parameters after the
            last step.

    Returns:
        Per iteration, the loss module's outputs as floats (at the parameters before that iteration's steps).

    Raises:
        ValueError: naming the argument, for ``m_steps`` < 1 (or > 1 without ``e_step``), ``tol`` < 0 or
            ``patience`` < 1.

    Examples:
        >>> import torch
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(8, 50)
        >>> loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
        >>> opt = torch.optim.Adam(loss.parameters(), lr=0.05)
        >>> records = fit_ddo(loss, opt, lambda it: data, 500, tol=1e-3, patience=10, progress=False)
        >>> len(records) < 500, records[-1]["log_likelihood_per_step"] > records[0]["log_likelihood_per_step"]
        (True, True)
    """
    _check_m_steps(m_steps)
    _check_tol(tol, patience)
    if m_steps > 1 and e_step is None:
        raise ValueError(f"m_steps={m_steps} needs an e_step (several G-steps reuse one E-step's posterior).")
    records: list[dict] = []
    best: list[float] = []
    best_state, best_value = None, float("-inf")
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
        if e_step is None:
            out = loss_module(batch)
        else:
            out, objective = e_step(batch)
        if keep_best:
            value = float(out["log_likelihood_per_step"])
            if value > best_value:  # the parameters this record was computed at, before this iteration's steps
                best_value = value
                best_state = {k: v.detach().clone() for k, v in loss_module.state_dict().items()}
        if e_step is None:
            optimizer.zero_grad()
            out["loss_ddo"].backward()
            optimizer.step()
        else:
            for _ in range(m_steps):
                optimizer.zero_grad()
                objective().backward()
                optimizer.step()
        if scheduler is not None:
            scheduler.step()
        record = {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in out.items()}
        records.append(record)
        if bar is not None:
            postfix = {"ll_step": f"{record['log_likelihood_per_step']:.4f}"}
            if "option_duration" in record:
                postfix["dur"] = f"{record['option_duration']:.1f}"
            bar.set_postfix(postfix)
        if full:
            logger.info("%s iteration %d: %s", desc, it, {k: round(v, 4) for k, v in record.items()})
        if tol is not None:
            x = record["log_likelihood_per_step"]
            prev = best[-1] if best else float("-inf")
            best.append(x if x == x and x > prev else prev)
            if it >= patience and not best[it] - best[it - patience] >= tol:
                logger.info(
                    "%s converged at iteration %d: log-likelihood per step %.4f, gained %.2e < tol=%g over the last %d",
                    desc, it, x, best[it] - best[it - patience], tol, patience,
                )
                break
    if bar is not None:
        bar.close()
    if best_state is not None:
        loss_module.load_state_dict(best_state)
    return records


def _infer_in_features(td: TensorDictBase, obs_keys: Sequence[NestedKey]) -> int:
    total = 0
    for key in obs_keys:
        x = td.get(key, None)
        if x is None:
            raise KeyError(f"the trajectories have no {key!r} entry (obs_keys).")
        total += x.shape[td.ndim :].numel() if x.ndim > td.ndim else 1
    return total


def _check_init_scale(init_scale: float | None, action_space: str) -> None:
    if init_scale is None:
        return
    if action_space != "continuous":
        raise ValueError(
            f"init_scale sets the starting standard deviation of Gaussian options: it needs "
            f"action_space='continuous', got action_space={action_space!r} with init_scale={init_scale!r}."
        )
    check_positive_number(init_scale, "init_scale")


def default_options(
    data: TensorDictBase,
    num_options: int,
    *,
    action_space: str = "categorical",
    num_actions: int | None = None,
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] = 8,
    termination_cells: int | Sequence[int] | None = None,
    activation: str = "tanh",
    architecture: str = "separate",
    init_scale: float | None = None,
) -> TensorDictModuleBase:
    """The fresh options :func:`discover_options` trains when none are given (weights from the global RNG).

    Discrete actions get an :class:`OptionsMLP`; continuous ones a :class:`GaussianOptionsMLP` whose options all
    start at the demonstrations' own action spread (the mean per-dimension standard deviation of the valid
    actions, clipped to ``[0.01, 1]``) unless ``init_scale`` is given: a start at 1.0 can dwarf the spread and
    leave every option alike, a symmetric start the likelihood cannot leave. Unless ``termination_cells`` is given, a Gaussian option's
    termination network has two hidden layers of twice the widest of ``num_cells``: one layer of tanh units
    draws half-planes, and a termination that fires within a region of a continuous state space (the planted
    suite's Gaussian options stop near their goal) is their intersection, which a second layer forms and one layer
    approaches only slowly (measured in ``docs/experiments/planted_suite.md``).

    Args:
        data (TensorDictBase): ``[B, T]`` trajectories with the ``("collector", "mask")`` of valid steps.
        num_options (int): K.

    Keyword Args:
        action_space (str): ``"categorical"`` (default) or ``"continuous"``.
        num_actions (int, optional): A, for discrete actions. Defaults to ``max(action) + 1`` over valid steps.
        obs_keys, action_key, num_cells, termination_cells, activation, architecture, init_scale: as in
            :func:`discover_options`.

    Examples:
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(num_trajectories=4, length=10, seed=0)
        >>> type(default_options(data, 2)).__name__
        'OptionsMLP'
    """
    if action_space not in ("categorical", "continuous"):
        raise ValueError(f"action_space must be 'categorical' or 'continuous', got {action_space!r}.")
    _check_init_scale(init_scale, action_space)
    obs_keys = [obs_keys] if isinstance(obs_keys, (str, tuple)) else list(obs_keys)
    mask = data.get(_MASK) if _MASK in data.keys(include_nested=True) else torch.ones(data.batch_size, dtype=torch.bool)
    in_features = _infer_in_features(data, obs_keys)
    if action_space == "categorical":
        if num_actions is None:
            num_actions = int(data.get(action_key)[mask].max()) + 1
        return OptionsMLP(
            in_features, num_actions, num_options, num_cells=num_cells, termination_cells=termination_cells,
            activation=activation, architecture=architecture, in_keys=obs_keys,
        )
    if termination_cells is None:
        width = 2 * max(hidden_sizes(num_cells))
        termination_cells = [width, width]
    actions = data.get(action_key)[mask]
    action_dim = actions.shape[-1]
    if init_scale is None:
        spread = float(actions.float().std(0).mean()) if actions.shape[0] > 1 else 1.0
        init_scale = min(max(spread, 1e-2), 1.0) if spread == spread else 1.0
    return GaussianOptionsMLP(
        in_features, action_dim, num_options, num_cells=num_cells, termination_cells=termination_cells,
        activation=activation, in_keys=obs_keys, init_scale=init_scale, min_scale=min(1e-3, init_scale / 10),
    )


@restores_global_rng
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
    num_cells: int | Sequence[int] = 8,
    termination_cells: int | Sequence[int] | None = None,
    activation: str = "tanh",
    architecture: str = "separate",
    init_scale: float | None = None,
    init: str = "auto",
    num_iterations: int = 1000,
    m_steps: int = 5,
    tol: float | None = 1e-4,
    patience: int | None = None,
    restarts: int | None = None,
    restart_iterations: int = 40,
    batch_size: int | None = None,
    optimizer: torch.optim.Optimizer | Callable[..., torch.optim.Optimizer] | None = None,
    lr: float = 0.03,
    lr_scheduler: Callable[[torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler] | None = None,
    device: torch.device | str | None = None,
    seed: int | None = None,
    progress: bool = True,
    trajectory_key: NestedKey = ("collector", "traj_ids"),
    return_info: bool = False,
    log_every: int = 50,
    desc: str = "DDO",
    split_merge: int = 0,
    split_merge_iterations: int = 300,
) -> TensorDictModuleBase | DiscoveryResult:
    """Discovers ``num_options`` options from demonstration trajectories with DDO.

    Hierarchical behavioural cloning by Expectation-Gradient (Fox, Krishnan, Stoica, Goldberg, "Multi-Level
    Discovery of Deep Options", 2017, section 4): the options' control policies, termination conditions and
    (optionally) meta-control policy are trained jointly to maximise the likelihood of the demonstrations, on
    minibatches of trajectories, under the model of :class:`~torchrl_options.DDOLoss`.

    Each iteration is an E-step (the exact posterior of the batch, :func:`~torchrl_options.forward_backward`)
    followed by ``m_steps`` optimizer steps (G-steps) on the expected complete-data log-likelihood, whose gradient
    at the E-step's parameters is the gradient of the log-likelihood: ``m_steps=1`` is the paper's
    Expectation-Gradient, ``m_steps > 1`` (default 5) a generalised EM that gets more out of each (costly) E-step. The networks
    are evaluated once per distinct state and state-action pair of the batch (:class:`TabulatedDDO`), which makes
    an iteration much cheaper when states repeat (grid worlds); results equal :class:`~torchrl_options.DDOLoss`'s
    to float rounding.

    On the paper's four rooms (50 x 1000 steps, K = 4, 2 tanh units; 1851 distinct states), ``m_steps=10,
    lr=0.1, tol=1e-3, patience=20`` converges in about 190 iterations, 25 s of CPU time on one core, where plain
    Expectation-Gradient (``m_steps=1``) is still improving after 400 (``benchmarks/bench_discovery.py``).

    The defaults were chosen on a suite of planted problems whose truth is known
    (:data:`~torchrl_options.testing.PLANTED_SUITE`, ``benchmarks/bench_planted_suite.py``): 8 tanh units, 5 G-steps
    per E-step at learning rate 0.03, 6 segment starts (``init="auto"``) of 40 iterations selected by likelihood,
    then up to 1000 iterations with the stopping rule ``tol=1e-4`` (over 20 iterations, 100 for Gaussian options),
    ending at the best iteration. Wider networks fit small data sets better than the truth does with other labels;
    the paper's 2 units, one start and plain Expectation-Gradient stop in local optima on several problems, and
    random starts miss the optimum next to the truth when options share moves.
    :data:`PAPER_SETTINGS` gives the paper's settings (``discover_options(data, K, **PAPER_SETTINGS)``). The result
    (``return_info=True``) reports each start's likelihood, each option's usage and duplicated options, and a
    warning is logged when they suggest a local optimum (:func:`~torchrl_options.discovery.option_diagnostics`).

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
        num_cells, activation, architecture: for the default modules. Defaults: 8 tanh units, one hidden layer,
            separate networks per option (the paper's four rooms: 2 tanh units). ``num_cells="auto"`` chooses the
            width among :data:`~torchrl_options.discovery.width.AUTO_WIDTHS` (4 and 8) by the log-likelihood of
            20% of the trajectories held out while each width is fitted on the rest (with the restarts), then
            trains the chosen fit on all the trajectories; about twice the CPU time of one width on the planted
            suite. The result's ``num_cells`` and ``width_log_likelihoods`` say what was chosen and why, and its
            ``history`` holds the chosen width's iterations on the training share followed by those on all the
            trajectories.
        termination_cells (int or sequence of int, optional): hidden sizes of the default modules' termination
            networks. Defaults to ``num_cells`` for discrete actions and, for continuous ones, to two layers of twice
            the widest of ``num_cells`` (``[16, 16]`` with the default width; see :func:`default_options`).
        init_scale (float, optional): for continuous actions, the standard deviation every fresh Gaussian option
            starts at. Defaults to the demonstrations' action spread (see :func:`default_options`); ``1.0`` was the
            default until 2026-12-05.
        init (str): how each start's options are drawn before DDO: ``"random"``, ``"kmeans"`` (pre-clustering of
            state-action pairs, appendix B), ``"segments"`` (the demonstrations cut where the actions change regime,
            the segments clustered by where they end, each option cloned from a cluster:
            :func:`~torchrl_options.discovery.pretrain_on_segments`; every start draws its own clusters), or
            ``"auto"`` (default): for fresh modules given tensordicts, segment starts, two of every three clustered
            by where the segments end and the third by their actions (``features="actions"``), :data:`AUTO_RESTARTS`
            of them unless ``restarts`` is set; ``"random"`` (the modules as they come) when ``options`` are given
            or the trajectories come from a replay buffer.
        num_iterations (int): the most iterations (E-steps). Defaults to 1000 (the stopping rule usually ends
            training sooner).
        m_steps (int): optimizer steps per E-step (G-steps); 1 is the paper's Expectation-Gradient. Defaults to 5.
        tol (float, optional): stopping rule: stop once the log-likelihood per step has gained less than ``tol``
            nats over the last ``patience`` iterations (see :func:`converged_at`; meant for full-batch training,
            minibatch estimates are noisy). Defaults to 1e-4; ``None`` runs all ``num_iterations``. With ``tol`` on
            the full batch, the last training (the chosen start's, continued) ends at its iteration with the
            highest log-likelihood per step (``fit_ddo(keep_best=True)``), not at its last one; a start that meets
            the stopping rule within ``restart_iterations`` is returned as it stopped.
        patience (int, optional): the stopping rule's window, in iterations. Defaults to 20 for discrete actions and
            to :data:`CONTINUOUS_PATIENCE` (100) for continuous ones: a Gaussian fit's likelihood pauses for tens of
            iterations and then climbs again (measured in ``docs/experiments/planted_suite.md``).
        restarts (int): starts from ``restarts`` initialisations (as ``init`` draws them), each trained for
            at most ``restart_iterations`` iterations; the one with the highest training log-likelihood (a
            label-free model selection) is then trained for the rest of ``num_iterations``. The likelihood has
            local optima (two options merged, one unused), which restarts avoid. More than 1 needs the default
            ``options`` and meta-control and an optimizer factory (not an instance). ``None`` (default): n starts
            when fresh modules can be drawn and ``num_iterations >= n * restart_iterations``, else 1, with n
            :data:`AUTO_RESTARTS` (6) for ``init="auto"`` and :data:`DEFAULT_RESTARTS` (4) otherwise.
        restart_iterations (int): the iterations given to each start when ``restarts > 1``. Defaults to 40.
        batch_size (int, optional): trajectories per minibatch; ``None`` uses all (or the buffer's batch size).
        optimizer: an optimizer instance over the modules' parameters, or a factory called as
            ``optimizer(params, lr=lr)``. Defaults to Adam (``fused=True`` on CPU and CUDA, else ``foreach=True``).
        lr (float): learning rate for the default or factory-made optimizer. Defaults to 0.03.
        lr_scheduler (callable, optional): ``lr_scheduler(optimizer)`` makes a learning-rate scheduler of the
            optimizer (given or made), stepped once per iteration, e.g.
            ``lambda opt: torch.optim.lr_scheduler.CosineAnnealingLR(opt, num_iterations)``. Defaults to none.
        device: where to train. Defaults to the data's device.
        seed (int, optional): seeds module initialisation, minibatch order and clustering; the global random
            states are restored on return, so the caller's random numbers do not change.
        progress (bool): show a tqdm progress bar. Defaults to ``True``.
        trajectory_key (NestedKey): trajectory ids used to split replay-buffer samples.
        return_info (bool): return a :class:`DiscoveryResult` (options, meta-control, history).
        log_every (int): log the diagnostics every this many iterations.
        desc (str): the progress bar's label, e.g. which run it fits (``"DDO supervised seed 0, K=4, uniform"``).
            Defaults to ``"DDO"``.
        split_merge (int): after the main fit, propose this many split-and-merge moves
            (:mod:`~torchrl_options.discovery.split_merge`; Ueda et al., 2000): a little-used or duplicated option
            is overwritten with a noisy copy of a busy one, the model re-trained for ``split_merge_iterations``
            iterations from there (one start, the same ``lr``, ``m_steps``, ``tol``, ``patience``, ``batch_size``,
            optimizer factory and scheduler), and the move kept only if the training log-likelihood per step rises
            by more than 1e-4; so the final likelihood is never below the main fit's. Each move costs up to
            ``split_merge_iterations`` iterations. It needs options whose every parameter has the option index as
            leading dimension (the default modules with ``architecture="separate"``), ``meta_control="uniform"``,
            ``num_options >= 2``, trajectories given as tensordicts (not a replay buffer) and no optimizer
            instance. With ``num_cells="auto"`` the moves follow the final fit on all the trajectories. Defaults
            to 0 (off). On the planted ``landmarks-8`` problem, 8 moves raise the share of correctly labelled
            steps from the main fit's local optimum (``docs/experiments/planted_suite.md``).
        split_merge_iterations (int): the most iterations of each move's re-fit. Defaults to 300.

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
    check_discover_options(trajectories, num_options, options=options, meta_control=meta_control, num_actions=num_actions, action_space=action_space, obs_keys=obs_keys, action_key=action_key)  # fmt: skip
    if num_options < 1:
        raise ValueError(f"num_options must be positive, got {num_options}.")
    if not isinstance(num_iterations, int) or isinstance(num_iterations, bool) or num_iterations < 0:
        raise ValueError(f"num_iterations must be an int >= 0, got {num_iterations!r}.")
    _check_m_steps(m_steps)
    if patience is None:
        patience = CONTINUOUS_PATIENCE if action_space == "continuous" else DEFAULT_PATIENCE
    _check_tol(tol, patience)
    _check_init_scale(init_scale, action_space)
    if isinstance(num_cells, str) and num_cells != "auto":
        raise ValueError(f"num_cells must be an int, a sequence of ints or 'auto', got {num_cells!r}.")
    _check_split_merge(split_merge, split_merge_iterations, num_options, options, meta_control, architecture,
                       optimizer, trajectories)  # fmt: skip
    fresh_modules = options is None and not isinstance(optimizer, torch.optim.Optimizer) and isinstance(meta_control, str)
    if restarts is None:
        # several short starts are the default whenever fresh modules can be drawn for each; a user's own modules
        # (or optimizer instance) are trained once
        default_starts = AUTO_RESTARTS if init == "auto" else DEFAULT_RESTARTS
        restarts = default_starts if fresh_modules and num_iterations >= default_starts * restart_iterations else 1
    if not isinstance(restarts, int) or isinstance(restarts, bool) or restarts < 1:
        raise ValueError(f"restarts must be a positive int (or None for the default), got {restarts!r}.")
    if restarts > 1:
        if not isinstance(restart_iterations, int) or not 1 <= restart_iterations <= num_iterations:
            raise ValueError(
                f"restart_iterations must be an int in [1, num_iterations={num_iterations}] when restarts > 1, got "
                f"{restart_iterations!r}."
            )
        if not fresh_modules:
            raise ValueError(
                f"restarts={restarts} draws fresh modules for each start: it needs options=None, meta_control "
                "'uniform' or 'learned', and an optimizer factory rather than an optimizer instance."
            )
    if lr_scheduler is not None and not callable(lr_scheduler):
        raise ValueError(f"lr_scheduler must be a callable making a scheduler from the optimizer, got {lr_scheduler!r}.")
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

    user_options = options
    if options is None and action_space == "categorical" and num_actions is None:
        num_actions = int(data.get(action_key)[mask].max()) + 1
        logger.info("num_actions not given: using max(action) + 1 = %d", num_actions)
    if init not in INITS:
        raise ValueError(f"init must be one of {', '.join(map(repr, INITS))}, got {init!r}.")
    if isinstance(meta_control, str) and meta_control not in ("uniform", "learned"):
        raise ValueError(f"meta_control must be 'uniform', 'learned' or a module, got {meta_control!r}.")
    if isinstance(num_cells, str):
        if not fresh_modules or buffer is not None or data.batch_size[0] < 5:
            raise ValueError(
                "num_cells='auto' fits fresh default modules of each width in AUTO_WIDTHS on 80% of the trajectories "
                "and keeps the width with the best likelihood on the rest: it needs options=None, meta_control "
                "'uniform' or 'learned', no optimizer instance, and at least 5 trajectories given as tensordicts "
                f"(not a replay buffer); got {data.batch_size[0]} trajectories"
                + (" from a replay buffer" if buffer is not None else "") + "."
            )
        common = dict(
            meta_control=meta_control, num_actions=num_actions, action_space=action_space, obs_keys=obs_keys,
            action_key=action_key, termination_cells=termination_cells, activation=activation,
            architecture=architecture, init_scale=init_scale, num_iterations=num_iterations,
            m_steps=m_steps, tol=tol, patience=patience, batch_size=batch_size, optimizer=optimizer, lr=lr,
            lr_scheduler=lr_scheduler, device=device, seed=seed, progress=progress, log_every=log_every,
            return_info=True,
        )  # fmt: skip

        def fit(part: TensorDictBase, width: int) -> DiscoveryResult:
            return discover_options(
                part, num_options, num_cells=width, init=init, restarts=restarts,
                restart_iterations=restart_iterations, desc=f"{desc} {width} units", **common,
            )  # fmt: skip

        width, first, scores = select_width(
            fit, data, widths=AUTO_WIDTHS, generator=generator, action_space=action_space, action_key=action_key
        )
        # the chosen fit continues on all the trajectories (its starts were already selected on the training share)
        common["meta_control"] = first.meta_control if first.meta_control is not None else "uniform"
        final = discover_options(data, num_options, options=first.options, num_cells=width, restarts=1, desc=desc,
                                 split_merge=split_merge, split_merge_iterations=split_merge_iterations,
                                 **common)  # fmt: skip
        final.restart_log_likelihoods = first.restart_log_likelihoods
        disagreement = restart_disagreement(first.restart_log_likelihoods)
        if disagreement and disagreement not in final.warnings:
            final.warnings.append(disagreement)
        final.history = first.history + final.history
        final.num_cells, final.width_log_likelihoods = width, scores
        return final if return_info else final.options

    def start(table: TabulatedDDO | None, start_init: str):
        """Fresh modules (drawn from the global RNG), optionally pre-clustered, with their optimizer."""
        options = user_options
        if options is None:
            options = default_options(
                data, num_options, action_space=action_space, num_actions=num_actions, obs_keys=obs_keys,
                action_key=action_key, num_cells=num_cells, termination_cells=termination_cells, activation=activation,
                architecture=architecture, init_scale=init_scale,
            )
        options = options.to(device)
        if meta_control == "uniform":
            meta_module = None
        elif meta_control == "learned":
            meta_module = MetaControlMLP(
                _infer_in_features(data, obs_keys), num_options, num_cells=num_cells, activation=activation,
                in_keys=obs_keys,
            ).to(device)
        else:
            meta_module = meta_control.to(device)
        loss_module = DDOLoss(options, meta_module, action_space=action_space)
        loss_module.set_keys(action=action_key)
        if start_init == "kmeans":
            pretrain_on_clusters(
                options, data, mask, num_options=num_options, action_key=action_key, action_space=action_space,
                num_actions=num_actions, meta_control=meta_module, lr=lr, generator=generator,
            )
        elif start_init in ("segments", "segments-actions"):
            pretrain_on_segments(
                options, data, mask, num_options=num_options, action_key=action_key, action_space=action_space,
                num_actions=num_actions, meta_control=meta_module, generator=generator,
                features="actions" if start_init == "segments-actions" else "end",
                termination_key=loss_module.tensor_keys.termination_logits,
            )
        params = list(loss_module.parameters())
        if isinstance(optimizer, torch.optim.Optimizer):
            opt = optimizer
        elif optimizer is None:
            # one fused kernel per step where PyTorch has it (CPU, CUDA): the G-steps are many small updates
            fused = all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
            opt = torch.optim.Adam(params, lr=lr, fused=True) if fused else torch.optim.Adam(params, lr=lr, foreach=True)
        else:
            opt = optimizer(params, lr=lr)
        sched = lr_scheduler(opt) if lr_scheduler is not None else None
        if buffer is None:
            table = TabulatedDDO(loss_module, data) if table is None else table.for_loss(loss_module)
        return loss_module, opt, sched, table

    unused_sample = [buffer is not None]  # the buffer sample drawn above, for the first iteration

    # with the stopping rule on the full batch, the fit ends at its best recorded iteration (fit_ddo's keep_best)
    keep_best = tol is not None and buffer is None and batch_size is None

    def train(loss_module, opt, sched, table, n_iterations, desc, final):
        def next_batch(it: int) -> TabulatedDDO:
            if buffer is not None:
                if unused_sample[0]:
                    unused_sample[0] = False
                    return TabulatedDDO(loss_module, data)
                sample = as_trajectory_batch(buffer.sample(), trajectory_key=trajectory_key).to(device)
                return TabulatedDDO(loss_module, sample)
            rows = minibatch_rows(data.batch_size[0], batch_size, generator)
            return table if rows is None else table.subset(rows.to(device))

        return fit_ddo(
            loss_module, opt, next_batch, n_iterations, e_step=TabulatedDDO.e_step, m_steps=m_steps, tol=tol,
            patience=patience, scheduler=sched, desc=desc, progress=progress, log_every=log_every,
            keep_best=keep_best and final,
        )  # fmt: skip

    table = None
    candidates = []
    for r in range(restarts):
        start_init = init
        if init == "auto":  # fresh modules start from segments of the demonstrations; given ones as they are
            start_init = "random" if user_options is not None or buffer is not None else "segments"
            if start_init == "segments" and r % 3 == 2:
                start_init = "segments-actions"
        loss_module, opt, sched, table = start(table, start_init)
        if r == 0 and table is not None:
            logger.info(
                "DDO: %d valid steps, %d distinct states, %d distinct state-action pairs",
                int(table.num_steps), table.num_states, table.num_pairs,
            )
        n_first = restart_iterations if restarts > 1 else num_iterations
        label = f"{desc} start {r + 1}/{restarts}" if restarts > 1 else desc
        records = train(loss_module, opt, sched, table, n_first, label, final=restarts == 1)
        candidates.append((records[-1]["log_likelihood_per_step"] if records else float("-inf"), r, loss_module,
                           opt, sched, table, records))  # fmt: skip
    restart_lls = [c[0] for c in candidates] if restarts > 1 else []
    _, best, loss_module, opt, sched, table, history = max(candidates, key=lambda c: (c[0], -c[1]))
    if restarts > 1:
        logger.info("DDO: start %d of %d has the best log-likelihood per step (%s)", best + 1, restarts,
                    ", ".join(f"{x:.4f}" for x in restart_lls))  # fmt: skip
        lls = [h["log_likelihood_per_step"] for h in history]
        stopped = tol is not None and converged_at(lls, tol, patience) is not None
        if not stopped and num_iterations > len(history):
            history = history + train(loss_module, opt, sched, table, num_iterations - len(history), desc, final=True)
    options, meta_module = loss_module.options, loss_module.meta_control
    if split_merge:
        check_split_merge_options(options, num_options)
    with torch.no_grad():
        diagnostics = option_diagnostics(loss_module.log_probabilities(data))
    disagreement = restart_disagreement(restart_lls)
    warnings = diagnostics.warnings + ([disagreement] if disagreement else [])
    for message in warnings:
        logger.warning("discover_options: %s", message)
    converged = None
    if tol is not None:
        converged = converged_at([h["log_likelihood_per_step"] for h in history], tol, patience) is not None
    result = DiscoveryResult(
        options=options, meta_control=meta_module, history=history, converged=converged,
        restart_log_likelihoods=restart_lls, option_usage=diagnostics.usage,
        duplicate_options=diagnostics.duplicates, warnings=warnings,
    )  # fmt: skip
    if split_merge:
        refits: list[DiscoveryResult] = []

        def refit(candidate: TensorDictModuleBase, move_seed: int) -> DiscoveryResult:
            refits.append(discover_options(
                data, num_options, options=candidate, meta_control="uniform", action_space=action_space,
                obs_keys=obs_keys, action_key=action_key, init="random", num_iterations=split_merge_iterations,
                m_steps=m_steps, tol=tol, patience=patience, restarts=1, batch_size=batch_size, optimizer=optimizer,
                lr=lr, lr_scheduler=lr_scheduler, device=device, seed=move_seed, progress=progress,
                return_info=True, log_every=log_every, desc=f"{desc} split-merge {len(refits) + 1}/{split_merge}",
            ))  # fmt: skip
            return refits[-1]

        def score(fit: DiscoveryResult) -> float:
            return held_out_log_likelihood(fit.options, None, data, action_space=action_space, action_key=action_key)

        moves_generator = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))
        final, moves = run_split_merge(result, refit, score, split_merge, moves_generator)
        accepted = [fit for fit, move in zip(refits, moves) if move["accepted"]]
        if accepted:
            # the final model's diagnostics, with the main fit's starts (and their disagreement) kept
            final.history = history + [h for fit in accepted for h in fit.history]
            final.restart_log_likelihoods = restart_lls
            if disagreement and disagreement not in final.warnings:
                final.warnings.append(disagreement)
            result = final
        result.split_merge_moves = moves
    return result if return_info else result.options
