"""Experiment results shared by the recipes: a resumable long-format CSV, summaries with Student-t intervals over
seeds (:func:`~torchrl_options.experiments.intervals.mean_interval`) and paired comparisons against a baseline.

Every recipe writes ``results.csv`` with one row per episode, in long format (``setting, condition, seed,
episode, return`` and optionally ``frames``), appends a cell's rows only when the cell (a setting, condition and
seed) has finished, and skips finished cells when run again — so a killed recipe loses no finished seed.
"""
from __future__ import annotations

import csv
import logging
import os
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from torchrl_options.checkpoints import atomic_replace
from torchrl_options.checks import check_int, check_number, check_numbers
from torchrl_options.experiments.intervals import (
    interval_verdict,
    mean_interval,
    paired_difference_interval,
)
from torchrl_options.experiments.run_settings import (
    describe_differences,
    read_run_settings,
    settings_differences,
    write_run_settings,
)

__all__ = [
    "merge_results",
    "ResultsLog",
    "episodes_to_reach",
    "within",
    "ConditionSummary",
    "summarize",
    "condition_rank",
    "summary_markdown",
    "BaselineComparison",
    "compare_to_baseline",
    "comparison_markdown",
]

logger = logging.getLogger(__name__)

FIELDS = ("setting", "condition", "seed", "episode", "return", "frames")


class ResultsLog:
    """An append-only, resumable ``results.csv``: one row per episode of a (setting, condition, seed) cell.

    Args:
        path (str): the CSV file; created with a header if missing.

    Examples:
        >>> import os, tempfile
        >>> log = ResultsLog(os.path.join(tempfile.mkdtemp(), "results.csv"))
        >>> log.append_cell("supervised", "A", 0, returns=[0.0, 1.0, 2.0])
        >>> log.is_done("supervised", "A", 0), log.is_done("supervised", "A", 1)
        (True, False)
        >>> log.returns("supervised", "A")
        {0: [0.0, 1.0, 2.0]}
    """

    def __init__(self, path: str | os.PathLike) -> None:
        if not isinstance(path, (str, os.PathLike)):
            raise TypeError(f"ResultsLog: path must be a str or a path, got {type(path).__name__}.")
        if os.path.isdir(path):
            raise ValueError(f"ResultsLog: {os.fspath(path)} is a directory; expected a CSV file name (results.csv).")
        self.path = os.fspath(path)
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        if not os.path.exists(self.path):
            with atomic_replace(self.path) as tmp, open(tmp, "w", newline="") as f:  # never half a header
                csv.writer(f).writerow(FIELDS)

    def rows(self) -> list[dict]:
        """Every row, with ``seed``, ``episode`` (ints), ``return`` (float) and ``frames`` (int or ``None``).

        Raises:
            ValueError: naming the file and the line, for a header without the columns :data:`FIELDS` or a row
                whose numbers do not parse.
        """
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            missing = [c for c in ("setting", "condition", "seed", "episode", "return") if c not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(
                    f"{self.path}: not a results file (expected the CSV columns {FIELDS}, the header lacks {missing})."
                )
            out = []
            for row in reader:
                try:
                    row["seed"] = int(row["seed"])
                    row["episode"] = int(row["episode"])
                    row["return"] = float(row["return"])
                    row["frames"] = int(row["frames"]) if row.get("frames") not in (None, "") else None
                except (TypeError, ValueError) as err:
                    raise ValueError(
                        f"{self.path}, line {reader.line_num}: not a valid results row ({err}); expected {FIELDS}."
                    ) from None
                out.append(row)
        return out

    def done_cells(self) -> set[tuple[str, str, int]]:
        return {(r["setting"], r["condition"], r["seed"]) for r in self.rows()}

    def is_done(self, setting: str, condition: str, seed: int) -> bool:
        return (setting, condition, int(seed)) in self.done_cells()

    def append_cell(
        self,
        setting: str,
        condition: str,
        seed: int,
        returns: Sequence[float],
        frames: Sequence[int] | None = None,
    ) -> None:
        """Appends a finished cell's episodes at once (a half-written cell is never left behind)."""
        self.append_cells([(setting, condition, seed, returns, frames)])

    def append_cells(
        self, cells: Iterable[tuple[str, str, int, Sequence[float], Sequence[int] | None]]
    ) -> None:
        """Appends several finished cells, ``(setting, condition, seed, returns, frames)`` each, in one write.

        Either all of them are written or none (the file is replaced atomically).
        """
        done = self.done_cells()
        lines = []
        for setting, condition, seed, returns, frames in cells:
            for name, value in (("setting", setting), ("condition", condition)):
                if not isinstance(value, str) or not value:
                    raise TypeError(f"{name} must be a non-empty str, got {value!r}.")
            check_int(seed, "seed", minimum=0)
            returns = check_numbers(returns, "returns", allow_empty=False)  # NaN would spoil every statistic
            if (setting, condition, int(seed)) in done:
                raise ValueError(f"cell ({setting!r}, {condition!r}, seed={seed}) is already in {self.path}.")
            if frames is not None and len(frames) != len(returns):
                raise ValueError(f"frames has {len(frames)} entries but returns has {len(returns)}.")
            done.add((setting, condition, int(seed)))
            for i, r in enumerate(returns):
                lines.append([setting, condition, int(seed), i, float(r), "" if frames is None else int(frames[i])])
        if not lines:
            return
        with open(self.path, newline="") as f:
            existing = f.read()
        with atomic_replace(self.path) as tmp, open(tmp, "w", newline="") as f:
            f.write(existing)
            csv.writer(f).writerows(lines)
            f.flush()
            os.fsync(f.fileno())

    def returns(self, setting: str, condition: str) -> dict[int, list[float]]:
        """``{seed: [return of episode 0, 1, ...]}`` for one setting and condition."""
        out: dict[int, list[float]] = defaultdict(list)
        for r in self.rows():
            if r["setting"] == setting and r["condition"] == condition:
                out[r["seed"]].append(r["return"])
        return dict(out)

    def settings_and_conditions(self) -> list[tuple[str, str]]:
        seen = []
        for r in self.rows():
            key = (r["setting"], r["condition"])
            if key not in seen:
                seen.append(key)
        return seen


def merge_results(destination: str | os.PathLike | ResultsLog, sources: Sequence[str | os.PathLike]) -> list[tuple[str, str, int]]:
    """Merges the cells of other ``results.csv`` files into ``destination`` (runs split over seeds or machines).

    Each (setting, condition, seed) cell of a source is appended whole unless the destination already has it;
    a cell found twice with the same episodes is kept once, a cell found twice with different episodes is an
    error (two runs of the same cell that disagree: nothing is written). Sources are read in order. Where runs
    recorded their settings (``settings.json`` beside ``results.csv``, see
    :func:`~torchrl_options.experiments.run_settings.check_run_settings`), they must agree, and the destination
    gets them.

    Args:
        destination (str, PathLike or ResultsLog): the merged ``results.csv`` (created if missing).
        sources (sequence of str or PathLike): the ``results.csv`` files to merge in.

    Returns:
        The cells added to ``destination``, in the order they were appended.

    Raises:
        ValueError: an empty ``sources``, a cell whose episodes differ between two files (named), or two runs whose
            recorded settings differ (each differing setting named).
        FileNotFoundError: a missing source file (named).

    Examples:
        >>> import os, tempfile
        >>> d = tempfile.mkdtemp()
        >>> ResultsLog(os.path.join(d, "a.csv")).append_cell("supervised", "A", 0, returns=[0.0, 1.0])
        >>> ResultsLog(os.path.join(d, "b.csv")).append_cell("supervised", "A", 1, returns=[1.0, 1.0])
        >>> merge_results(os.path.join(d, "all.csv"), [os.path.join(d, "a.csv"), os.path.join(d, "b.csv")])
        [('supervised', 'A', 0), ('supervised', 'A', 1)]
        >>> sorted(ResultsLog(os.path.join(d, "all.csv")).returns("supervised", "A"))
        [0, 1]
    """
    if isinstance(sources, (str, os.PathLike)) or not len(sources):
        raise ValueError(f"sources must be a non-empty list of results.csv paths, got {sources!r}.")
    dest = destination if isinstance(destination, ResultsLog) else ResultsLog(destination)
    settings = _agreed_settings([dest.path, *(os.fspath(s) for s in sources)])
    cells = {key: (*cell, dest.path) for key, cell in _cells(dest).items()}
    new: dict[tuple[str, str, int], tuple[list[float], list[int | None], str]] = {}
    for source in sources:
        source = os.fspath(source)
        if not os.path.isfile(source):
            raise FileNotFoundError(f"sources: no results file at {source!r}.")
        for key, (returns, frames) in _cells(ResultsLog(source)).items():
            if key in cells:
                if cells[key][0] != returns:
                    raise ValueError(
                        f"cell (setting={key[0]!r}, condition={key[1]!r}, seed={key[2]}) differs between "
                        f"{cells[key][2]!r} and {source!r}; remove one of them before merging."
                    )
                continue
            cells[key] = new[key] = (returns, frames, source)
    dest.append_cells(
        (*key, returns, None if any(f is None for f in frames) else frames) for key, (returns, frames, _) in new.items()
    )
    dest_dir = os.path.dirname(os.path.abspath(dest.path))
    if settings is not None and read_run_settings(dest_dir) is None:
        write_run_settings(dest_dir, settings)
    logger.info("merged %d cells into %s", len(new), dest.path)
    return list(new)


def _agreed_settings(paths: Sequence[str]) -> dict | None:
    """The settings recorded beside these ``results.csv`` files (None where none were), which must agree."""
    agreed, agreed_from = None, None
    for path in paths:
        settings = read_run_settings(os.path.dirname(os.path.abspath(path)))
        if settings is None:
            continue
        if agreed is None:
            agreed, agreed_from = settings, path
            continue
        diffs = settings_differences(agreed, settings)
        if diffs:
            raise ValueError(
                f"{agreed_from!r} and {path!r} come from runs with other settings: "
                f"{describe_differences(diffs, 'in the first', 'in the second')}. Merge only runs of one experiment."
            )
    return agreed


def _cells(log: ResultsLog) -> dict[tuple[str, str, int], tuple[list[float], list[int | None]]]:
    """``{(setting, condition, seed): (returns, frames)}``, episodes in order."""
    out: dict[tuple[str, str, int], tuple[list[float], list[int | None]]] = {}
    for row in sorted(log.rows(), key=lambda r: (r["setting"], r["condition"], r["seed"], r["episode"])):
        returns, frames = out.setdefault((row["setting"], row["condition"], row["seed"]), ([], []))
        returns.append(row["return"])
        frames.append(row["frames"])
    return out


def within(interval: tuple[float, float, float], low: float, high: float) -> tuple[float, float, float]:
    """``interval`` ``(mean, low, high)`` intersected with the range ``[low, high]`` the quantity can take.

    The mean of a quantity that lies in ``[low, high]`` does too, so the intersection keeps the interval's coverage
    (e.g. episode counts: a Student-t interval over 3 seeds can reach below 0).

    Examples:
        >>> within((329.0, -407.0, 1066.0), 50, 1000)
        (329.0, 50.0, 1000.0)
    """
    m, lo, hi = interval
    return m, float(min(max(lo, low), high)), float(max(min(hi, high), low))


def smooth(returns: Sequence[float], window: int) -> np.ndarray:
    """Trailing moving average (the first entries average what is there)."""
    x = np.asarray(returns, dtype=float)
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def episodes_to_reach(returns: Sequence[float], target: float, window: int) -> int | None:
    """The first episode count after which the ``window``-episode moving average reaches ``target``.

    Returns ``None`` when it never does.

    Examples:
        >>> episodes_to_reach([0, 0, 1, 1, 1, 1], target=1.0, window=2)
        4
    """
    check_int(window, "window", minimum=1)
    check_number(target, "target")
    s = smooth(returns, window)
    hit = np.nonzero(s >= target - 1e-12)[0]
    hit = hit[hit >= min(window, len(s)) - 1]
    return int(hit[0]) + 1 if hit.size else None


@dataclass
class ConditionSummary:
    """Per (setting, condition) figures over seeds."""

    setting: str
    condition: str
    num_seeds: int
    num_episodes: int
    final_return: tuple[float, float, float]
    episodes_to_baseline: tuple[float, float, float] | None
    reached: int


def _check_summary_settings(*, confidence: float, **windows: int) -> None:
    for name, value in windows.items():
        check_int(value, name, minimum=1)
    check_number(confidence, "confidence", lo=0.0, hi=1.0, lo_open=True, hi_open=True)


def condition_rank(condition_order: Sequence[str] | None) -> Callable[[str], tuple[int, str]]:
    """A sort key for condition names: those of ``condition_order`` in its order (e.g. the recipe's ``A, H1u,
    H1s``), then any other alphabetically; ``None``: alphabetical.

    Examples:
        >>> sorted(["H1s", "A", "H1u", "X"], key=condition_rank(["A", "H1u", "H1s"]))
        ['A', 'H1u', 'H1s', 'X']
    """
    order = {c: i for i, c in enumerate(condition_order or ())}
    return lambda condition: (order.get(condition, len(order)), condition)


def _return_curves(
    log: ResultsLog | Iterable[dict], condition_order: Sequence[str] | None = None
) -> tuple[dict[tuple[str, str], dict[int, list[float]]], list[tuple[str, str]]]:
    """Per ``(setting, condition)``, each seed's returns in episode order, and those keys in order: settings
    alphabetically, conditions by :func:`condition_rank`."""
    rows = log.rows() if isinstance(log, ResultsLog) else list(log)
    curves: dict[tuple[str, str], dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    order: list[tuple[str, str]] = []
    rank = condition_rank(condition_order)
    for r in sorted(rows, key=lambda r: (r["setting"], rank(r["condition"]), r["seed"], r["episode"])):
        key = (r["setting"], r["condition"])
        if key not in order:
            order.append(key)
        curves[key][r["seed"]].append(r["return"])
    return curves, order


def summarize(
    log: ResultsLog | Iterable[dict],
    *,
    baseline: str = "A",
    final_window: int = 100,
    smooth_window: int = 100,
    confidence: float = 0.95,
    condition_order: Sequence[str] | None = None,
) -> list[ConditionSummary]:
    """Per setting and condition: the mean final return and the episodes needed to reach the baseline's.

    The final return of a seed is its mean return over its last ``final_window`` episodes. The target of a
    setting is the baseline condition's mean final return; a seed reaches it at the first episode where its
    ``smooth_window`` moving average does. Seeds that never reach it count with their total number of episodes
    (so the figure is then a lower bound), and ``reached`` says how many did. Intervals are Student-t intervals over
    seeds (:func:`~torchrl_options.experiments.intervals.mean_interval`; one seed gives an unbounded interval), those
    of episode counts cut to the counts possible (from ``smooth_window`` to the number of episodes, :func:`within`).
    Rows come by setting, then in ``condition_order`` (:func:`condition_rank`; default alphabetical).

    Examples:
        >>> rows = [{"setting": "s", "condition": c, "seed": 0, "episode": i, "return": float(i >= n)}
        ...         for c, n in (("A", 6), ("H1u", 2)) for i in range(10)]
        >>> [(x.condition, x.episodes_to_baseline[0]) for x in summarize(rows, final_window=2, smooth_window=2)]
        [('A', 8.0), ('H1u', 4.0)]
        >>> print(summary_markdown(summarize(rows, final_window=2, smooth_window=2), final_window=2).splitlines()[2])
        | s | A | 1 | 10 | 1.000 [-inf, inf] | 8 [2, 10] | 1/1 |
    """
    _check_summary_settings(final_window=final_window, smooth_window=smooth_window, confidence=confidence)
    curves, order = _return_curves(log, condition_order)
    targets = {}
    for (setting, condition), seeds in curves.items():
        if condition == baseline:
            finals = [np.mean(v[-final_window:]) for v in seeds.values()]
            targets[setting] = float(np.mean(finals))
    out = []
    for setting, condition in order:
        seeds = curves[(setting, condition)]
        finals = [float(np.mean(v[-final_window:])) for v in seeds.values()]
        to_reach = None
        reached = 0
        if setting in targets:
            counts = []
            for v in seeds.values():
                n = episodes_to_reach(v, targets[setting], smooth_window)
                reached += n is not None
                counts.append(len(v) if n is None else n)
            lengths = [len(v) for v in seeds.values()]
            to_reach = within(mean_interval(counts, confidence=confidence), min(smooth_window, *lengths), max(lengths))
        out.append(
            ConditionSummary(
                setting=setting,
                condition=condition,
                num_seeds=len(seeds),
                num_episodes=max(len(v) for v in seeds.values()),
                final_return=mean_interval(finals, confidence=confidence),
                episodes_to_baseline=to_reach,
                reached=reached,
            )
        )
    return out


def _count(x: float) -> str:
    """An episode count, or an interval end of one, rounded (never "-0"; infinite ends as "-inf" / "inf")."""
    return str(round(x)) if np.isfinite(x) else str(x)


def summary_markdown(summaries: Sequence[ConditionSummary], *, baseline: str = "A", final_window: int = 100) -> str:
    """The summary table in Markdown (95% intervals: :data:`~torchrl_options.experiments.intervals.METHOD`)."""
    lines = [
        f"| setting | condition | seeds | episodes | final return (last {final_window}) [95% t-interval] | "
        f"episodes to reach {baseline}'s final return [95% t-interval] | seeds that reach it |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        m, lo, hi = s.final_return
        if s.episodes_to_baseline is None:
            reach = "n/a"
        else:
            em, elo, ehi = s.episodes_to_baseline
            reach = f"{_count(em)} [{_count(elo)}, {_count(ehi)}]"
        lines.append(
            f"| {s.setting} | {s.condition} | {s.num_seeds} | {s.num_episodes} | {m:.3f} [{lo:.3f}, {hi:.3f}] | "
            f"{reach} | {s.reached}/{s.num_seeds} |"
        )
    return "\n".join(lines) + "\n"


@dataclass
class BaselineComparison:
    """A condition against the baseline in one setting: the paired per-seed difference of final returns."""

    setting: str
    condition: str
    baseline: str
    num_seeds: int
    difference: tuple[float, float, float]
    verdict: str


def compare_to_baseline(
    log: ResultsLog | Iterable[dict],
    *,
    baseline: str = "A",
    final_window: int = 100,
    confidence: float = 0.95,
    condition_order: Sequence[str] | None = None,
) -> list[BaselineComparison]:
    """Per setting, every other condition against ``baseline`` on the seeds both ran: the mean and Student-t
    interval of the per-seed difference of final returns (mean return over the last ``final_window`` episodes),
    and its verdict, "ahead", "behind" or "no evidence either way"
    (:func:`~torchrl_options.experiments.intervals.paired_difference_interval`). Conditions come in
    ``condition_order`` (:func:`condition_rank`).

    Examples:
        >>> rows = [{"setting": "s", "condition": c, "seed": seed, "episode": i, "return": seed + gain}
        ...         for c, gain in (("A", 0.0), ("H1u", 0.5)) for seed in range(3) for i in range(4)]
        >>> [(c.condition, c.difference[0], c.verdict, c.num_seeds) for c in compare_to_baseline(rows)]
        [('H1u', 0.5, 'ahead', 3)]
    """
    _check_summary_settings(final_window=final_window, confidence=confidence)
    curves, order = _return_curves(log, condition_order)
    out = []
    for setting, condition in order:
        if condition == baseline or (setting, baseline) not in curves:
            continue
        ours, base = curves[(setting, condition)], curves[(setting, baseline)]
        seeds = sorted(set(ours) & set(base))
        if not seeds:
            continue
        diff = paired_difference_interval(
            [np.mean(ours[s][-final_window:]) for s in seeds], [np.mean(base[s][-final_window:]) for s in seeds],
            confidence,
        )
        out.append(BaselineComparison(setting, condition, baseline, len(seeds), diff, interval_verdict(diff)))
    return out


def comparison_markdown(comparisons: Sequence[BaselineComparison], *, final_window: int = 100) -> str:
    """The table of :func:`compare_to_baseline` in Markdown, naming the method and the seeds each verdict rests on.

    Examples:
        >>> c = BaselineComparison("supervised", "H1u", "A", 3, (0.18, 0.07, 0.29), "ahead")
        >>> print(comparison_markdown([c]).splitlines()[-1])
        | supervised | H1u - A | +0.180 [+0.070, +0.290] | ahead | 3 |
    """
    if not comparisons:
        return ""
    lines = [
        f"Paired by seed: per seed, the condition's final return (last {final_window} episodes) minus the baseline's; "
        "mean and 95% Student-t interval of those differences. Verdict "
        "\"ahead\" / \"behind\" when the interval lies above / below 0, \"no evidence either way\" when it "
        "contains 0.\n",
        "| setting | comparison | final-return difference [95% t-interval] | verdict | seeds |",
        "|---|---|---|---|---|",
    ]
    for c in comparisons:
        m, lo, hi = c.difference
        lines.append(
            f"| {c.setting} | {c.condition} - {c.baseline} | {m:+.3f} [{lo:+.3f}, {hi:+.3f}] | {c.verdict} | "
            f"{c.num_seeds} |"
        )
    return "\n".join(lines) + "\n"
