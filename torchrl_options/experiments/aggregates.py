"""Aggregates over tasks as Agarwal et al. report them: interquartile mean, probability of improvement and
performance profiles, with stratified bootstrap intervals.

Agarwal, Schwarzer, Castro, Courville, Bellemare, "Deep Reinforcement Learning at the Edge of the Statistical
Precipice", NeurIPS 2021 (the `rliable` library). Scores come as one matrix per algorithm, ``[num_runs, num_tasks]``
(one row per seed, one column per task, e.g. per Atari game), normalised so that tasks are comparable
(:func:`min_max_normalize`). Implemented here after the paper's definitions, with numpy only:

- the interquartile mean (IQM): the mean of the middle 50% of all run x task scores pooled (25% trimmed from
  each end), robust to outlier runs and more efficient than the median;
- the probability of improvement P(X > Y): per task, the probability that a run of X scores above a run of Y
  (ties count half: the Mann-Whitney U statistic over ``n_x * n_y``), averaged over tasks;
- the performance profile: for each threshold tau, the fraction of runs scoring above tau, per task, averaged over
  tasks (the run-score distribution);
- intervals by the stratified bootstrap: runs are resampled with replacement within each task, independently for
  each algorithm, and the percentile interval of the statistic is taken.

The stratified bootstrap is a percentile bootstrap, so like any percentile bootstrap it is too narrow when each task
has few runs (``benchmarks/bench_intervals.py`` measures it); summaries name the number of runs it rests on.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from torchrl_options.experiments.intervals import _check_confidence, AHEAD, BEHIND, NO_EVIDENCE

__all__ = [
    "Aggregates",
    "aggregate_scores",
    "aggregates_markdown",
    "interquartile_mean",
    "min_max_normalize",
    "performance_profile",
    "probability_of_improvement",
    "stratified_bootstrap_interval",
]

#: how the intervals of this module are computed, for tables and plots to name it
METHOD = "stratified percentile bootstrap over runs (Agarwal et al. 2021)"


def _as_scores(scores, name: str) -> np.ndarray:
    """``scores`` as a finite float array ``[num_runs, num_tasks]`` (a 1-D array is one task), or a clear error."""
    try:
        x = np.asarray(scores, dtype=float)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be an array of scores [num_runs, num_tasks], got {scores!r} ({err}).") from None
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty array of scores [num_runs, num_tasks], got shape {x.shape}.")
    if not np.isfinite(x).all():
        raise ValueError(f"{name} must hold finite scores, got {x.tolist()!r}.")
    return x


def _iqm(x: np.ndarray) -> np.ndarray:
    """IQM over the last two dims of ``x`` ``[..., runs, tasks]`` (vectorised over the leading ones)."""
    flat = np.sort(x.reshape(*x.shape[:-2], -1), axis=-1)
    n = flat.shape[-1]
    cut = int(0.25 * n)  # as scipy.stats.trim_mean(..., 0.25), which rliable uses
    return flat[..., cut : n - cut].mean(-1)


def interquartile_mean(scores: np.ndarray | Sequence) -> float:
    """The mean of the middle 50% of all scores of ``scores`` ``[num_runs, num_tasks]`` pooled.

    ``int(0.25 * N)`` of the ``N = num_runs * num_tasks`` scores are dropped from each end, as
    ``scipy.stats.trim_mean(scores, 0.25)`` (what `rliable` computes).

    Examples:
        >>> interquartile_mean([[0.0, 1.0], [2.0, 3.0], [4.0, 100.0]])  # drops 0.0 and 100.0
        2.5
    """
    return float(_iqm(_as_scores(scores, "scores")))


def _poi(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y) / 2 per task, averaged over tasks; ``x`` ``[..., n, T]``, ``y`` ``[..., m, T]``."""
    diff = x[..., :, None, :] - y[..., None, :, :]  # [..., n, m, T]
    return ((diff > 0).mean((-3, -2)) + 0.5 * (diff == 0).mean((-3, -2))).mean(-1)


def probability_of_improvement(scores: np.ndarray | Sequence, baseline: np.ndarray | Sequence) -> float:
    """P(X > Y): per task, the probability that a run of ``scores`` beats a run of ``baseline`` (ties count half),
    averaged over tasks. 0.5 means neither is better.

    Args:
        scores: ``[num_runs, num_tasks]`` of the algorithm X.
        baseline: ``[num_runs', num_tasks]`` of the algorithm Y (the same tasks in the same order).

    Examples:
        >>> probability_of_improvement([[1.0, 5.0], [2.0, 6.0]], [[0.0, 6.0], [3.0, 7.0]])  # (2/4 + 0.5/4) / 2
        0.3125
    """
    x, y = _as_scores(scores, "scores"), _as_scores(baseline, "baseline")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"scores and baseline must have the same tasks, got {x.shape[1]} and {y.shape[1]} columns.")
    return float(_poi(x, y))


def _profile(x: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Fraction of runs above each threshold per task, averaged over tasks; ``x`` ``[..., n, T]`` -> ``[..., K]``."""
    return (x[..., None, :, :] > thresholds[:, None, None]).mean(-2).mean(-1)


def performance_profile(scores: np.ndarray | Sequence, thresholds: np.ndarray | Sequence) -> np.ndarray:
    """The run-score distribution: for each threshold tau, the fraction of runs scoring above tau, computed per task
    and averaged over tasks (each task weighs the same whatever its number of runs).

    Examples:
        >>> performance_profile([[0.0, 0.5], [1.0, 1.0]], [-1.0, 0.25, 0.75, 1.0]).tolist()
        [1.0, 0.75, 0.5, 0.0]
    """
    x = _as_scores(scores, "scores")
    taus = np.asarray(thresholds, dtype=float)
    if taus.ndim != 1 or taus.size == 0 or not np.isfinite(taus).all():
        raise ValueError(f"thresholds must be a non-empty 1-D array of finite numbers, got {thresholds!r}.")
    return _profile(x, taus)


def stratified_bootstrap_interval(
    statistic: Callable[..., np.ndarray],
    *scores: np.ndarray | Sequence,
    confidence: float = 0.95,
    num_resamples: int = 2000,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(point, low, high)`` of ``statistic(*scores)`` by the stratified percentile bootstrap.

    Each score matrix ``[num_runs, num_tasks]`` is resampled within each task (its runs drawn with replacement, the
    tasks kept), independently of the others; ``statistic`` must accept batched matrices ``[B, num_runs, num_tasks]``
    and return ``[B, ...]`` (as the vectorised helpers of this module do). Resamples are drawn in chunks, so memory
    stays bounded.

    Args:
        statistic: the statistic, vectorised over a leading batch dimension.
        *scores: one or more score matrices.
        confidence (float): in (0, 1).
        num_resamples (int): bootstrap resamples (at least 100).
        seed (int): the seed of the resampling, so a summary is reproducible.

    Examples:
        >>> point, low, high = stratified_bootstrap_interval(_iqm, [[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]])
        >>> float(point), bool(low <= point <= high)
        (2.5, True)
    """
    if not callable(statistic):
        raise TypeError(f"statistic must be a callable of the score matrices, got {type(statistic).__name__}.")
    confidence = _check_confidence(confidence)
    if isinstance(num_resamples, bool) or not isinstance(num_resamples, (int, np.integer)) or num_resamples < 100:
        raise ValueError(f"num_resamples must be an integer >= 100, got {num_resamples!r}.")
    if not scores:
        raise ValueError("stratified_bootstrap_interval needs at least one score matrix.")
    mats = [_as_scores(s, f"scores[{i}]") for i, s in enumerate(scores)]
    point = np.asarray(statistic(*(m[None] for m in mats)))[0]
    rng = np.random.default_rng(seed)
    draws = []
    chunk = max(1, min(num_resamples, 2_000_000 // max(1, sum(m.size for m in mats) * 8)))
    for start in range(0, num_resamples, chunk):
        b = min(chunk, num_resamples - start)
        resampled = []
        for m in mats:
            idx = rng.integers(0, m.shape[0], size=(b, *m.shape))
            resampled.append(np.take_along_axis(m[None].repeat(b, 0), idx, axis=1))
        draws.append(np.asarray(statistic(*resampled)))
    draws = np.concatenate(draws, 0)
    alpha = (1 - confidence) / 2
    return point, np.quantile(draws, alpha, axis=0), np.quantile(draws, 1 - alpha, axis=0)


def min_max_normalize(scores: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Per task, scales every algorithm's scores so that the lowest run of any algorithm is 0 and the highest 1.

    For tasks without reference scores (no human or random-agent baselines, as for the capped Atari RAM games):
    the aggregates then compare algorithms relative to each other, not to an outside reference. A task where every
    run scored the same maps to 0.

    Returns:
        ``(normalised scores, low, high)``, ``low`` and ``high`` per task.

    Examples:
        >>> norm, low, high = min_max_normalize({"A": [[0.0, 10.0]], "B": [[2.0, 30.0]]})
        >>> norm["A"].tolist(), norm["B"].tolist(), low.tolist(), high.tolist()
        ([[0.0, 0.0]], [[1.0, 1.0]], [0.0, 10.0], [2.0, 30.0])
    """
    if not scores:
        raise ValueError("scores must map at least one algorithm to its score matrix, got none.")
    mats = {name: _as_scores(s, f"scores[{name!r}]") for name, s in scores.items()}
    tasks = {m.shape[1] for m in mats.values()}
    if len(tasks) != 1:
        columns = {k: m.shape[1] for k, m in mats.items()}
        raise ValueError(f"every algorithm must have the same tasks, got these numbers of columns: {columns}.")
    low = np.min([m.min(0) for m in mats.values()], axis=0)
    high = np.max([m.max(0) for m in mats.values()], axis=0)
    span = np.where(high > low, high - low, 1.0)
    return {name: (m - low) / span for name, m in mats.items()}, low, high


@dataclass
class Aggregates:
    """What :func:`aggregate_scores` computes, for :func:`aggregates_markdown` and
    :func:`~torchrl_options.experiments.plotting.plot_aggregates`."""

    tasks: list[str]
    num_runs: dict[str, int]
    iqm: dict[str, tuple[float, float, float]]
    improvement: dict[tuple[str, str], tuple[float, float, float]]
    thresholds: np.ndarray
    profiles: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    confidence: float
    num_resamples: int
    normalization: str = "min-max per task over all runs of all algorithms"

    def verdict(self, pair: tuple[str, str]) -> str:
        """``"ahead"`` when the interval of P(X > Y) lies above 0.5, ``"behind"`` below, else no evidence."""
        _, low, high = self.improvement[pair]
        return AHEAD if low > 0.5 else BEHIND if high < 0.5 else NO_EVIDENCE


def aggregate_scores(
    scores: Mapping[str, np.ndarray],
    pairs: Sequence[tuple[str, str]],
    *,
    tasks: Sequence[str] | None = None,
    normalize: bool = True,
    num_thresholds: int = 51,
    confidence: float = 0.95,
    num_resamples: int = 2000,
    seed: int = 0,
) -> Aggregates:
    """IQM per algorithm, probability of improvement per ``(algorithm, baseline)`` pair and performance profiles,
    each with stratified bootstrap intervals.

    Args:
        scores: ``{algorithm: [num_runs, num_tasks]}`` (raw scores; min-max normalised per task when ``normalize``).
        pairs: the ``(algorithm, baseline)`` pairs whose probability of improvement to report.
        tasks: the tasks' names (default ``task0``, ``task1``, ...).
        normalize (bool): min-max normalise per task (:func:`min_max_normalize`); give False for scores that are
            already normalised.
        num_thresholds (int): points of the performance profiles, spread over the range of the (normalised) scores.
        confidence, num_resamples, seed: of the stratified bootstrap.

    Examples:
        >>> rng = np.random.default_rng(0)
        >>> agg = aggregate_scores({"A": rng.normal(0, 1, (5, 3)), "B": rng.normal(3, 1, (5, 3))}, [("B", "A")])
        >>> agg.verdict(("B", "A")), agg.num_runs
        ('ahead', {'A': 5, 'B': 5})
    """
    mats, _, _ = min_max_normalize(scores) if normalize else (
        {k: _as_scores(v, f"scores[{k!r}]") for k, v in scores.items()}, None, None)
    num_tasks = next(iter(mats.values())).shape[1]
    if any(m.shape[1] != num_tasks for m in mats.values()):
        columns = {k: m.shape[1] for k, m in mats.items()}
        raise ValueError(f"every algorithm must have the same tasks, got these numbers of columns: {columns}.")
    tasks = [f"task{i}" for i in range(num_tasks)] if tasks is None else list(tasks)
    if len(tasks) != num_tasks:
        raise ValueError(f"tasks must name the {num_tasks} columns of the scores, got {len(tasks)} names: {tasks!r}.")
    for pair in pairs:
        missing = [name for name in pair if name not in mats]
        if len(pair) != 2 or missing:
            raise ValueError(f"pairs must be (algorithm, baseline) among {sorted(mats)}, got {pair!r}.")
    if isinstance(num_thresholds, bool) or not isinstance(num_thresholds, int) or num_thresholds < 2:
        raise ValueError(f"num_thresholds must be an integer >= 2, got {num_thresholds!r}.")
    kw = dict(confidence=confidence, num_resamples=num_resamples, seed=seed)
    iqm = {k: tuple(float(v) for v in stratified_bootstrap_interval(_iqm, m, **kw)) for k, m in mats.items()}
    improvement = {
        (a, b): tuple(float(v) for v in stratified_bootstrap_interval(_poi, mats[a], mats[b], **kw)) for a, b in pairs
    }
    lo = min(float(m.min()) for m in mats.values())
    hi = max(float(m.max()) for m in mats.values())
    thresholds = np.linspace(lo, hi if hi > lo else lo + 1.0, num_thresholds)
    profiles = {
        k: stratified_bootstrap_interval(lambda x: _profile(x, thresholds), m, **kw) for k, m in mats.items()
    }
    return Aggregates(
        tasks=tasks,
        num_runs={k: int(m.shape[0]) for k, m in mats.items()},
        iqm=iqm,
        improvement=improvement,
        thresholds=thresholds,
        profiles=profiles,
        confidence=float(confidence),
        num_resamples=int(num_resamples),
        normalization="min-max per task over all runs of all algorithms" if normalize else "as given",
    )


def aggregates_markdown(agg: Aggregates, *, score_name: str = "score") -> str:
    """The IQM and probability-of-improvement tables of :func:`aggregate_scores` in Markdown, each verdict with the
    number of runs it rests on and the interval method.

    Examples:
        >>> agg = aggregate_scores({"A": [[0.0, 1.0], [1.0, 2.0]], "B": [[1.0, 3.0], [2.0, 4.0]]}, [("B", "A")],
        ...                        num_resamples=200)
        >>> print(aggregates_markdown(agg).splitlines()[-1])
        | B vs A | 0.94 [0.75, 1.00] | ahead | 2 vs 2 |
    """
    pct = round(100 * agg.confidence)
    lines = [
        f"Aggregates over {len(agg.tasks)} tasks ({', '.join(agg.tasks)}) after Agarwal et al. (2021): {score_name} "
        f"normalised {agg.normalization}; {pct}% intervals by the {METHOD}, {agg.num_resamples} resamples. "
        "With few runs per task these percentile intervals are too narrow; read them with the run counts.\n",
        f"| algorithm | runs per task | interquartile mean (normalised) [{pct}% CI] |",
        "|---|---|---|",
    ]
    for name, (m, lo, hi) in agg.iqm.items():
        lines.append(f"| {name} | {agg.num_runs[name]} | {m:.3f} [{lo:.3f}, {hi:.3f}] |")
    if agg.improvement:
        lines += [
            "",
            f"Probability of improvement P(X > Y), averaged over tasks: verdict \"ahead\" / \"behind\" when its {pct}% "
            "interval lies above / below 0.5, \"no evidence either way\" when it contains 0.5. It compares every run "
            "of X with every run of Y (unpaired), so it does not use a pairing of runs by seed.\n",
            f"| X vs Y | P(X > Y) [{pct}% CI] | verdict | runs per task (X vs Y) |",
            "|---|---|---|---|",
        ]
        for (a, b), (p, lo, hi) in agg.improvement.items():
            lines.append(f"| {a} vs {b} | {p:.2f} [{lo:.2f}, {hi:.2f}] | {agg.verdict((a, b))} | "
                         f"{agg.num_runs[a]} vs {agg.num_runs[b]} |")
    return "\n".join(lines) + "\n"
