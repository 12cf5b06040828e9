"""The statistics and Markdown of the Atari RAM experiment: per game, a condition against a baseline (Student-t
intervals over seeds, paired differences), aggregates over games, greedy evaluations and option usage."""
from __future__ import annotations

import glob
import logging
import os
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from torchrl_options.checkpoints import load_json_file
from torchrl_options.checks import check_int, check_number
from torchrl_options.experiments.atari.conditions import _describe, _option_flags, CONDITIONS
from torchrl_options.experiments.intervals import interval_verdict, mean_interval, paired_difference_interval
from torchrl_options.experiments.results import ResultsLog

__all__ = [
    "AtariComparison",
    "atari_comparison",
    "atari_summary_markdown",
    "atari_summary_pairs",
    "atari_scores",
    "atari_aggregates",
    "greedy_evaluation_markdown",
    "option_usage_markdown",
    "demonstration_fit_markdown",
]

logger = logging.getLogger(__name__)


@dataclass
class AtariComparison:
    """A condition (``H1`` by default) against a baseline (``A`` by default) in one game, over seeds that finished
    both. (Fields are named for the paper's pair: ``options_*`` is ``condition``, ``baseline_*`` is ``baseline``.)

    ``*_episodes``: mean return over the phase-3 episodes (the paper's "learns faster": area under the curve);
    ``final_*``: mean over the last ``final_window`` episodes, both at equal episodes. ``*_frames``: mean return
    of the episodes ending within the first ``F`` frames after phase 1, ``F`` the smaller of the two conditions'
    phase-3 frame budgets in that seed (the demonstration frames count against conditions with options). Each is
    ``(mean, low, high)`` over seeds; ``diff_*`` is the paired difference ``condition - baseline``.
    """

    game: str
    num_seeds: int
    phase3_episodes: int
    baseline_episodes: tuple[float, float, float]
    options_episodes: tuple[float, float, float]
    diff_episodes: tuple[float, float, float]
    baseline_final: tuple[float, float, float]
    options_final: tuple[float, float, float]
    diff_final: tuple[float, float, float]
    baseline_frames: tuple[float, float, float]
    options_frames: tuple[float, float, float]
    diff_frames: tuple[float, float, float]
    equal_frames: float
    extra: dict = field(default_factory=dict)
    condition: str = "H1"
    baseline: str = "A"


def _ci_text(x: tuple[float, float, float]) -> str:
    """``(mean, low, high)`` as ``"mean [low, high]"``."""
    return f"{x[0]:.2f} [{x[1]:.2f}, {x[2]:.2f}]"


def _cell_infos(out_dir: str, pattern: str = "*") -> list[tuple[str, int, str, dict]]:
    """``(game, seed, condition, info)`` of the finished cells' json files
    ``<out_dir>/<game>/seed<s>/<pattern>.json``."""
    import glob

    infos = []
    for path in sorted(glob.glob(os.path.join(out_dir, "*", "seed*", f"{pattern}.json"))):
        parts = path.split(os.sep)
        infos.append((parts[-3], int(parts[-2][len("seed"):]), os.path.splitext(parts[-1])[0],
                      load_json_file(path, what="Atari cell info")))  # fmt: skip
    return infos


def _verdict_counts(diffs: Sequence[tuple[float, float, float]]) -> str:
    """``"ahead in a, behind in b, no evidence either way in c"`` for the paired differences ``diffs``."""
    verdicts = [interval_verdict(d) for d in diffs]
    return ", ".join(f"{v} in {verdicts.count(v)}" for v in ("ahead", "behind", "no evidence either way"))


def _seed_counts(counts: Sequence[int]) -> str:
    """``"3 seeds"`` or ``"2-8 seeds"``."""
    lo, hi = min(counts), max(counts)
    return f"{lo} seed{'s' if hi > 1 else ''}" if lo == hi else f"{lo}-{hi} seeds"


def atari_comparison(log: ResultsLog | Sequence[dict], *, phase1_episodes: int, final_window: int = 100,
                     confidence: float = 0.95, condition: str = "H1", baseline: str = "A") -> list[AtariComparison]:
    """Per game, ``condition`` against ``baseline`` at equal episodes and at equal frames: means over seeds with
    Student-t intervals (:func:`~torchrl_options.experiments.intervals.mean_interval`), and the differences paired by
    seed (:func:`~torchrl_options.experiments.intervals.paired_difference_interval`). The default is the paper's
    pair: options (``H1``) against actions only, continued (``A``).

    Examples:
        >>> rows = []
        >>> for seed in range(3):
        ...     for cond, gain in (("A", 0.0), ("H1", 1.0)):
        ...         for ep in range(6):  # 2 phase-1 episodes, 4 phase-3 episodes of 10 frames
        ...             r = 0.0 if ep < 2 else gain + seed
        ...             rows.append(dict(setting="Pong", condition=cond, seed=seed, episode=ep, frames=10 * (ep + 1),
        ...                              **{"return": r}))
        >>> [c] = atari_comparison(rows, phase1_episodes=2, final_window=2)
        >>> c.diff_episodes[0], c.diff_frames[0], c.num_seeds
        (1.0, 1.0, 3)
    """
    check_int(phase1_episodes, "phase1_episodes", minimum=0)
    check_int(final_window, "final_window", minimum=1)
    check_number(confidence, "confidence", lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    rows = log.rows() if isinstance(log, ResultsLog) else list(log)
    data: dict[str, dict[str, dict[int, list[tuple[float, int | None]]]]] = defaultdict(lambda: defaultdict(dict))
    for r in sorted(rows, key=lambda r: (r["setting"], r["condition"], r["seed"], r["episode"])):
        data[r["setting"]][r["condition"]].setdefault(r["seed"], []).append((r["return"], r.get("frames")))
    out = []
    for game, conds in data.items():
        if baseline not in conds or condition not in conds:
            continue
        seeds = sorted(set(conds[baseline]) & set(conds[condition]))
        if not seeds:
            continue
        per = defaultdict(list)
        budgets = []
        for s in seeds:
            a, h = conds[baseline][s][phase1_episodes:], conds[condition][s][phase1_episodes:]
            n = min(len(a), len(h))
            if n == 0:
                continue
            ra, rh = np.array([x[0] for x in a[:n]]), np.array([x[0] for x in h[:n]])
            w = min(final_window, n)
            per["A_ep"].append(ra.mean())
            per["H_ep"].append(rh.mean())
            per["A_fin"].append(ra[-w:].mean())
            per["H_fin"].append(rh[-w:].mean())
            start_a = conds[baseline][s][phase1_episodes - 1][1] if phase1_episodes else 0
            start_h = start_a or 0
            fa = np.array([x[1] for x in a[:n]], dtype=float) - (start_a or 0)
            fh = np.array([x[1] for x in h[:n]], dtype=float) - start_h
            budget = min(fa[-1], fh[-1])
            budgets.append(budget)
            # returns of the episodes finished within the common frame budget (at least the first one)
            per["A_fr"].append(ra[: max(int((fa <= budget).sum()), 1)].mean())
            per["H_fr"].append(rh[: max(int((fh <= budget).sum()), 1)].mean())
        if not per["A_ep"]:
            continue

        def ci(x):
            return mean_interval(x, confidence=confidence)

        d = lambda k1, k2: paired_difference_interval(per[k1], per[k2], confidence)  # noqa: E731
        out.append(
            AtariComparison(
                game=game,
                num_seeds=len(per["A_ep"]),
                phase3_episodes=min(len(conds[baseline][s]) for s in seeds) - phase1_episodes,
                baseline_episodes=ci(per["A_ep"]),
                options_episodes=ci(per["H_ep"]),
                diff_episodes=d("H_ep", "A_ep"),
                baseline_final=ci(per["A_fin"]),
                options_final=ci(per["H_fin"]),
                diff_final=d("H_fin", "A_fin"),
                baseline_frames=ci(per["A_fr"]),
                options_frames=ci(per["H_fr"]),
                diff_frames=d("H_fr", "A_fr"),
                equal_frames=float(np.mean(budgets)),
                condition=condition,
                baseline=baseline,
            )
        )
    return out


def atari_summary_markdown(comparisons: Sequence[AtariComparison], *, final_window: int = 100,
                           header: str | None = None) -> str:
    """The per-game table of :func:`atari_comparison` in Markdown, with a verdict per comparison and a count.

    ``comparisons`` should share one ``(condition, baseline)`` pair (one call per pair); the table names them. A
    verdict is "ahead" / "behind" when the 95% Student-t interval of the paired per-seed difference lies above /
    below 0, "no evidence either way" when it contains 0; the count line says how many seeds the verdicts rest on.
    """

    f = _ci_text
    c_name = comparisons[0].condition if comparisons else "H1"
    b_name = comparisons[0].baseline if comparisons else "A"
    lines = [header + "\n"] if header else []
    lines += [
        "Returns of phase 3 (after the shared phase 1), mean over seeds with 95% Student-t intervals over seeds. "
        f"`{c_name}`: {_describe(c_name)}; `{b_name}`: {_describe(b_name)}. Verdict of `{c_name}` against "
        f"`{b_name}`: \"ahead\" / \"behind\" when the 95% Student-t interval of the per-seed paired difference "
        f"{c_name} - {b_name} lies above / below 0, \"no evidence either way\" when it contains 0.\n",
        f"| game | seeds | phase-3 episodes | {b_name}, mean over episodes | {c_name}, mean over episodes | "
        f"{c_name} - {b_name} | verdict (equal episodes) | {b_name}, last {final_window} | {c_name}, last "
        f"{final_window} | {c_name} - {b_name} | equal frames (phase 3) | {b_name} at equal frames | {c_name} at "
        f"equal frames | {c_name} - {b_name} | verdict (equal frames) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ahead = 0
    for c in comparisons:
        ahead += c.diff_episodes[0] > 0
        lines.append(
            f"| {c.game} | {c.num_seeds} | {c.phase3_episodes} | {f(c.baseline_episodes)} | {f(c.options_episodes)} | "
            f"{f(c.diff_episodes)} | {interval_verdict(c.diff_episodes)} | {f(c.baseline_final)} | "
            f"{f(c.options_final)} | {f(c.diff_final)} | {c.equal_frames:.0f} | {f(c.baseline_frames)} | "
            f"{f(c.options_frames)} | {f(c.diff_frames)} | {interval_verdict(c.diff_frames)} |"
        )
    lines.append("")
    if comparisons:
        seeds = _seed_counts([c.num_seeds for c in comparisons])
        lines.append(
            f"`{c_name}` against `{b_name}` over {len(comparisons)} games, on {seeds} per game (Student-t intervals of "
            f"the paired per-seed differences): at equal episodes "
            f"{_verdict_counts([c.diff_episodes for c in comparisons])}; "
            f"at equal frames {_verdict_counts([c.diff_frames for c in comparisons])}. Mean difference above 0 at "
            f"equal episodes in {ahead} of {len(comparisons)} games."
        )
    return "\n".join(lines) + "\n"


def atari_summary_pairs(conditions: Iterable[str]) -> list[tuple[str, str]]:
    """The ``(condition, baseline)`` pairs to report for a sweep over ``conditions``, among those that ran.

    The paper's comparison (``H1`` vs ``A``) first; then every other options condition against ``A``; ``A0`` against
    ``A`` (what the reset costs); every options condition with a reset (no ``w``) against ``A0``; every options
    condition against ``H1``; and every condition ending in ``i`` or ``s`` after another letter against the same
    without that last letter.

    Examples:
        >>> atari_summary_pairs(["A", "H1", "A0"])
        [('H1', 'A'), ('A0', 'A'), ('H1', 'A0')]
        >>> atari_summary_pairs(["A", "H1", "H1w", "H1wi"])
        [('H1', 'A'), ('H1w', 'A'), ('H1wi', 'A'), ('H1w', 'H1'), ('H1wi', 'H1'), ('H1wi', 'H1w')]
    """
    if isinstance(conditions, str):
        raise TypeError(f"conditions must be an iterable of condition names, got the string {conditions!r}.")
    conditions = set(conditions)
    unknown = sorted(map(str, conditions - set(CONDITIONS)))
    if unknown:
        raise ValueError(f"conditions: unknown conditions {unknown}; expected some of {CONDITIONS}.")
    have = [c for c in CONDITIONS if c in conditions]
    options = [c for c in have if _option_flags(c) is not None]
    pairs = [("H1", "A")] + [(c, "A") for c in options if c != "H1"] + [("A0", "A")]
    pairs += [(c, "A0") for c in options if not _option_flags(c).warm]
    pairs += [(c, "H1") for c in options if c != "H1"]
    pairs += [(c, c[:-1]) for c in options if c[-1] in "is" and len(c) > 3]
    return [(c, b) for c, b in pairs if c in have and b in have]


def atari_scores(
    log: ResultsLog | Sequence[dict], *, phase1_episodes: int, conditions: Sequence[str] | None = None
) -> tuple[list[str], dict[str, np.ndarray]]:
    """Per condition, a score matrix ``[num_seeds, num_games]`` for :mod:`~torchrl_options.experiments.aggregates`:
    each run's mean training return over its phase-3 episodes (after ``phase1_episodes``).

    The games are those every condition ran (conditions that did not run at all are left out); a condition's seeds,
    those it finished in every one of these games. A condition with no such seed is left out.

    Returns:
        ``(games, {condition: scores})``.

    Examples:
        >>> rows = [dict(setting=g, condition=c, seed=s, episode=e, **{"return": float(e >= 2) * (s + (c == "H1"))})
        ...         for g in ("Pong", "Seaquest") for c in ("A", "H1") for s in range(3) for e in range(4)]
        >>> games, scores = atari_scores(rows, phase1_episodes=2)
        >>> games, scores["H1"].shape, scores["H1"][:, 0].tolist()
        (['Pong', 'Seaquest'], (3, 2), [1.0, 2.0, 3.0])
    """
    check_int(phase1_episodes, "phase1_episodes", minimum=0)
    rows = log.rows() if isinstance(log, ResultsLog) else list(log)
    returns: dict[tuple[str, str, int], list[tuple[int, float]]] = defaultdict(list)
    for r in rows:
        returns[(r["setting"], r["condition"], r["seed"])].append((r["episode"], r["return"]))
    score = {}
    for key, eps in returns.items():
        phase3 = [ret for _, ret in sorted(eps)][phase1_episodes:]
        if phase3:
            score[key] = float(np.mean(phase3))
    ran = list(dict.fromkeys(c for _, c, _ in score))
    names = ran if conditions is None else [c for c in conditions if c in ran]
    games = sorted(set.intersection(*({g for g, c, _ in score if c == name} for name in names)) if names else set())
    out = {}
    for name in names:
        seeds = sorted(set.intersection(*({s for g2, c, s in score if g2 == g and c == name} for g in games))
                       if games else set())
        if seeds:
            out[name] = np.array([[score[(g, name, s)] for g in games] for s in seeds])
        else:
            logger.warning("aggregates: condition %r has no seed finished in every game of %s; left out", name, games)
    return games, out


def atari_aggregates(
    log: ResultsLog | Sequence[dict],
    *,
    phase1_episodes: int,
    pairs: Sequence[tuple[str, str]],
    confidence: float = 0.95,
    num_resamples: int = 2000,
    seed: int = 0,
):
    """The aggregates over games of Agarwal et al. (2021) for the conditions of ``pairs``: interquartile mean,
    probability of improvement per ``(condition, baseline)`` pair and performance profiles, with stratified
    bootstrap intervals (:func:`~torchrl_options.experiments.aggregates.aggregate_scores`), of each run's mean
    phase-3 training return (:func:`atari_scores`), min-max normalised per game. ``None`` when no game has them.

    Examples:
        >>> rows = [dict(setting=g, condition=c, seed=s, episode=e, **{"return": float(e >= 2) * (s + 3 * (c == "H1"))})
        ...         for g in ("Pong", "Seaquest") for c in ("A", "H1") for s in range(3) for e in range(4)]
        >>> agg = atari_aggregates(rows, phase1_episodes=2, pairs=[("H1", "A")], num_resamples=200)
        >>> agg.tasks, agg.verdict(("H1", "A")), agg.improvement[("H1", "A")][0]
        (['Pong', 'Seaquest'], 'ahead', 1.0)
    """
    from torchrl_options.experiments.aggregates import aggregate_scores

    names = list(dict.fromkeys(c for pair in pairs for c in pair))
    games, scores = atari_scores(log, phase1_episodes=phase1_episodes, conditions=names)
    pairs = [(c, b) for c, b in pairs if c in scores and b in scores]
    if not games or not pairs:
        return None
    return aggregate_scores(scores, pairs, tasks=games, confidence=confidence, num_resamples=num_resamples,
                            seed=seed)


def greedy_evaluation_markdown(out_dir: str, pairs: Sequence[tuple[str, str]], *, phase1_episodes: int) -> str:
    """Markdown tables comparing conditions on their greedy evaluations (``AtariConfig.eval_every``), read from
    the finished cells' json files under ``out_dir``: per game and pair ``(condition, baseline)``, the mean over
    the phase-3 evaluation points (after ``phase1_episodes``) of each seed, and the paired difference over the seeds
    that ran both, with 95% Student-t intervals over seeds and a verdict ("ahead", "behind", "no evidence either
    way"). Empty when no cell was evaluated.

    Examples:
        >>> import json, os, tempfile
        >>> out = tempfile.mkdtemp()
        >>> for cond, value in (("A", 1.0), ("H1", 3.0)):
        ...     os.makedirs(os.path.join(out, "Pooyan", "seed0"), exist_ok=True)
        ...     evals = [[10, 10, 0.0], [20, 21, value], [30, 30, value]]
        ...     with open(os.path.join(out, "Pooyan", "seed0", f"{cond}.json"), "w") as f:
        ...         json.dump({"evaluations": evals}, f)
        >>> print(greedy_evaluation_markdown(out, [("H1", "A")], phase1_episodes=10).splitlines()[-3])
        | Pooyan | 1 | 2 | 1.00 [-inf, inf] | 3.00 [-inf, inf] | 2.00 [-inf, inf] | no evidence either way |
    """
    evals: dict[tuple[str, str], dict[int, float]] = defaultdict(dict)  # (game, condition) -> seed -> mean
    points: dict[tuple[str, str], int] = {}
    for game, seed, condition, info in _cell_infos(out_dir):
        phase3 = [e[2] for e in info.get("evaluations", []) if e[0] > phase1_episodes]
        if phase3:
            evals[(game, condition)][seed] = float(np.mean(phase3))
            points[(game, condition)] = len(phase3)
    text = ""
    for condition, baseline in pairs:
        games = sorted({g for g, c in evals if c == condition} & {g for g, c in evals if c == baseline})
        if not games:
            continue
        text += (
            f"\n## Greedy evaluation: {condition} vs {baseline}\n\nMean return of the greedy policy (options run as in "
            f"training) on the same freshly seeded games, averaged over the evaluations of phase 3, then over seeds "
            f"(95% Student-t intervals over seeds; verdict from the paired per-seed difference).\n\n"
            f"| game | seeds | evaluations | {baseline} | {condition} | {condition} - {baseline} | verdict |\n"
            "|---|---|---|---|---|---|---|\n"
        )
        ahead, diffs, counts = 0, [], []
        for game in games:
            a, b = evals[(game, condition)], evals[(game, baseline)]
            seeds = sorted(set(a) & set(b))
            if not seeds:
                continue
            ci_b = mean_interval([b[s] for s in seeds])
            ci_a = mean_interval([a[s] for s in seeds])
            diff = paired_difference_interval([a[s] for s in seeds], [b[s] for s in seeds])
            ahead += diff[0] > 0
            diffs.append(diff)
            counts.append(len(seeds))
            text += (f"| {game} | {len(seeds)} | {points[(game, condition)]} | {_ci_text(ci_b)} | {_ci_text(ci_a)} | "
                     f"{_ci_text(diff)} | {interval_verdict(diff)} |\n")
        text += (f"\n`{condition}` against `{baseline}` in greedy evaluation over {len(diffs)} games, on "
                 f"{_seed_counts(counts)} per game (Student-t intervals of the paired per-seed differences): "
                 f"{_verdict_counts(diffs)}. Mean difference above 0 in {ahead} of {len(diffs)} games.\n")
    return text


def option_usage_markdown(out_dir: str) -> str:
    """A Markdown table of the option usage recorded by the finished options cells (``H1...``) under ``out_dir``
    (mean over seeds of :func:`option_usage`); empty when there is none.

    Examples:
        >>> import json, os, tempfile
        >>> out = tempfile.mkdtemp()
        >>> os.makedirs(os.path.join(out, "Pooyan", "seed0"))
        >>> info = {"option_decision_share": 0.5, "option_step_share": 0.8, "mean_option_steps": 4.0}
        >>> with open(os.path.join(out, "Pooyan", "seed0", "H1.json"), "w") as f:
        ...     json.dump(info, f)
        >>> print(option_usage_markdown(out).splitlines()[-1])
        | Pooyan | H1 | 1 | 0.50 | 0.80 | 4.0 |
    """
    usage: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for game, _, condition, info in _cell_infos(out_dir, "H1*"):
        if "option_decision_share" in info:
            usage[(game, condition)].append(info)
    if not usage:
        return ""
    keys = ("option_decision_share", "option_step_share", "mean_option_steps")
    lines = [
        "| game | condition | seeds | decisions that start an option | env steps inside options | steps per option |",
        "|---|---|---|---|---|---|",
    ]
    for (game, condition), infos in sorted(usage.items()):
        means = [float(np.nanmean([i[k] for i in infos])) if any(np.isfinite(i[k]) for i in infos) else float("nan")
                 for k in keys]
        lines.append(f"| {game} | {condition} | {len(infos)} | {means[0]:.2f} | {means[1]:.2f} | {means[2]:.1f} |")
    return "\n".join(lines) + "\n"


def demonstration_fit_markdown(out_dir: str, *, tolerance: float = 0.05) -> str:
    """A Markdown table of phase 2 per game, from ``<out_dir>/<game>/seed<s>/phase2.json``: the greedy
    demonstrations' log-likelihood per step under the discovered options next to the epsilon-greedy demonstrator's
    own (the log-probability of its greedy actions, ``log(1 - eps + eps / A)``), how many seeds' options come within
    ``tolerance`` nats per step of it, the quality gate (seeds whose demonstrator was degenerate: demonstrations
    no better than a random policy), and how many of the ``K`` options DDO put to use: active on at least ``0.1 / K``
    of the demonstrations' steps (the posterior usage recorded as ``option_usage``, mean over seeds; DDO's own
    threshold for an unused option, :func:`~torchrl_options.discovery.options_in_use`), "not recorded" for
    runs made before it was. Empty when no seed has finished phase 2.

    Examples:
        >>> import json, os, tempfile
        >>> out = tempfile.mkdtemp()
        >>> for seed, ll in ((0, -0.03), (1, -0.2)):
        ...     os.makedirs(os.path.join(out, "Pooyan", f"seed{seed}"))
        ...     info = {"option_encoding": "one_hot", "options_log_likelihood_per_step": ll,
        ...             "demonstrator_log_likelihood_per_step": -0.04, "demo_returns": [3.0, 5.0],
        ...             "random_returns": [4.5], "degenerate_demonstrator": seed == 1, "num_options": 2,
        ...             "option_usage": [0.99, 0.01] if seed else [0.6, 0.4]}
        ...     with open(os.path.join(out, "Pooyan", f"seed{seed}", "phase2.json"), "w") as f:
        ...         json.dump(info, f)
        >>> print(demonstration_fit_markdown(out).splitlines()[-1])
        | Pooyan | one_hot | 2 | -0.115 [-0.200, -0.030] | -0.040 | 1 of 2 | 4.00 | 4.50 | 1 of 2 | 1.5 of 2 |
    """
    rows: dict[str, list[dict]] = defaultdict(list)
    for path in sorted(glob.glob(os.path.join(out_dir, "*", "seed*", "phase2.json"))):
        rows[os.path.basename(os.path.dirname(os.path.dirname(path)))].append(load_json_file(path, what="phase-2 info"))
    if not rows:
        return ""
    lines = [
        "| game | option encoding | seeds | options: log-likelihood per step (mean [min, max]) | demonstrator's own | "
        f"seeds within {tolerance} nats | demonstrations' mean return | random policy's | degenerate demonstrators | "
        "options in use (mean over seeds) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for game, infos in sorted(rows.items()):
        ll = [i["options_log_likelihood_per_step"] for i in infos]
        own = [i["demonstrator_log_likelihood_per_step"] for i in infos]
        within = sum(a >= b - tolerance for a, b in zip(ll, own))
        demo = float(np.mean([np.mean(i["demo_returns"]) for i in infos]))
        rand = [np.mean(i["random_returns"]) for i in infos if i.get("random_returns")]
        gated = [i for i in infos if i.get("degenerate_demonstrator") is not None]
        encodings = ", ".join(sorted({str(i.get("option_encoding", "bytes")) for i in infos}))
        lines.append(
            f"| {game} | {encodings} | {len(infos)} | {np.mean(ll):.3f} [{min(ll):.3f}, {max(ll):.3f}] | "
            f"{np.mean(own):.3f} | {within} of {len(infos)} | {demo:.2f} | "
            f"{f'{np.mean(rand):.2f}' if rand else 'not measured'} | "
            f"{sum(bool(i['degenerate_demonstrator']) for i in gated)} of {len(gated)} | {_options_in_use(infos)} |"
        )
    return "\n".join(lines) + "\n"


def _options_in_use(infos: Sequence[dict]) -> str:
    """``"<mean> of <K>"``: the options active on at least ``0.1 / K`` of the demonstrations' steps, mean over the
    seeds that recorded their ``option_usage`` (``"... (n seeds)"`` when not all did); ``"not recorded"`` when none
    did."""
    from torchrl_options.discovery import options_in_use

    recorded = [info["option_usage"] for info in infos if info.get("option_usage")]
    counts, sizes = [options_in_use(usage) for usage in recorded], {len(usage) for usage in recorded}
    if not counts:
        return "not recorded"
    text = f"{np.mean(counts):.1f} of {'/'.join(str(k) for k in sorted(sizes))}"
    return text if len(counts) == len(infos) else f"{text} ({len(counts)} seeds)"
