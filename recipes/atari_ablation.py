"""One divergence from the paper at a time: Atari runs that change one setting, against the run they ablate.

Each ablation is a run of ``recipes/atari_ram.py`` with the reference run's settings but one (its own ``out_dir``).
Its ``H1`` (and ``A``, when it ran one) are compared with the reference's ``H1``, per game and paired by seed
(Student-t intervals of the per-seed differences), and over games (probability of improvement, stratified
bootstrap), next to each run's own ``H1 - A``. An ablation that did not run ``A`` (``"conditions=[H1]"``: a setting
that does not touch the actions-only agent, such as the options' encoding or the discount inside options) is
paired with the reference's ``A``, whose phase 1 it shares; the script checks that the phase-1 returns agree.
An ablation whose returns are on another reward scale than the reference's (the env semantics: clipped rewards
against the paper's raw ones, read from each run's ``settings.json``) needs its own ``A``: only its own
``H1 - A`` is compared, and its aggregates are computed apart.

    python recipes/atari_ablation.py results/atari_cpu_vec_paper_env bytes=outputs/abl_bytes \\
        step=outputs/abl_step projenv=outputs/abl_projenv --phase1-episodes 150 --out outputs/ablations
"""
import argparse
import gzip
import json
import logging
import tempfile
from pathlib import Path

from torchrl_options.experiments import ResultsLog
from torchrl_options.experiments.aggregates import aggregates_markdown
from torchrl_options.experiments.atari import atari_aggregates, atari_comparison
from torchrl_options.experiments.intervals import interval_verdict


def read_rows(folder: Path) -> list[dict]:
    """A run's rows from ``results.csv`` or a kept ``results.csv.gz``, through :class:`ResultsLog`."""
    plain, packed = folder / "results.csv", folder / "results.csv.gz"
    if plain.exists():
        return ResultsLog(plain).rows()
    if not packed.exists():
        raise FileNotFoundError(f"{folder}: no results.csv or results.csv.gz")
    with tempfile.TemporaryDirectory() as tmp, gzip.open(packed, "rt") as f:
        path = Path(tmp) / "results.csv"
        path.write_text(f.read())
        return ResultsLog(path).rows()


def reward_scale(folder: str | Path) -> str:
    """``"raw"`` or ``"clipped"``: the rewards a run's returns sum, from its ``settings.json``."""
    path = Path(folder) / "settings.json"
    if not path.exists():
        raise FileNotFoundError(f"{folder}: no settings.json (needed to tell the run's reward scale)")
    try:
        settings = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(settings, dict):
        raise ValueError(f"{path}: expected a JSON object of settings, got {type(settings).__name__}")
    paper_env = settings.get("atari.env_semantics", "project") == "paper"
    return "raw" if paper_env or not settings.get("atari.clip_rewards", True) else "clipped"


def fmt(interval) -> str:
    return f"{interval[0]:+.2f} [{interval[1]:+.2f}, {interval[2]:+.2f}]"


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("reference", help="the reference run's directory (results.csv or results.csv.gz)")
    parser.add_argument("ablations", nargs="+", help="label=directory, one per ablation")
    parser.add_argument("--phase1-episodes", type=int, required=True)
    parser.add_argument("--final-window", type=int, default=50)
    parser.add_argument("--out", default=None, help="a directory for ablations.md")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    p1 = args.phase1_episodes
    reference = [r for r in read_rows(Path(args.reference)) if r["condition"] in ("A", "H1")]
    reference_scale = reward_scale(args.reference)
    rows = list(reference)
    ablations = []
    for item in args.ablations:
        label, sep, folder = item.partition("=")
        if not sep or not label or not folder:
            parser.error(f"ablations must be given as label=directory, got {item!r}")
        own = read_rows(Path(folder))
        has_a = any(r["condition"] == "A" for r in own)
        same_scale = reward_scale(folder) == reference_scale
        if not same_scale and not has_a:
            raise SystemExit(f"{label}: its returns are on another reward scale than the reference's; run it with A "
                             "(its own baseline)")  # fmt: skip
        for r in own:
            if r["condition"] in ("A", "H1"):
                rows.append(dict(r, condition=f"{r['condition']}-{label}"))
        if not has_a:  # shares the reference's phase 1: check it, then pair with the reference's A
            ref_p1 = {(r["setting"], r["seed"], r["episode"]): r["return"] for r in reference
                      if r["condition"] == "H1" and r["episode"] < p1}  # fmt: skip
            own_p1 = {(r["setting"], r["seed"], r["episode"]): r["return"] for r in own
                      if r["condition"] == "H1" and r["episode"] < p1}  # fmt: skip
            common = set(ref_p1) & set(own_p1)
            differ = sum(ref_p1[k] != own_p1[k] for k in common)
            if not common or differ:
                raise SystemExit(f"{label}: phase 1 differs from the reference's on {differ} of {len(common)} "
                                 "episodes; run it with A (its own baseline)")  # fmt: skip
        ablations.append((label, f"A-{label}" if has_a else "A", same_scale))

    lines = [
        f"# One divergence at a time, against `{args.reference}`\n",
        "Per game: mean phase-3 training return over the seeds both runs finished, and the paired per-seed "
        "difference with its 95% Student-t interval (verdict \"ahead\" / \"behind\" when it excludes 0). "
        "`H1 - A` is each run's own gap on the same seeds (an ablation without its own `A` uses the reference's, "
        "whose phase 1 it shares).\n",
        "| ablation | game | seeds | reference H1 | ablation H1 | ablation H1 - reference H1 | verdict | "
        "reference H1 - A | ablation H1 - A |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    pairs, apart = [], []
    for label, baseline, same_scale in ablations:
        # the reference's own H1 - A on the seeds this ablation ran, so that every column of a row has the same seeds
        seeds = {(r["setting"], r["seed"]) for r in rows if r["condition"] == f"H1-{label}"}
        ref_gap = {c.game: c for c in atari_comparison([r for r in reference if (r["setting"], r["seed"]) in seeds],
                                                       phase1_episodes=p1, final_window=args.final_window)}  # fmt: skip
        gap = {c.game: c for c in atari_comparison(rows, phase1_episodes=p1, final_window=args.final_window,
                                                   condition=f"H1-{label}", baseline=baseline)}  # fmt: skip
        if same_scale:
            effect = atari_comparison(rows, phase1_episodes=p1, final_window=args.final_window,
                                      condition=f"H1-{label}", baseline="H1")  # fmt: skip
            for c in effect:
                lines.append(
                    f"| {label} | {c.game} | {c.num_seeds} | {c.baseline_episodes[0]:.2f} | "
                    f"{c.options_episodes[0]:.2f} | {fmt(c.diff_episodes)} | {interval_verdict(c.diff_episodes)} | "
                    f"{fmt(ref_gap[c.game].diff_episodes) if c.game in ref_gap else '-'} | "
                    f"{fmt(gap[c.game].diff_episodes) if c.game in gap else '-'} |"
                )
            pairs += [(f"H1-{label}", "H1"), (f"H1-{label}", baseline)]
        else:  # returns on another reward scale: only the run's own H1 - A compares
            for game, c in gap.items():
                lines.append(
                    f"| {label} | {game} | {c.num_seeds} | "
                    f"{f'{ref_gap[game].options_episodes[0]:.2f}' if game in ref_gap else '-'} | "
                    f"{c.options_episodes[0]:.2f} (another reward scale) | - | {interval_verdict(c.diff_episodes)} "
                    f"(own H1 - A) | {fmt(ref_gap[game].diff_episodes) if game in ref_gap else '-'} | "
                    f"{fmt(c.diff_episodes)} |"
                )
            apart.append((label, [(f"H1-{label}", baseline)]))
    agg = atari_aggregates(rows, phase1_episodes=p1, pairs=[("H1", "A")] + pairs)
    if agg is not None:
        lines += ["", "## Over games", "", aggregates_markdown(agg, score_name="mean phase-3 training return")]
    for label, own_pairs in apart:
        agg = atari_aggregates(rows, phase1_episodes=p1, pairs=own_pairs)
        if agg is not None:
            lines += ["", f"## Over games, {label} (its own reward scale, normalised apart)", "",
                      aggregates_markdown(agg, score_name="mean phase-3 training return")]  # fmt: skip
    text = "\n".join(lines) + "\n"
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "ablations.md").write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
