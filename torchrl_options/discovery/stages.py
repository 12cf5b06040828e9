"""The stages of option discovery, as plain functions that compose: one start (:func:`make_start`,
:func:`train_start`), the choice among starts (:func:`best_of_starts`), a fit of one width (:func:`fit_starts`),
the width choice (:func:`choose_width`), split-and-merge moves (:func:`improve_by_split_merge`), and the whole run
(:func:`run_discovery`), which :func:`~torchrl_options.discover_options` calls after its door.

DDO (Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 4) fits the options by
maximum likelihood with Expectation-Gradient (:func:`~torchrl_options.discovery.fit.fit_ddo`). Every stage takes
the run's checked :class:`~torchrl_options.discovery.batch.DiscoveryBatch`, its
:class:`~torchrl_options.discovery.settings.DiscoverySettings` (with ``patience`` and ``restarts`` resolved,
:func:`~torchrl_options.discovery.networks.resolve_settings`), its
:class:`~torchrl_options.discovery.networks.Networks` and a ``torch.Generator``; none checks the data again.

Examples:
    >>> import torch
    >>> from torchrl_options.discovery.batch import discovery_batch
    >>> from torchrl_options.discovery.networks import Networks, resolve_settings
    >>> from torchrl_options.discovery.settings import DiscoverySettings
    >>> from torchrl_options.testing import planted_corridor_demonstrations
    >>> settings = DiscoverySettings(2, num_iterations=60, restart_iterations=10, progress=False)
    >>> networks = Networks()
    >>> settings = resolve_settings(settings, networks)
    >>> batch = discovery_batch(planted_corridor_demonstrations(8, 30, seed=0), settings)
    >>> with seeded(0) as generator:
    ...     result = run_discovery(batch, settings, networks, generator)
    >>> len(result.restart_log_likelihoods), settings.restarts
    (6, 6)
"""
from __future__ import annotations

import contextlib
import logging
from functools import partial
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_options.checkpoints import rng_state, set_rng_state
from torchrl_options.discovery.batch import DiscoveryBatch, minibatch_rows
from torchrl_options.discovery.diagnostics import option_diagnostics, restart_disagreement
from torchrl_options.discovery.fit import converged_at, fit_ddo
from torchrl_options.discovery.initialization import pretrain_on_clusters, pretrain_on_segments
from torchrl_options.discovery.networks import Networks
from torchrl_options.discovery.settings import DiscoverySettings
from torchrl_options.discovery.split_merge import check_split_merge_options, split_merge
from torchrl_options.discovery.stream_fit import fit_stream
from torchrl_options.discovery.tabulated import TabulatedDDO
from torchrl_options.discovery.usage_floor import UsageFloor
from torchrl_options.discovery.width import AUTO_WIDTHS, held_out_log_likelihood, select_width
from torchrl_options.objectives import DDOLoss

__all__ = [
    "DiscoveryResult",
    "Start",
    "best_of_starts",
    "choose_width",
    "fit_starts",
    "improve_by_split_merge",
    "make_start",
    "run_discovery",
    "seeded",
    "start_strategy",
    "summarize",
    "train_start",
]

logger = logging.getLogger(__name__)

S = TypeVar("S")


@dataclass
class DiscoveryResult:
    """What :func:`~torchrl_options.discover_options` returns with ``return_info=True``.

    Attributes:
        options: the trained options module.
        meta_control: the trained meta-control module, ``None`` for the uniform one.
        history (list of dict): per iteration, ``loss_ddo`` and the diagnostics of :class:`DDOLoss` (at the
            parameters before the iteration's steps). With the stopping rule the returned modules are those of the
            best recorded iteration, which need not be the last one.
        log_likelihood_per_step (float or None): the exact log-likelihood per step of the demonstrations under the
            returned modules (the unpenalised likelihood with ``usage_floor``); ``None`` for trajectories streamed
            from a replay buffer (see :attr:`final_log_likelihood_per_step`).
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
    log_likelihood_per_step: float | None = None

    @property
    def final_log_likelihood_per_step(self) -> float:
        """The last training record's log-likelihood per step (``history[-1]``): the training curve's end. When
        the stopping rule restored an earlier, better iteration it is below the returned modules' own
        :attr:`log_likelihood_per_step`."""
        return self.history[-1]["log_likelihood_per_step"] if self.history else float("nan")


@dataclass
class Start:
    """One start of a fit: its loss module (holding the options and meta-control), optimizer, scheduler and the
    tabulated batch it trains on (``None`` with a replay buffer)."""

    loss_module: torch.nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: Any = None
    table: TabulatedDDO | None = None
    usage_floor: UsageFloor | None = None


@contextlib.contextmanager
def seeded(seed: int | None) -> Iterator[torch.Generator]:
    """A generator for a stage, and the global RNG seeded with ``seed`` for the block, every global random state put
    back after it (as :func:`~torchrl_options.checkpoints.scoped_seed`). ``seed=None``: an unseeded generator, the
    global state left running.

    Examples:
        >>> with seeded(0) as g:
        ...     a = torch.rand(1), torch.rand(1, generator=g)
        >>> with seeded(0) as g:
        ...     b = torch.rand(1), torch.rand(1, generator=g)
        >>> a == b
        True
    """
    generator = torch.Generator()
    if seed is None:
        yield generator
        return
    saved = rng_state()
    try:
        torch.manual_seed(seed)
        generator.manual_seed(seed)
        yield generator
    finally:
        set_rng_state(saved)


def start_strategy(init: str, start: int, *, given_options: bool, from_buffer: bool) -> str:
    """How start number ``start`` draws its options: ``init`` itself, or for ``init="auto"``: ``"random"`` for given
    options or a replay buffer, else segments clustered by where they end, every third one by their actions
    (``"segments-actions"``).

    Examples:
        >>> [start_strategy("auto", r, given_options=False, from_buffer=False) for r in range(3)]
        ['segments', 'segments', 'segments-actions']
    """
    if init != "auto":
        return init
    if given_options or from_buffer:
        return "random"
    return "segments-actions" if start % 3 == 2 else "segments"


def _optimizer(networks: Networks, params: list[torch.Tensor], lr: float) -> torch.optim.Optimizer:
    if isinstance(networks.optimizer, torch.optim.Optimizer):
        return networks.optimizer
    if networks.optimizer is None:
        # one fused kernel per step where PyTorch has it (CPU, CUDA): the G-steps are many small updates
        fused = all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
        return torch.optim.Adam(params, lr=lr, fused=True) if fused else torch.optim.Adam(params, lr=lr, foreach=True)
    return networks.optimizer(params, lr=lr)


def make_start(
    batch: DiscoveryBatch,
    settings: DiscoverySettings,
    networks: Networks,
    strategy: str,
    generator: torch.Generator,
    table: TabulatedDDO | None = None,
    *,
    first: bool = False,
) -> Start:
    """A new start: modules from ``networks`` (fresh ones drawn from the global RNG; the first made by a factory
    checked on the data when ``first``), pre-trained by ``strategy`` (:func:`start_strategy`: ``"kmeans"``,
    ``"segments"``, ``"segments-actions"``; ``"random"``: as they come), their optimizer and scheduler, and the
    tabulated batch (``table`` re-used for the new modules)."""
    device = batch.device
    options = networks.new_options(batch, settings, check=first).to(device)
    meta_module = networks.new_meta_control(batch, settings, check=first)
    meta_module = meta_module.to(device) if meta_module is not None else None
    loss_module = DDOLoss(options, meta_module, action_space=settings.action_space)
    loss_module.set_keys(action=settings.action_key)
    common = dict(num_options=settings.num_options, action_key=settings.action_key,
                  action_space=settings.action_space, num_actions=batch.num_actions, meta_control=meta_module,
                  generator=generator)  # fmt: skip
    if strategy == "kmeans":
        pretrain_on_clusters(options, batch.data, batch.mask, lr=settings.lr, **common)
    elif strategy in ("segments", "segments-actions"):
        pretrain_on_segments(options, batch.data, batch.mask, features="actions" if strategy == "segments-actions" else "end",
                             termination_key=loss_module.tensor_keys.termination_logits, **common)  # fmt: skip
    optimizer = _optimizer(networks, list(loss_module.parameters()), settings.lr)
    scheduler = networks.lr_scheduler(optimizer) if networks.lr_scheduler is not None else None
    if batch.buffer is None:
        table = TabulatedDDO(loss_module, batch.data) if table is None else table.for_loss(loss_module)
    floor = None
    if settings.usage_floor is not None:
        floor = UsageFloor(settings.num_options, settings.usage_floor, device=device)
    return Start(loss_module, optimizer, scheduler, table, floor)


class _Batches:
    """The batch of each iteration: a minibatch of the tabulated trajectories (streamed trajectories are read by
    :func:`~torchrl_options.discovery.stream_fit.fit_stream` itself)."""

    def __init__(self, batch: DiscoveryBatch, settings: DiscoverySettings, generator: torch.Generator) -> None:
        self.batch, self.batch_size, self.generator = batch, settings.batch_size, generator

    def next(self, start: Start) -> TabulatedDDO:
        batch = self.batch
        rows = minibatch_rows(batch.num_trajectories, self.batch_size, self.generator)
        return start.table if rows is None else start.table.subset(rows.to(batch.device))


def train_start(start: Start, settings: DiscoverySettings, batches: _Batches, num_iterations: int, desc: str,
                final: bool) -> list[dict]:  # fmt: skip
    """Trains a start for at most ``num_iterations`` iterations (:func:`~torchrl_options.discovery.fit.fit_ddo`
    with the tabulated E-step, or :func:`~torchrl_options.discovery.stream_fit.fit_stream` on streamed
    trajectories). With the stopping rule on the full batch (or, streamed, on the evaluation set), the ``final``
    training ends at its best recorded iteration (``keep_best``)."""
    batch = batches.batch
    if batch.stream is not None:
        return fit_stream(
            start.loss_module, start.optimizer, batch.stream, batches.generator, num_iterations, m_steps=settings.m_steps,
            tol=settings.tol, patience=settings.patience, scheduler=start.scheduler, desc=desc,
            progress=settings.progress, log_every=settings.log_every, keep_best=settings.tol is not None and final,
            probe=batch.data,
        )  # fmt: skip
    keep_best = settings.tol is not None and batch.buffer is None and settings.batch_size is None
    e_step = TabulatedDDO.e_step if start.usage_floor is None else partial(TabulatedDDO.e_step, usage_floor=start.usage_floor)
    return fit_ddo(
        start.loss_module, start.optimizer, lambda it: batches.next(start), num_iterations, e_step=e_step,
        m_steps=settings.m_steps, tol=settings.tol, patience=settings.patience, scheduler=start.scheduler, desc=desc,
        progress=settings.progress, log_every=settings.log_every, keep_best=keep_best and final,
    )  # fmt: skip


def best_of_starts(
    make: Callable[[int], S],
    train: Callable[[S, int, str, bool], list[dict]],
    *,
    restarts: int,
    restart_iterations: int,
    num_iterations: int,
    tol: float | None,
    patience: int,
    desc: str,
    what: str = "DDO",
) -> tuple[S, list[dict], list[float]]:
    """The choice among starts: ``restarts`` starts (``make(r)``) each trained for ``restart_iterations``
    (``train(start, n, label, final)``), the one with the highest log-likelihood per step kept (ties: the first)
    and trained for the rest of ``num_iterations`` unless the stopping rule already ended it. One start is trained
    for ``num_iterations`` at once. Label-free model selection against the likelihood's local optima (an unused
    option, two merged).

    Returns:
        ``(start, history, restart_log_likelihoods)``: the kept start, its records, and every start's final
        log-likelihood per step (empty for one start).
    """
    candidates = []
    for r in range(restarts):
        start = make(r)
        n_first = restart_iterations if restarts > 1 else num_iterations
        label = f"{desc} start {r + 1}/{restarts}" if restarts > 1 else desc
        records = train(start, n_first, label, restarts == 1)
        candidates.append((records[-1]["log_likelihood_per_step"] if records else float("-inf"), r, start, records))
    restart_lls = [c[0] for c in candidates] if restarts > 1 else []
    _, best, start, history = max(candidates, key=lambda c: (c[0], -c[1]))
    if restarts > 1:
        logger.info("%s: start %d of %d has the best log-likelihood per step (%s)", what, best + 1, restarts,
                    ", ".join(f"{x:.4f}" for x in restart_lls))  # fmt: skip
        lls = [h["log_likelihood_per_step"] for h in history]
        stopped = tol is not None and converged_at(lls, tol, patience) is not None
        if not stopped and num_iterations > len(history):
            history = history + train(start, num_iterations - len(history), desc, True)
    return start, history, restart_lls


def summarize(
    loss_module: torch.nn.Module, data: TensorDictBase, history: list[dict], restart_lls: list[float],
    settings: DiscoverySettings, *, streamed: bool = False,
) -> DiscoveryResult:  # fmt: skip
    """The result of a fit: the trained modules, the stopping rule's verdict, and the label-free diagnostics of the
    options on the demonstrations (usage, duplicates, starts that disagree, the returned modules' log-likelihood;
    ``streamed``: ``data`` is a buffer's evaluation set, whose likelihood is not the demonstrations'), logged as
    warnings."""
    with torch.no_grad():
        diagnostics = option_diagnostics(loss_module.log_probabilities(data))
    disagreement = restart_disagreement(restart_lls)
    warnings = diagnostics.warnings + ([disagreement] if disagreement else [])
    for message in warnings:
        logger.warning("discover_options: %s", message)
    converged = None
    if settings.tol is not None:
        converged = converged_at([h["log_likelihood_per_step"] for h in history], settings.tol, settings.patience) is not None
    return DiscoveryResult(
        options=loss_module.options, meta_control=loss_module.meta_control, history=history, converged=converged,
        restart_log_likelihoods=restart_lls, option_usage=diagnostics.usage, duplicate_options=diagnostics.duplicates,
        warnings=warnings, log_likelihood_per_step=None if streamed else diagnostics.log_likelihood_per_step,
    )  # fmt: skip


def fit_starts(
    batch: DiscoveryBatch, settings: DiscoverySettings, networks: Networks, generator: torch.Generator
) -> DiscoveryResult:
    """A fit of one width: ``settings.restarts`` starts (:func:`start_strategy`, :func:`make_start`), the best one
    kept and trained on (:func:`best_of_starts`), summarised (:func:`summarize`)."""
    batches = _Batches(batch, settings, generator)
    table: TabulatedDDO | None = None  # tabulated once, re-used by every start's modules

    def make(r: int) -> Start:
        nonlocal table
        # streamed trajectories: segment starts on the evaluation set (the door's sample)
        strategy = start_strategy(settings.init, r, given_options=networks.options is not None,
                                  from_buffer=batch.buffer is not None and batch.stream is None)  # fmt: skip
        start = make_start(batch, settings, networks, strategy, generator, table, first=r == 0)
        if r == 0 and start.table is not None:
            logger.info("DDO: %d valid steps, %d distinct states, %d distinct state-action pairs",
                        int(start.table.num_steps), start.table.num_states, start.table.num_pairs)  # fmt: skip
        table = start.table
        return start

    def train(start: Start, n: int, label: str, final: bool) -> list[dict]:
        return train_start(start, settings, batches, n, label, final)

    start, history, restart_lls = best_of_starts(
        make, train, restarts=settings.restarts, restart_iterations=settings.restart_iterations,
        num_iterations=settings.num_iterations, tol=settings.tol, patience=settings.patience, desc=settings.desc,
    )  # fmt: skip
    if settings.split_merge:
        check_split_merge_options(start.loss_module.options, settings.num_options)
    return summarize(start.loss_module, batch.data, history, restart_lls, settings, streamed=batch.buffer is not None)


def improve_by_split_merge(
    result: DiscoveryResult,
    batch: DiscoveryBatch,
    settings: DiscoverySettings,
    networks: Networks,
    generator: torch.Generator,
) -> DiscoveryResult:
    """``settings.split_merge`` split-and-merge moves from ``result`` (:func:`~torchrl_options.discovery.split_merge.
    split_merge`; Ueda et al., 2000): each candidate re-fitted from one start for ``split_merge_iterations``
    iterations under its own seed, kept when the training log-likelihood per step rises. The final result keeps
    the main fit's starts and their disagreement, and its history is the main fit's followed by the accepted
    re-fits'."""
    refits: list[DiscoveryResult] = []
    refit_settings = settings.replace(init="random", num_iterations=settings.split_merge_iterations, restarts=1,
                                      split_merge=0, meta_control="uniform")  # fmt: skip

    def refit(candidate: TensorDictModuleBase, move_seed: int) -> DiscoveryResult:
        desc = f"{settings.desc} split-merge {len(refits) + 1}/{settings.split_merge}"
        with seeded(move_seed) as move_generator:
            refits.append(fit_starts(batch, refit_settings.replace(seed=move_seed, desc=desc),
                                     networks.trained(candidate), move_generator))  # fmt: skip
        return refits[-1]

    def score(fit: DiscoveryResult) -> float:
        return held_out_log_likelihood(fit.options, None, batch.data, action_space=settings.action_space,
                                       action_key=settings.action_key)  # fmt: skip

    moves_generator = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))
    final, moves = split_merge(result, refit, score, settings.split_merge, moves_generator)
    accepted = [fit for fit, move in zip(refits, moves) if move["accepted"]]
    if accepted:
        disagreement = restart_disagreement(result.restart_log_likelihoods)
        final.history = result.history + [h for fit in accepted for h in fit.history]
        final.restart_log_likelihoods = result.restart_log_likelihoods
        if disagreement and disagreement not in final.warnings:
            final.warnings.append(disagreement)
        result = final
    result.split_merge_moves = moves
    return result


def choose_width(
    batch: DiscoveryBatch, settings: DiscoverySettings, networks: Networks, generator: torch.Generator
) -> DiscoveryResult:
    """``num_cells="auto"``: every width of :data:`~torchrl_options.discovery.width.AUTO_WIDTHS` fitted (with its
    starts, :func:`fit_starts`) on the same 80% of the trajectories, the one with the best held-out likelihood
    kept (:func:`~torchrl_options.discovery.width.select_width`) and trained on on all the trajectories from one
    start, then the split-and-merge moves. Each fit runs under the run's seed."""

    def fit(part: TensorDictBase, width: int) -> DiscoveryResult:
        with seeded(settings.seed) as fit_generator:
            return fit_starts(batch.with_data(part), settings.replace(num_cells=width, split_merge=0,
                              desc=f"{settings.desc} {width} units"), networks.with_width(width), fit_generator)  # fmt: skip

    width, first, scores = select_width(fit, batch.data, widths=AUTO_WIDTHS, generator=generator,
                                        action_space=settings.action_space, action_key=settings.action_key)  # fmt: skip
    # the chosen fit continues on all the trajectories (its starts were already selected on the training share)
    final_settings = settings.replace(num_cells=width, restarts=1, init="auto")
    with seeded(settings.seed) as final_generator:
        final_networks = networks.trained(first.options, first.meta_control)
        final = fit_starts(batch, final_settings, final_networks, final_generator)
        if settings.split_merge:
            final = improve_by_split_merge(final, batch, final_settings, final_networks, final_generator)
    final.restart_log_likelihoods = first.restart_log_likelihoods
    disagreement = restart_disagreement(first.restart_log_likelihoods)
    if disagreement and disagreement not in final.warnings:
        final.warnings.append(disagreement)
    final.history = first.history + final.history
    final.num_cells, final.width_log_likelihoods = width, scores
    return final


def run_discovery(
    batch: DiscoveryBatch, settings: DiscoverySettings, networks: Networks, generator: torch.Generator
) -> DiscoveryResult:
    """The whole run: the width choice (``num_cells="auto"``, :func:`choose_width`) or one fit
    (:func:`fit_starts`), then the split-and-merge moves (:func:`improve_by_split_merge`). The caller seeds the
    global RNG and ``generator`` (:func:`seeded`)."""
    if isinstance(settings.num_cells, str):
        return choose_width(batch, settings, networks, generator)
    result = fit_starts(batch, settings, networks, generator)
    if settings.split_merge:
        result = improve_by_split_merge(result, batch, settings, networks, generator)
    return result
