"""Plots of the recipes (matplotlib, headless): learning curves with Student-t bands over seeds, and the aggregates
over tasks of :mod:`~torchrl_options.experiments.aggregates`."""
from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Sequence

import numpy as np

from torchrl_options.checks import check_int, check_number
from torchrl_options.experiments.aggregates import Aggregates, METHOD as AGGREGATE_METHOD
from torchrl_options.experiments.intervals import METHOD as INTERVAL_METHOD, t_intervals
from torchrl_options.experiments.results import condition_rank, ResultsLog, smooth

__all__ = ["plot_aggregates", "plot_curves"]


def plot_curves(
    log: ResultsLog,
    path: str | os.PathLike,
    *,
    smooth_window: int = 50,
    confidence: float = 0.95,
    title: str | None = None,
    condition_order: Sequence[str] | None = None,
):
    """Writes ``curves.png``: one panel per setting, per condition the mean (over seeds) of the smoothed returns
    with a Student-t interval over seeds at each episode
    (:func:`~torchrl_options.experiments.intervals.mean_interval`). The legend names the interval and each
    condition's number of seeds, conditions in ``condition_order``
    (:func:`~torchrl_options.experiments.results.condition_rank`); a condition with one seed gets no band. A
    caption under the panels says what the lines and bands are. Returns the matplotlib ``Figure`` (written, not
    shown; it holds no pyplot state).

    Needs matplotlib (the ``recipes`` extra).

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options.experiments import ResultsLog
        >>> d = tempfile.mkdtemp()
        >>> log = ResultsLog(os.path.join(d, "results.csv"))
        >>> for seed in (0, 1):
        ...     log.append_cell("supervised", "A", seed, returns=[0.0, 1.0, 1.0, 1.0])
        >>> fig = plot_curves(log, os.path.join(d, "curves.png"), smooth_window=2)
        >>> fig.axes[0].get_xlabel(), fig.axes[0].get_legend() is not None
        ('episode', True)
    """
    check_int(smooth_window, "smooth_window", minimum=1)
    check_number(confidence, "confidence", lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    rows = log.rows()
    data: dict[str, dict[str, dict[int, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    rank = condition_rank(condition_order)
    for r in sorted(rows, key=lambda r: (r["setting"], rank(r["condition"]), r["seed"], r["episode"])):
        data[r["setting"]][r["condition"]][r["seed"]].append(r["return"])
    settings = list(data)
    pct = round(100 * confidence)
    seed_counts = sorted({len(seeds) for conditions in data.values() for seeds in conditions.values()})
    counts = "/".join(str(n) for n in seed_counts) or "0"
    caption = (
        f"Each line: the mean over seeds of the episode return smoothed by a running mean over {smooth_window} "
        f"episodes ({counts} seeds per condition). Shaded bands: the {pct}% {INTERVAL_METHOD}, at each episode "
        "(no band with one seed)."
    )
    fig, _, axes = _captioned_figure(1, max(len(settings), 1), (6, 4), caption)
    for ax, setting in zip(axes[0], settings):
        for condition, seeds in data[setting].items():
            n = min(len(v) for v in seeds.values())
            curves = np.stack([smooth(v[:n], smooth_window) for v in seeds.values()])
            mean, lo, hi = t_intervals(curves, confidence, axis=0)
            x = np.arange(1, n + 1)
            k = curves.shape[0]
            (line,) = ax.plot(x, mean, label=f"{condition}: mean of {k} seed{'s' if k > 1 else ''}")
            if k > 1:
                ax.fill_between(x, lo, hi, alpha=0.2, color=line.get_color(),
                                label=f"{condition}: {pct}% t-interval over {k} seeds")
        name = setting if title is None else f"{title}: {setting}"
        ax.set_title(f"{name}\nbands: {pct}% {INTERVAL_METHOD}", fontsize=10)
        ax.set_xlabel("episode")
        ax.set_ylabel(f"return ({smooth_window}-episode mean)")
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)
    return fig


def plot_aggregates(agg: Aggregates, path: str | os.PathLike, *, title: str | None = None):
    """Writes ``aggregates.png``: the interquartile mean per algorithm, the probability of improvement per pair and
    the performance profiles, each with its stratified bootstrap interval (:func:`~torchrl_options.experiments.
    aggregates.aggregate_scores`), with a caption under the panels. Returns the matplotlib ``Figure`` (written,
    not shown). Needs matplotlib (the ``recipes`` extra).

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options.experiments.aggregates import aggregate_scores
        >>> rng = np.random.default_rng(0)
        >>> agg = aggregate_scores({"A": rng.normal(0, 1, (4, 3)), "H1": rng.normal(1, 1, (4, 3))}, [("H1", "A")],
        ...                        num_resamples=200)
        >>> path = os.path.join(tempfile.mkdtemp(), "aggregates.png")
        >>> fig = plot_aggregates(agg, path)
        >>> os.path.getsize(path) > 0, [ax.get_title() for ax in fig.axes]
        (True, ['IQM, 95% CI', 'Probability of improvement, 95% CI', 'Performance profiles, 95% bands'])
    """
    pct = round(100 * agg.confidence)
    names = list(agg.iqm)
    pairs = list(agg.improvement)
    caption = (
        f"Left: the interquartile mean of the normalised scores per algorithm. Middle: the probability that the first "
        "algorithm of a pair scores higher than the second on a task (0.5: no difference). Right: the fraction of "
        f"runs whose normalised score exceeds tau. Dots and lines are point estimates; bars and shaded bands: {pct}% "
        f"{AGGREGATE_METHOD} ({agg.num_resamples} resamples) over runs per task, tasks as strata."
    )
    fig, main, axes = _captioned_figure(1, 3, (16 / 3, max(3.5, 0.5 * max(len(names), len(pairs)) + 2)), caption)
    axes = axes[0]
    colors = {name: f"C{i}" for i, name in enumerate(names)}
    ax = axes[0]
    for i, name in enumerate(names):
        m, lo, hi = agg.iqm[name]
        ax.errorbar([m], [i], xerr=[[m - lo], [hi - m]], fmt="o", color=colors[name], capsize=4)
    ax.set_yticks(range(len(names)), [f"{n} ({agg.num_runs[n]} runs/task)" for n in names])
    ax.set_ylabel("algorithm")
    ax.set_xlabel("interquartile mean of normalised scores")
    ax.set_title(f"IQM, {pct}% CI")
    ax = axes[1]
    for i, pair in enumerate(pairs):
        p, lo, hi = agg.improvement[pair]
        ax.errorbar([p], [i], xerr=[[p - lo], [hi - p]], fmt="o", color=colors[pair[0]], capsize=4)
    ax.axvline(0.5, color="grey", linestyle="--", linewidth=1)
    ax.set_yticks(range(len(pairs)), [f"P({a} > {b}): {agg.verdict((a, b))}" for a, b in pairs])
    ax.set_xlim(0, 1)
    ax.set_ylabel("pair of algorithms")
    ax.set_xlabel("probability of improvement")
    ax.set_title(f"Probability of improvement, {pct}% CI")
    ax = axes[2]
    for name in names:
        prof, lo, hi = agg.profiles[name]
        ax.plot(agg.thresholds, prof, color=colors[name], label=f"{name} ({agg.num_runs[name]} runs/task)")
        ax.fill_between(agg.thresholds, lo, hi, color=colors[name], alpha=0.2)
    ax.set_xlabel("normalised score tau")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_title(f"Performance profiles, {pct}% bands")
    ax.legend(fontsize=8)
    head = f"{title}: " if title else ""
    main.suptitle(f"{head}{len(agg.tasks)} tasks ({', '.join(agg.tasks)}); scores normalised {agg.normalization}; "
                      f"intervals: {AGGREGATE_METHOD}, {agg.num_resamples} resamples", fontsize=9)
    fig.savefig(path, dpi=100)
    return fig


def _captioned_figure(
    num_rows: int, num_cols: int, panel_size: tuple[float, float], caption: str, extra_width: float = 0.0
):
    """A matplotlib ``Figure`` (no pyplot: no global state, no backend to choose) of ``num_rows x num_cols``
    panels over a wrapped caption. Returns ``(figure, the panels' subfigure, axes [num_rows, num_cols])``."""
    import textwrap

    try:
        from matplotlib.figure import Figure
    except ImportError as e:  # an optional dependency (the ``recipes`` extra)
        raise ImportError("the plots need matplotlib: pip install matplotlib") from e
    width, height = num_cols * panel_size[0] + extra_width, num_rows * panel_size[1]
    lines = textwrap.wrap(caption, width=max(int(width * 15), 60))
    caption_h = 0.16 * len(lines) + 0.15
    fig = Figure(figsize=(width, height + caption_h), layout="constrained")
    main, below = fig.subfigures(2, 1, height_ratios=[height, caption_h])
    below.text(0.01, 0.98, "\n".join(lines), ha="left", va="top", fontsize=8)
    return fig, main, main.subplots(num_rows, num_cols, squeeze=False)
