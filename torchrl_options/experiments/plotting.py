"""Plots of the recipes (matplotlib, headless): learning curves with Student-t bands over seeds, and the aggregates
over tasks of :mod:`~torchrl_options.experiments.aggregates`."""
from __future__ import annotations

import os
from collections import defaultdict

import numpy as np

from torchrl_options.experiments.aggregates import Aggregates, METHOD as AGGREGATE_METHOD
from torchrl_options.experiments.intervals import METHOD as INTERVAL_METHOD, t_intervals
from torchrl_options.experiments.results import ResultsLog, smooth

__all__ = ["plot_aggregates", "plot_curves"]


def plot_curves(
    log: ResultsLog,
    path: str | os.PathLike,
    *,
    smooth_window: int = 50,
    confidence: float = 0.95,
    title: str | None = None,
) -> None:
    """Writes ``curves.png``: one panel per setting, per condition the mean (over seeds) of the smoothed returns
    with a Student-t interval over seeds at each episode
    (:func:`~torchrl_options.experiments.intervals.mean_interval`). The legend names the interval and each
    condition's number of seeds; a condition with one seed gets no band.

    Needs matplotlib (the ``recipes`` extra).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = log.rows()
    data: dict[str, dict[str, dict[int, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in sorted(rows, key=lambda r: (r["setting"], r["condition"], r["seed"], r["episode"])):
        data[r["setting"]][r["condition"]][r["seed"]].append(r["return"])
    settings = list(data)
    fig, axes = plt.subplots(1, max(len(settings), 1), figsize=(6 * max(len(settings), 1), 4), squeeze=False)
    pct = round(100 * confidence)
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
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_aggregates(agg: Aggregates, path: str | os.PathLike, *, title: str | None = None) -> None:
    """Writes ``aggregates.png``: the interquartile mean per algorithm, the probability of improvement per pair and
    the performance profiles, each with its stratified bootstrap interval (:func:`~torchrl_options.experiments.
    aggregates.aggregate_scores`). Needs matplotlib (the ``recipes`` extra).

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options.experiments.aggregates import aggregate_scores
        >>> rng = np.random.default_rng(0)
        >>> agg = aggregate_scores({"A": rng.normal(0, 1, (4, 3)), "H1": rng.normal(1, 1, (4, 3))}, [("H1", "A")],
        ...                        num_resamples=200)
        >>> path = os.path.join(tempfile.mkdtemp(), "aggregates.png")
        >>> plot_aggregates(agg, path)
        >>> os.path.getsize(path) > 0
        True
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pct = round(100 * agg.confidence)
    names = list(agg.iqm)
    pairs = list(agg.improvement)
    fig, axes = plt.subplots(1, 3, figsize=(16, max(3.5, 0.5 * max(len(names), len(pairs)) + 2)))
    colors = {name: f"C{i}" for i, name in enumerate(names)}
    ax = axes[0]
    for i, name in enumerate(names):
        m, lo, hi = agg.iqm[name]
        ax.errorbar([m], [i], xerr=[[m - lo], [hi - m]], fmt="o", color=colors[name], capsize=4)
    ax.set_yticks(range(len(names)), [f"{n} ({agg.num_runs[n]} runs/task)" for n in names])
    ax.set_xlabel("interquartile mean of normalised scores")
    ax.set_title(f"IQM, {pct}% CI")
    ax = axes[1]
    for i, pair in enumerate(pairs):
        p, lo, hi = agg.improvement[pair]
        ax.errorbar([p], [i], xerr=[[p - lo], [hi - p]], fmt="o", color=colors[pair[0]], capsize=4)
    ax.axvline(0.5, color="grey", linestyle="--", linewidth=1)
    ax.set_yticks(range(len(pairs)), [f"P({a} > {b}): {agg.verdict((a, b))}" for a, b in pairs])
    ax.set_xlim(0, 1)
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
    fig.suptitle(f"{head}{len(agg.tasks)} tasks ({', '.join(agg.tasks)}); scores normalised {agg.normalization}; "
                 f"intervals: {AGGREGATE_METHOD}, {agg.num_resamples} resamples", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
