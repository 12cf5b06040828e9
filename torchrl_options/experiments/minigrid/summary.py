"""Tables of the MiniGrid segmentation measurements: means over seeds with 95% Student-t intervals
(:func:`~torchrl_options.experiments.mean_interval`), DDO next to the trivial baselines, and what the options held.

Records are the dicts of :func:`~torchrl_options.experiments.minigrid.segmentation.segmentation_cell`, one per
(level, method, seed), kept one JSON object per line (:func:`read_records`, :func:`append_record`).
"""
from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = [
    "append_record",
    "method_label",
    "read_records",
    "segmentation_summary",
    "segmentation_markdown",
    "composition_markdown",
    "coverage_markdown",
    "information_markdown",
]

_ROWS = ("ddo", "action_change", "random", "one_option")
_METRICS = ("label_accuracy", "f1_w1", "f1_w2", "precision_w2", "recall_w2", "boundary_rate")


def method_label(method: dict) -> str:
    """A short name of a method dict: ``"mlp K=5"``, ``"conv K=5 init=random"``, ...

    Examples:
        >>> method_label({"network": "mlp", "num_options": 5})
        'mlp K=5'
        >>> method_label({"network": "conv", "num_options": 3, "restarts": 2})
        'conv K=3 restarts=2'
    """
    rest = {k: v for k, v in method.items() if k not in ("network", "num_options")}
    text = f"{method.get('network', 'mlp')} K={method.get('num_options', 5)}"
    return text + "".join(f" {k}={v}" for k, v in sorted(rest.items(), key=lambda kv: kv[0]))


def read_records(path: str | Path) -> list[dict]:
    """The records of a ``.jsonl`` file (one JSON object per line; missing file: none)."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    with open(path) as f:
        for i, line in enumerate(f):
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError as err:
                raise ValueError(f"{path}: line {i + 1} is not JSON ({err}).") from None
    return out


def append_record(path: str | Path, record: dict) -> None:
    """Appends one record as a JSON line (the file and its folder are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")


def _groups(records: Iterable[dict]) -> dict[tuple[str, str], list[dict]]:
    """Records by (level, method label), in their order."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["level"], method_label(r["method"])), []).append(r)
    return groups


def _interval(values: Sequence[float]) -> tuple[float, float, float]:
    from torchrl_options.experiments import mean_interval

    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not vals:
        return (math.nan, math.nan, math.nan)
    if len(vals) == 1:
        return (float(vals[0]), -math.inf, math.inf)
    return tuple(float(x) for x in mean_interval(vals))


def segmentation_summary(records: Iterable[dict], granularity: str = "subgoal") -> dict:
    """Per (level, method): the number of seeds and, per row (``ddo`` and each baseline) and metric, the mean and
    95% Student-t interval over the seeds, ``(mean, low, high)``; also the usage of the most used option.

    Examples:
        >>> recs = [{"level": "L", "seed": s, "method": {"network": "mlp", "num_options": 2},
        ...          "subgoal": {r: {"label_accuracy": 0.5 + 0.1 * s, "f1_w2": 0.2} for r in _ROWS}
        ...          | {"composition": {"max_usage": 0.9}}} for s in range(3)]
        >>> out = segmentation_summary(recs)
        >>> cell = out[("L", "mlp K=2")]
        >>> cell["seeds"], [round(x, 3) for x in cell["ddo"]["label_accuracy"]]
        (3, [0.6, 0.352, 0.848])
    """
    out = {}
    for key, recs in _groups(records).items():
        recs = sorted(recs, key=lambda r: r["seed"])
        cell: dict = {"seeds": len(recs), "seed_list": [r["seed"] for r in recs]}
        for row in _ROWS:
            cell[row] = {m: _interval([r[granularity][row].get(m, math.nan) for r in recs]) for m in _METRICS}
        cell["max_usage"] = _interval([r[granularity]["composition"]["max_usage"] for r in recs])
        out[key] = cell
    return out


def _fmt(x: tuple[float, float, float]) -> str:
    mean, lo, hi = x
    if math.isnan(mean):
        return "-"
    if not math.isfinite(lo):
        return f"{mean:.3f}"
    return f"{mean:.3f} [{lo:.3f}, {hi:.3f}]"


def segmentation_markdown(records: Iterable[dict], granularity: str = "subgoal") -> str:
    """A Markdown table: per level and method, DDO's label accuracy, boundary F1 within +-1 and +-2, precision /
    recall within +-2 and boundary rate, each row followed by the baselines on the same data.

    Examples:
        >>> recs = [{"level": "L", "seed": s, "method": {"network": "mlp", "num_options": 2},
        ...          "subgoal": {r: {"label_accuracy": 0.5, "f1_w2": 0.2} for r in _ROWS}
        ...          | {"composition": {"max_usage": 0.9}}} for s in range(2)]
        >>> print(segmentation_markdown(recs).splitlines()[2][:40])
        | L | mlp K=2 | DDO | 2 | 0.500 [0.500,
    """
    summary = segmentation_summary(records, granularity)
    head = ("| level | method | labelling | seeds | label accuracy | boundary F1 +-1 | boundary F1 +-2 | precision +-2 "
            "| recall +-2 | boundary rate |\n|---|---|---|---|---|---|---|---|---|---|\n")
    names = {"ddo": "DDO", "action_change": "a boundary at every action change", "random": "random, at the true rate",
             "one_option": "one option everywhere"}  # fmt: skip
    lines = []
    for (level, label), cell in sorted(summary.items()):
        for row in _ROWS:
            c = cell[row]
            lines.append(f"| {level} | {label} | {names[row]} | {cell['seeds']} | " + " | ".join(
                _fmt(c[m]) for m in _METRICS) + " |")  # fmt: skip
    return head + "\n".join(lines) + "\n"


def composition_markdown(records: Iterable[dict], granularity: str = "subgoal") -> str:
    """What the options held, per record: usage per option (sorted), boundary rate against the reference's, mean
    segment length, the reference labels merged into one option, and how far the options are the bot's actions
    renamed (``action_agreement``, when recorded)."""
    lines = ["| level | method | seed | usage per option | options used | boundary rate (reference) | mean segment "
             "length (reference) | labels merged into one option | agreement with the actions |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(records, key=lambda r: (r["level"], method_label(r["method"]), r["seed"])):
        comp = r[granularity]["composition"]
        ddo = r[granularity]["ddo"]
        usage = ", ".join(f"{u:.2f}" for u in sorted(comp["usage"], reverse=True))
        merged = "; ".join(" + ".join(g) for g in comp["merged"]) or "none"
        agreement = f"{r['action_agreement']:.3f}" if "action_agreement" in r else "-"
        lines.append(
            f"| {r['level']} | {method_label(r['method'])} | {r['seed']} | {usage} | {comp['options_used']} | "
            f"{ddo['boundary_rate']:.3f} ({ddo['reference_rate']:.3f}) | {comp['mean_segment_length']:.1f} "
            f"({comp['reference_mean_segment_length']:.1f}) | {merged} | {agreement} |"
        )
    return "\n".join(lines) + "\n"


def coverage_markdown(records: Iterable[dict], granularity: str = "skill") -> str:
    """How whole each reference label stays, per level and method: the share of the label's steps that its
    majority option holds (``majority_option`` of the composition), mean with its 95% Student-t interval over the
    seeds, the smallest, and the number of seeds where no option holds half of it. Labels are sorted by their
    share of the steps, largest first, read from the compositions (per option, the labels holding 0.05 of its
    steps or more: a lower bound, shown as such). A label split over options costs best-matching label accuracy
    as a merge does: a matched option scores only the part of its label it holds.

    Examples:
        >>> comp = lambda h: {"usage": [0.6, 0.4], "contents": [{"a": 0.9, "b": 0.1}, {"b": 1.0}],
        ...                   "majority_option": {"a": [0, 1.0], "b": [1, h]}}
        >>> recs = [{"level": "L", "seed": s, "method": {"network": "conv"}, "skill": {"composition": comp(h)}}
        ...         for s, h in enumerate((0.8, 0.9))]
        >>> print(coverage_markdown(recs).splitlines()[3])
        | L | conv K=5 | b | 2 | 0.46 | 0.850 [0.215, 1.485] | 0.800 | 0 |
    """
    from torchrl_options.checks import check_choice
    from torchrl_options.experiments.minigrid.scoring import GRANULARITIES

    check_choice(granularity, "granularity", tuple(GRANULARITIES))
    lines = ["| level | method | label | seeds | share of the steps (at least) | share its best option holds | "
             "smallest | seeds under half |", "|---|---|---|---|---|---|---|---|"]
    for (level, label), recs in sorted(_groups(records).items()):
        shares: dict[str, list[float]] = {}
        held: dict[str, list[float]] = {}
        for r in recs:
            comp = r[granularity]["composition"]
            total: dict[str, float] = {}
            for usage, contents in zip(comp["usage"], comp["contents"]):
                for name, part in contents.items():
                    total[name] = total.get(name, 0.0) + usage * part
            for name, (_, part) in comp["majority_option"].items():
                held.setdefault(name, []).append(part)
                shares.setdefault(name, []).append(total.get(name, 0.0))
        for name in sorted(held, key=lambda n: (-sum(shares[n]) / len(shares[n]), n)):
            parts = held[name]
            lines.append(f"| {level} | {label} | {name} | {len(parts)} | {sum(shares[name]) / len(shares[name]):.2f} | "
                         f"{_fmt(_interval(parts))} | {min(parts):.3f} | {sum(p < 0.5 for p in parts)} |")
    return "\n".join(lines) + "\n"


def information_markdown(records: Iterable[dict]) -> str:
    """A Markdown table of :func:`~torchrl_options.experiments.minigrid.option_information` over seeds: per level and
    method, the share of each target's entropy that the option explains and the share of the turning steps held
    by one-sided options, means with 95% Student-t intervals. Records carry an ``"information"`` dict (those of
    ``benchmarks/diagnose_minigrid_options.py``, or segmentation records that have one).

    Examples:
        >>> info = lambda x: {"skill": x, "subgoal": x, "action": 0.2, "turn_side": 0.9, "direction": 0.0,
        ...                   "carrying": 0.1, "handed_turns": 0.8}
        >>> recs = [{"level": "L", "seed": s, "method": {"network": "conv"}, "information": info(0.1 * s)}
        ...         for s in range(3)]
        >>> print(information_markdown(recs).splitlines()[2][:45])
        | L | conv K=5 | 3 | 0.100 [-0.148, 0.348] |
    """
    from torchrl_options.experiments.minigrid.scoring import INFORMATION_TARGETS

    names = (*INFORMATION_TARGETS, "handed_turns")
    head = ("| level | method | seeds | " + " | ".join(n.replace("_", " ") for n in names) + " |\n"
            + "|---" * (3 + len(names)) + "|\n")
    lines = []
    for (level, label), recs in sorted(_groups(r for r in records if "information" in r).items()):
        cells = [_fmt(_interval([r["information"][n] for r in recs])) for n in names]
        lines.append(f"| {level} | {label} | {len(recs)} | " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"
