"""The MiniGrid RL cells' summary: success rates and frames to reach a success rate, over seeds with 95% Student-t
intervals, each condition paired by seed with the actions-only condition of its algorithm; and success curves
against frames.

MiniGrid's reward is positive exactly when the mission succeeds, so an episode's success is ``return > 0``. Rows are
those of ``results.csv`` (:class:`~torchrl_options.experiments.ResultsLog`: setting, condition, seed, episode,
frames, return).
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["RLSummary", "rl_summary", "rl_summary_markdown", "frames_to_reach", "plot_success_curves"]


def frames_to_reach(successes: Sequence[float], frames: Sequence[int], target: float, window: int) -> int | None:
    """The frame count at the end of the first episode after which the success rate over the last ``window``
    episodes is at least ``target`` (``None``: never).

    Examples:
        >>> frames_to_reach([0, 0, 1, 1, 1], [10, 20, 30, 40, 50], target=1.0, window=2)
        40
        >>> frames_to_reach([0, 1], [10, 20], target=1.0, window=2) is None
        True
    """
    s = np.asarray(successes, dtype=float)
    if s.size < window:
        return None
    rate = np.convolve(s, np.ones(window) / window, mode="valid")  # rate[i]: episodes i .. i + window - 1
    hit = np.nonzero(rate >= target - 1e-12)[0]
    return int(frames[hit[0] + window - 1]) if hit.size else None


@dataclass
class RLSummary:
    """One (setting, condition): per-seed figures and their intervals ``(mean, low, high)``.

    ``final_success``: success rate over the last ``window`` episodes; ``frames_to_reach``: per seed, the frames to
    the target success rate (``None``: not reached in the budget); ``reach_interval``: over the seeds, counting a
    seed that did not reach as the budget (a lower bound then, flagged by ``reached < seeds``); ``diff_final``: the
    paired difference of final success with the algorithm's ``A`` (``None`` for ``A``), and its verdict.
    """

    setting: str
    condition: str
    seeds: list[int]
    final_success: tuple[float, float, float]
    frames_to_reach: list[int | None]
    reach_interval: tuple[float, float, float]
    budget: int
    diff_final: tuple[float, float, float] | None = None
    verdict: str | None = None

    @property
    def reached(self) -> int:
        return sum(f is not None for f in self.frames_to_reach)


def _interval(values) -> tuple[float, float, float]:
    from torchrl_options.experiments import mean_interval

    values = list(values)
    if len(values) == 1:
        return (float(values[0]), -math.inf, math.inf)
    return tuple(float(x) for x in mean_interval(values))


def rl_summary(rows: Iterable[dict], *, target: float = 0.5, window: int = 50) -> list[RLSummary]:
    """Per (setting, condition), the summary of its seeds (see :class:`RLSummary`); conditions paired with the
    ``A`` of their algorithm (``"ppo-H1"`` with ``"ppo-A"``) on their common seeds.

    Examples:
        >>> rows = [dict(setting="L", condition=c, seed=s, episode=e, frames=10 * (e + 1), **{"return": r})
        ...         for c, rs in (("ppo-A", [0, 0, 0, 1]), ("ppo-H1", [0, 1, 1, 1])) for s in (0, 1)
        ...         for e, r in enumerate(rs)]
        >>> out = {x.condition: x for x in rl_summary(rows, target=1.0, window=2)}
        >>> out["ppo-H1"].frames_to_reach, out["ppo-A"].frames_to_reach, out["ppo-H1"].diff_final[0]
        ([30, 30], [None, None], 0.5)
    """
    from torchrl_options.experiments import interval_verdict, paired_difference_interval

    cells: dict[tuple[str, str], dict[int, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        cells[(r["setting"], r["condition"])][int(r["seed"])].append(r)
    per_seed: dict[tuple[str, str], dict[int, tuple[float, int | None, int]]] = {}
    for key, seeds in cells.items():
        per_seed[key] = {}
        for seed, eps in seeds.items():
            eps = sorted(eps, key=lambda r: int(r["episode"]))
            success = [float(float(r["return"]) > 0) for r in eps]
            frames = [int(r["frames"]) if r.get("frames") not in (None, "") else 0 for r in eps]
            final = float(np.mean(success[-window:])) if success else math.nan
            per_seed[key][seed] = (final, frames_to_reach(success, frames, target, window), max(frames, default=0))
    out = []
    for (setting, condition), seeds in sorted(per_seed.items()):
        order = sorted(seeds)
        finals = [seeds[s][0] for s in order]
        reach = [seeds[s][1] for s in order]
        budget = max(seeds[s][2] for s in order)
        summary = RLSummary(setting, condition, order, _interval(finals), reach,
                            _interval([f if f is not None else budget for f in reach]), budget)  # fmt: skip
        algorithm = condition.partition("-")[0]
        base = per_seed.get((setting, f"{algorithm}-A"))
        if not condition.endswith("-A") and base is not None:
            common = [s for s in order if s in base]
            if len(common) >= 2:
                summary.diff_final = paired_difference_interval([seeds[s][0] for s in common],
                                                                [base[s][0] for s in common])  # fmt: skip
                summary.verdict = f"{interval_verdict(summary.diff_final)} ({len(common)} seeds)"
        out.append(summary)
    return out


def _fmt(x: tuple[float, float, float], digits: int = 2) -> str:
    mean, lo, hi = x
    if not math.isfinite(lo):
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def rl_summary_markdown(summaries: Sequence[RLSummary], *, target: float, window: int) -> str:
    """A Markdown table of :func:`rl_summary`: per level and condition, seeds, final success rate, frames to reach
    ``target`` (with how many seeds reached it), and the paired difference in final success with ``A``.

    Examples:
        >>> s = RLSummary("L", "ppo-H1", [0, 1], (0.5, 0.1, 0.9), [30, None], (65.0, -200.0, 330.0), 100,
        ...               (0.25, -0.5, 1.0), "no evidence either way (2 seeds)")
        >>> print(rl_summary_markdown([s], target=0.5, window=10).splitlines()[-1])
        | L | ppo-H1 | 2 | 0.50 [0.10, 0.90] | >= 65 [-200, 330] (1/2 reached) | 0.25 [-0.50, 1.00] | no evidence either way (2 seeds) |
    """
    head = (f"| level | condition | seeds | final success rate (last {window} episodes) | frames to a success rate of "
            f"{target:g} over {window} episodes | final success - A (paired by seed) | verdict |\n"
            "|---|---|---|---|---|---|---|\n")
    lines = []
    for s in summaries:
        reach = _fmt(s.reach_interval, 0)
        reach = (f">= {reach} ({s.reached}/{len(s.seeds)} reached)" if s.reached < len(s.seeds)
                 else f"{reach} ({s.reached}/{len(s.seeds)} reached)")  # fmt: skip
        diff = _fmt(s.diff_final) if s.diff_final is not None else "-"
        lines.append(f"| {s.setting} | {s.condition} | {len(s.seeds)} | {_fmt(s.final_success)} | {reach} | {diff} | "
                     f"{s.verdict or '-'} |")  # fmt: skip
    return head + "\n".join(lines) + "\n"


def plot_success_curves(rows: Iterable[dict], path: str, *, bins: int = 20, title: str | None = None):
    """Writes the success curves: per level, per condition, the success rate of the episodes ending in each of
    ``bins`` equal frame intervals, averaged over seeds with a 95% Student-t band (no band with one seed).
    Needs matplotlib. Returns the figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_options.experiments.intervals import METHOD, t_intervals

    data: dict[str, dict[str, dict[int, list[tuple[int, float]]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in rows:
        frames = int(r["frames"]) if r.get("frames") not in (None, "") else 0
        data[r["setting"]][r["condition"]][int(r["seed"])].append((frames, float(float(r["return"]) > 0)))
    settings = sorted(data)
    fig, axes = plt.subplots(1, max(len(settings), 1), figsize=(6 * max(len(settings), 1), 4.2), squeeze=False)
    for ax, setting in zip(axes[0], settings):
        budget = max(f for c in data[setting].values() for eps in c.values() for f, _ in eps)
        edges = np.linspace(0, budget, bins + 1)
        centres = 0.5 * (edges[1:] + edges[:-1])
        for condition in sorted(data[setting]):
            curves = []
            for eps in data[setting][condition].values():
                f = np.array([e[0] for e in eps])
                s = np.array([e[1] for e in eps])
                idx = np.clip(np.searchsorted(edges, f, side="left") - 1, 0, bins - 1)
                rate = np.full(bins, np.nan)
                for b in range(bins):
                    if (idx == b).any():
                        rate[b] = s[idx == b].mean()
                # a bin without an ending episode carries the last rate on
                for b in range(1, bins):
                    if np.isnan(rate[b]):
                        rate[b] = rate[b - 1]
                curves.append(np.nan_to_num(rate, nan=0.0))
            curves = np.stack(curves)
            mean, lo, hi = t_intervals(curves, 0.95, axis=0)
            k = curves.shape[0]
            (line,) = ax.plot(centres, mean, label=f"{condition} ({k} seed{'s' if k > 1 else ''})")
            if k > 1:
                ax.fill_between(centres, np.clip(lo, 0, 1), np.clip(hi, 0, 1), alpha=0.2, color=line.get_color())
        ax.set_title(f"{title + ': ' if title else ''}{setting}\nbands: 95% {METHOD}", fontsize=9)
        ax.set_xlabel("frames")
        ax.set_ylabel("success rate of the episodes ending in the interval")
        ax.set_ylim(-0.02, 1.02)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return fig
