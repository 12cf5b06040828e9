"""The Atari summary on synthetic results (no emulator): Student-t intervals paired by seed, verdicts worded "ahead" /
"behind" / "no evidence either way" with their seed counts, and the aggregates over games with their plot."""
import importlib.util
import os

import numpy as np
import pytest

from torchrl_options.experiments import mean_interval, paired_difference_interval
from torchrl_options.experiments.atari import (
    AtariConfig,
    atari_aggregates,
    atari_comparison,
    atari_scores,
    atari_summary_markdown,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GAMES = ["Atlantis", "Gopher", "Pooyan", "Seaquest", "SpaceInvaders"]
P1, P3 = 3, 6
#: per game, H1's gain over A: clearly ahead, clearly behind, and noise only
GAIN = {"Atlantis": 2.0, "Gopher": -2.0, "Pooyan": 0.0, "Seaquest": 2.0, "SpaceInvaders": 0.0}


def _rows(seeds=range(4), games=GAMES, noise=0.05):
    rng = np.random.default_rng(0)
    rows = []
    for game in games:
        for seed in seeds:
            base = 10.0 * seed + 100.0 * GAMES.index(game)  # seeds and games differ widely; pairing removes it
            for cond in ("A", "H1"):
                gain = 0.0 if cond == "A" else GAIN[game] + (rng.normal(0, 1.0) if GAIN[game] == 0.0 else 0.0)
                for ep in range(P1 + P3):
                    r = base if ep < P1 else base + gain + rng.normal(0, noise)
                    rows.append(dict(setting=game, condition=cond, seed=seed, episode=ep, frames=10 * (ep + 1),
                                     **{"return": r}))
    return rows


def test_comparison_intervals_are_paired_t_intervals():
    rows = _rows()
    comps = {c.game: c for c in atari_comparison(rows, phase1_episodes=P1, final_window=3)}
    assert list(comps) == GAMES and all(c.num_seeds == 4 for c in comps.values())
    per = {cond: [np.mean([r["return"] for r in rows if r["setting"] == "Gopher" and r["condition"] == cond
                           and r["seed"] == s and r["episode"] >= P1]) for s in range(4)] for cond in ("A", "H1")}
    gopher = comps["Gopher"]
    assert gopher.baseline_episodes == pytest.approx(mean_interval(per["A"]))
    assert gopher.diff_episodes == pytest.approx(paired_difference_interval(per["H1"], per["A"]))
    # the seeds' spread (10 per seed) would hide a gain of 2 unpaired; paired, it is clear
    assert gopher.options_episodes[2] > gopher.baseline_episodes[1]
    assert gopher.diff_episodes[2] < 0


def test_summary_markdown_words_verdicts_with_seed_counts_and_method():
    rows = _rows() + [r for r in _rows(seeds=[4, 5], games=["Atlantis"])]  # Atlantis has 6 seeds
    comps = atari_comparison(rows, phase1_episodes=P1, final_window=3)
    text = atari_summary_markdown(comps, final_window=3, header="## H1 vs A")
    verdicts = {line.split(" | ")[0][2:]: line.split(" | ")[6] for line in text.splitlines()
                if line.startswith("| ") and line.split(" | ")[0][2:] in GAMES}
    assert verdicts["Atlantis"] == "ahead" and verdicts["Seaquest"] == "ahead" and verdicts["Gopher"] == "behind"
    assert verdicts["Pooyan"] in ("no evidence either way", "ahead", "behind")
    assert "verdict (equal episodes)" in text and "verdict (equal frames)" in text
    assert "Student-t" in text and "n.s." not in text and "better" not in text
    count = text.strip().splitlines()[-1]
    assert "over 5 games, on 4-6 seeds per game" in count
    n_ahead = list(verdicts.values()).count("ahead")
    assert f"at equal episodes ahead in {n_ahead}, behind in {list(verdicts.values()).count('behind')}" in count
    one = atari_summary_markdown([c for c in comps if c.game == "Gopher"], final_window=3)
    assert "on 4 seeds per game" in one


def test_one_seed_is_no_evidence():
    comps = atari_comparison(_rows(seeds=[0]), phase1_episodes=P1, final_window=3)
    assert all(c.diff_episodes[1] == -np.inf for c in comps)
    text = atari_summary_markdown(comps, final_window=3)
    assert "no evidence either way in 5" in text and "on 1 seed per game" in text


def test_scores_and_aggregates_over_games():
    rows = _rows() + _rows(seeds=[7], games=["Pooyan"])  # a seed not finished in every game: left out
    games, scores = atari_scores(rows, phase1_episodes=P1)
    assert games == sorted(GAMES) and scores["A"].shape == (4, 5)
    assert scores["H1"][1, games.index("Gopher")] == pytest.approx(
        np.mean([r["return"] for r in rows if r["setting"] == "Gopher" and r["condition"] == "H1"
                 and r["seed"] == 1 and r["episode"] >= P1]))
    agg = atari_aggregates(rows, phase1_episodes=P1, pairs=[("H1", "A"), ("H2", "A")], num_resamples=300)
    assert list(agg.improvement) == [("H1", "A")]  # H2 did not run: its pair is left out
    assert agg.tasks == sorted(GAMES) and agg.num_runs == {"A": 4, "H1": 4}
    p, lo, hi = agg.improvement[("H1", "A")]
    assert 0.0 <= lo <= p <= hi <= 1.0
    assert atari_aggregates(rows, phase1_episodes=P1, pairs=[("H2", "A")]) is None


def test_recipe_writes_aggregates_and_their_plot(tmp_path):
    pytest.importorskip("matplotlib")
    from omegaconf import OmegaConf

    from torchrl_options.experiments import ResultsLog

    spec = importlib.util.spec_from_file_location("atari_ram_recipe", os.path.join(ROOT, "recipes", "atari_ram.py"))
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    log = ResultsLog(tmp_path / "results.csv")
    cells = {}
    for r in _rows():
        cells.setdefault((r["setting"], r["condition"], r["seed"]), []).append(r)
    for (game, cond, seed), rs in cells.items():
        log.append_cell(game, cond, seed, [r["return"] for r in rs], [r["frames"] for r in rs])
    cfg = OmegaConf.create({"preset_name": "synthetic", "final_window": 3, "smooth_window": 2})
    config = AtariConfig(phase1_episodes=P1, phase3_episodes=P3)
    recipe.write_outputs(log, str(tmp_path), cfg, config)
    summary = (tmp_path / "summary.md").read_text()
    assert "## Aggregates over games (Agarwal et al. 2021)" in summary
    assert "interquartile mean" in summary and "| H1 vs A |" in summary and "aggregates.png" in summary
    assert summary.index("## Aggregates") < summary.index("## H1 vs A")  # the aggregates first, per game after
    for png in ("aggregates.png", "curves.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"


def _kept_rows(folder, tmp_path):
    """The rows of a kept ``results.csv.gz``, read back by the recipes' own :class:`ResultsLog`."""
    import gzip

    from torchrl_options.experiments import ResultsLog

    with gzip.open(os.path.join(folder, "results.csv.gz"), "rt") as f:
        (tmp_path / "results.csv").write_text(f.read())
    return ResultsLog(tmp_path / "results.csv").rows()


def _seeds_within(folder) -> dict:
    """Per game, the "seeds within 0.05 nats" cell of the kept run's demonstration-fit table."""
    from torchrl_options.experiments.atari import demonstration_fit_markdown

    lines = [line.split("|")[1:-1] for line in demonstration_fit_markdown(folder).splitlines() if line.startswith("|")]
    column = [c.strip() for c in lines[0]].index("seeds within 0.05 nats")
    return {cells[0].strip(): cells[column].strip() for cells in lines[2:]}


def test_kept_cpu_vec_results(tmp_path):
    """The figures quoted on docs/experiments/atari_ram.md and in the README, recomputed from results/atari_cpu_vec/."""
    from torchrl_options.experiments.aggregates import aggregates_markdown
    from torchrl_options.experiments.atari import demonstration_fit_markdown

    folder = os.path.join(ROOT, "results", "atari_cpu_vec")
    rows = _kept_rows(folder, tmp_path)
    comparisons = {c.game: c for c in atari_comparison(rows, phase1_episodes=150, final_window=50)}
    assert set(comparisons) == set(GAMES) and all(c.num_seeds == 4 for c in comparisons.values())

    def fmt(interval):
        mean, low, high = interval
        return f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]"

    assert fmt(comparisons["Atlantis"].diff_episodes) == "-0.28 [-0.48, -0.08]"
    assert fmt(comparisons["Pooyan"].diff_episodes) == "-2.85 [-6.01, +0.30]"
    assert all(c.diff_episodes[0] < 0 for c in comparisons.values())  # H1 below A in every game
    behind = [g for g, c in comparisons.items() if c.diff_episodes[2] < 0]
    ahead = [g for g, c in comparisons.items() if c.diff_episodes[1] > 0]
    assert behind == ["Atlantis"] and ahead == []
    aggregates = aggregates_markdown(atari_aggregates(rows, phase1_episodes=150, pairs=[("H1", "A")]), score_name="x")
    for figure in ("0.727 [0.620, 0.806]", "0.361 [0.140, 0.578]", "0.24 [0.09, 0.39]"):
        assert figure in aggregates
    within = _seeds_within(folder)
    assert within == {game: "4 of 4" for game in GAMES}  # every seed within 0.05 nats of its demonstrator
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    for figure in ("-0.28 [-0.48, -0.08]", "0.727 [0.620, 0.806]", "0.361 [0.140, 0.578]", "0.24 [0.09, 0.39]"):
        assert figure in readme and figure in page


def test_kept_cpu_vec_paper_env_results(tmp_path):
    """The figures quoted on docs/experiments/atari_ram.md for the run with the paper's env semantics, recomputed
    from results/atari_cpu_vec_paper_env/."""
    from torchrl_options.experiments.aggregates import aggregates_markdown

    rows = _kept_rows(os.path.join(ROOT, "results", "atari_cpu_vec_paper_env"), tmp_path)
    comparisons = {c.game: c for c in atari_comparison(rows, phase1_episodes=150, final_window=50)}
    mean, low, high = comparisons["SpaceInvaders"].diff_episodes
    assert f"{mean:+.1f} [{low:+.1f}, {high:+.1f}]" == "+14.6 [-18.6, +47.8]"
    assert all(c.diff_episodes[1] <= 0 <= c.diff_episodes[2] for c in comparisons.values())  # no verdict either way
    aggregates = aggregates_markdown(atari_aggregates(rows, phase1_episodes=150, pairs=[("H1", "A")]), score_name="x")
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    for figure in ("0.459 [0.381, 0.548]", "0.239 [0.075, 0.509]", "0.45 [0.28, 0.62]"):
        assert figure in aggregates and figure in page


def test_kept_ablation_results(tmp_path):
    """The one-at-a-time ablations on docs/experiments/atari_ram.md, recomputed by recipes/atari_ablation.py from
    the kept runs (each ablation's phase 1 checked against the reference's by the script)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("atari_ablation", os.path.join(ROOT, "recipes", "atari_ablation.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = os.path.join(ROOT, "results")
    ablations = [
        f"bytes={os.path.join(results, 'atari_cpu_vec_ablation_bytes')}",
        f"step={os.path.join(results, 'atari_cpu_vec_ablation_step')}",
        f"projenv={os.path.join(results, 'atari_cpu_vec_ablation_projenv')}",
    ]
    text = module.main([os.path.join(results, "atari_cpu_vec_paper_env_8seeds"), *ablations, "--phase1-episodes", "150"])
    rows = [line for line in text.splitlines() if line.startswith(("| bytes |", "| step |", "| projenv |"))]
    assert len(rows) == 3 * len(GAMES)
    # the encoding ablation ran the reference's 8 seeds
    assert all(line.split(" | ")[2] == "8" for line in rows if line.startswith("| bytes |"))
    # the bytes / 255 options fit their demonstrators within 0.05 nats on 10 of 40 game-seeds (one-hot: 34 of 40)
    within = _seeds_within(os.path.join(results, "atari_cpu_vec_ablation_bytes"))
    assert within == {"Atlantis": "3 of 8", "Gopher": "0 of 8", "Pooyan": "3 of 8", "Seaquest": "2 of 8",
                      "SpaceInvaders": "2 of 8"}  # fmt: skip
    # the project's env semantics: 8 seeds too, every options' fit within 0.05 nats
    assert all(line.split(" | ")[2] == "8" for line in rows if line.startswith("| projenv |"))
    assert set(_seeds_within(os.path.join(results, "atari_cpu_vec_ablation_projenv")).values()) == {"8 of 8"}
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    assert "10 of 40 game-seeds, against 34 of 40 one-hot" in page and "within 0.05 nats per step on 40 of\n  40" in page
    assert all(line.split(" | ")[2] == "8" for line in rows if line.startswith("| step |"))
    # every column of a row is on the ablation's seeds: the discount ablation cut to seeds 0-3 gives the same rows
    # against the 8-seed reference as against the 4-seed reference
    import gzip
    import shutil

    four = tmp_path / "step4"
    four.mkdir()
    shutil.copy(os.path.join(results, "atari_cpu_vec_ablation_step", "settings.json"), four)
    with gzip.open(os.path.join(results, "atari_cpu_vec_ablation_step", "results.csv.gz"), "rt") as f:
        lines = f.read().splitlines()
    seed = lines[0].split(",").index("seed")
    (four / "results.csv").write_text("\n".join([lines[0]] + [x for x in lines[1:] if int(x.split(",")[seed]) < 4]) + "\n")
    cut = [f"step={four}", "--phase1-episodes", "150"]
    rows8 = [r for r in module.main([os.path.join(results, "atari_cpu_vec_paper_env_8seeds"), *cut]).splitlines()
             if r.startswith("| step |")]  # fmt: skip
    rows4 = [r for r in module.main([os.path.join(results, "atari_cpu_vec_paper_env"), *cut]).splitlines()
             if r.startswith("| step |")]  # fmt: skip
    assert len(rows8) == len(GAMES) and {r.split(" | ")[2] for r in rows8} == {"4"} and rows8 == rows4
    # the env ablation sums clipped rewards: only its own H1 - A is compared, never its H1 with the reference's
    assert all("another reward scale" in line for line in rows if line.startswith("| projenv |"))
    for row in rows:
        assert row in page, row
    over_games = [line for line in text.splitlines()
                  if line.startswith(("| H1-bytes vs", "| H1-step vs", "| H1-projenv vs"))]  # fmt: skip
    assert len(over_games) == 5 and not any(line.startswith("| H1-projenv vs H1 ") for line in over_games)
    for line in over_games:
        assert line in page, line


def test_ablation_on_another_reward_scale_needs_its_own_baseline(tmp_path):
    """An ablation whose returns sum clipped rewards while the reference's are raw cannot borrow the reference's A."""
    import importlib.util
    import json
    import shutil

    spec = importlib.util.spec_from_file_location("atari_ablation", os.path.join(ROOT, "recipes", "atari_ablation.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = os.path.join(ROOT, "results")
    h1_only = tmp_path / "h1_only"
    h1_only.mkdir()
    shutil.copy(os.path.join(results, "atari_cpu_vec_ablation_bytes", "results.csv.gz"), h1_only)
    with open(os.path.join(results, "atari_cpu_vec_ablation_bytes", "settings.json")) as f:
        settings = json.load(f)
    (h1_only / "settings.json").write_text(json.dumps(dict(settings, **{"atari.env_semantics": "project"})))
    assert module.reward_scale(h1_only) == "clipped"
    assert module.reward_scale(os.path.join(results, "atari_cpu_vec_paper_env")) == "raw"
    with pytest.raises(SystemExit, match="another reward scale"):
        module.main([os.path.join(results, "atari_cpu_vec_paper_env"), f"clipped={h1_only}", "--phase1-episodes", "150"])
    with pytest.raises(FileNotFoundError, match="settings.json"):
        module.reward_scale(tmp_path)
    (tmp_path / "settings.json").write_text("{not json")
    with pytest.raises(ValueError, match="settings.json"):
        module.reward_scale(tmp_path)
    (tmp_path / "settings.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="JSON object"):
        module.reward_scale(tmp_path)


def test_kept_cpu_vec_paper_env_8_seeds(tmp_path):
    """The 8-seed run of the faithful protocol at the cpu-vec budget (seeds 0-3 are the 4-seed run's, kept apart):
    the figures quoted on docs/experiments/atari_ram.md and the README, recomputed from the kept results."""
    from torchrl_options.experiments.aggregates import aggregates_markdown

    rows = _kept_rows(os.path.join(ROOT, "results", "atari_cpu_vec_paper_env_8seeds"), tmp_path)
    comparisons = {c.game: c for c in atari_comparison(rows, phase1_episodes=150, final_window=50)}
    assert all(c.diff_episodes[1] <= 0 <= c.diff_episodes[2] for c in comparisons.values())  # no verdict either way
    mean, low, high = comparisons["Atlantis"].diff_episodes
    assert f"{mean:+.1f} [{low:+.1f}, {high:+.1f}]" == "-76.7 [-236.6, +83.2]"
    aggregates = aggregates_markdown(atari_aggregates(rows, phase1_episodes=150, pairs=[("H1", "A")]), score_name="x")
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    for figure in ("0.425 [0.389, 0.463]", "0.271 [0.138, 0.410]", "0.44 [0.32, 0.57]"):
        assert figure in aggregates and figure in page
    assert "0.44 [0.32, 0.57]" in readme
    within = _seeds_within(os.path.join(ROOT, "results", "atari_cpu_vec_paper_env_8seeds"))
    assert within == {"Atlantis": "8 of 8", "Gopher": "3 of 8", "Pooyan": "8 of 8", "Seaquest": "7 of 8",
                      "SpaceInvaders": "8 of 8"}  # fmt: skip
    # seeds 0-3 are the 4-seed run's cells, unchanged
    (tmp_path / "four").mkdir()
    four = _kept_rows(os.path.join(ROOT, "results", "atari_cpu_vec_paper_env"), tmp_path / "four")
    assert four and [r for r in rows if int(r["seed"]) < 4] == four


def test_kept_faithful_cpu(tmp_path):
    """The faithful protocol at cpu-vec's budget with a phase 2 that fits (preset faithful-cpu): the figures quoted
    on docs/experiments/atari_ram.md and the README, recomputed from results/atari_faithful_cpu/."""
    from torchrl_options.experiments.aggregates import aggregates_markdown
    from torchrl_options.experiments.atari import greedy_evaluation_markdown, option_usage_markdown

    folder = os.path.join(ROOT, "results", "atari_faithful_cpu")
    rows = _kept_rows(folder, tmp_path)
    seeds = sorted({int(r["seed"]) for r in rows})
    comparisons = {c.game: c for c in atari_comparison(rows, phase1_episodes=150, final_window=50)}
    assert set(comparisons) == set(GAMES) and all(c.num_seeds == len(seeds) for c in comparisons.values())
    assert all(c.diff_episodes[1] <= 0 <= c.diff_episodes[2] for c in comparisons.values())  # no verdict either way
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    section = page[page.index("### The faithful protocol with options that fit"):]
    for game, c in comparisons.items():
        mean, low, high = c.diff_episodes
        row = next(x for x in section.splitlines() if x.startswith(f"| {game} |"))
        assert f"| {mean:+.1f} [{low:+.1f}, {high:+.1f}] |" in row, game
    aggregates = aggregates_markdown(atari_aggregates(rows, phase1_episodes=150, pairs=[("H1", "A")]), score_name="x")
    line = next(x for x in aggregates.splitlines() if x.startswith("| H1 vs A |"))
    improvement = line.split(" | ")[1]
    assert improvement in section and improvement in readme
    # every seed of every game: the options within 0.05 nats per step of their demonstrator (the run's own record)
    assert _seeds_within(folder) == {game: f"{len(seeds)} of {len(seeds)}" for game in GAMES}
    # the greedy evaluations and the options' usage, as the page quotes them
    greedy = greedy_evaluation_markdown(folder, [("H1", "A")], phase1_episodes=150)
    usage = option_usage_markdown(folder)
    for table in (greedy, usage):
        game_rows = [x for x in table.splitlines() if x.startswith(tuple(f"| {g} |" for g in GAMES))]
        assert len(game_rows) == len(GAMES)
        for x in game_rows:
            assert x in section, x
    # the same phase 1 as the reference run (which ran cpu-vec's phase 2) on every game and seed, and the same A
    # episode for episode on the seeds both ran on today's code (the reference's seeds 0-3 are the 4-seed run's, on
    # the code of 2026-12-05: 5 of their 20 A cells part from it late in phase 3)
    (tmp_path / "reference").mkdir()
    reference = _kept_rows(os.path.join(ROOT, "results", "atari_cpu_vec_paper_env_8seeds"), tmp_path / "reference")

    def actions_only(table, keep):
        return sorted((r["setting"], int(r["seed"]), int(r["episode"]), float(r["return"]), int(r["frames"]))
                      for r in table if r["condition"] == "A" and int(r["seed"]) in seeds and keep(r))  # fmt: skip

    phase1 = actions_only(rows, lambda r: int(r["episode"]) < 150)
    assert phase1 == actions_only(reference, lambda r: int(r["episode"]) < 150)
    assert len(phase1) == len(GAMES) * len(seeds) * 150
    later = actions_only(rows, lambda r: int(r["seed"]) >= 4)
    assert later == actions_only(reference, lambda r: int(r["seed"]) >= 4) and len(later) == len(GAMES) * 4 * 450


def test_kept_faithful_cpu_usage_floor(tmp_path):
    """faithful-cpu with ``atari.ddo_usage_floor=0.5`` (issue 49): the figures quoted on docs/experiments/atari_ram.md
    and the README, recomputed from results/atari_faithful_cpu_floor/."""
    import json

    from torchrl_options.discovery import options_in_use
    from torchrl_options.experiments.aggregates import aggregates_markdown
    from torchrl_options.experiments.atari import greedy_evaluation_markdown, option_usage_markdown

    folder = os.path.join(ROOT, "results", "atari_faithful_cpu_floor")
    with open(os.path.join(folder, "settings.json")) as f:
        assert json.load(f)["atari.ddo_usage_floor"] == 0.5
    rows = _kept_rows(folder, tmp_path)
    seeds = sorted({int(r["seed"]) for r in rows})
    assert seeds == list(range(8))
    comparisons = {c.game: c for c in atari_comparison(rows, phase1_episodes=150, final_window=50)}
    assert set(comparisons) == set(GAMES) and all(c.num_seeds == 8 for c in comparisons.values())
    with open(os.path.join(ROOT, "docs", "experiments", "atari_ram.md")) as f:
        page = f.read()
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    start = page.index("### The faithful protocol with a usage floor")
    section = page[start:page.index("\n### ", start + 1)]
    for game, c in comparisons.items():
        mean, low, high = c.diff_episodes
        assert low <= 0 <= high, game  # no verdict in any game, as the page says
        row = next(x for x in section.splitlines() if x.startswith(f"| {game} |"))
        assert f"| {mean:+.1f} [{low:+.1f}, {high:+.1f}] |" in row, game
    aggregates = aggregates_markdown(atari_aggregates(rows, phase1_episodes=150, pairs=[("H1", "A")]), score_name="x")
    improvement = next(x for x in aggregates.splitlines() if x.startswith("| H1 vs A |")).split(" | ")[1]
    assert improvement == "0.47 [0.36, 0.59]" and improvement in section and improvement in readme
    # the floor's purpose: every fit puts K or K - 1 options to use, K on 38 of 40; 39 of 40 within 0.05 nats
    fits = []
    for game in GAMES:
        for seed in seeds:
            with open(os.path.join(folder, game, f"seed{seed}", "phase2.json")) as f:
                fits.append(json.load(f))
    in_use = [options_in_use(d["option_usage"]) for d in fits]
    assert len(fits) == 40 and all(n >= d["num_options"] - 1 for n, d in zip(in_use, fits))
    assert sum(n == d["num_options"] for n, d in zip(in_use, fits)) == 38
    largest = [max(d["option_usage"]) for d in fits]
    assert f"{min(largest):.0%}"[:-1] == "20" and f"{max(largest):.0%}"[:-1] == "83"
    within = _seeds_within(folder)
    assert within == {**{game: "8 of 8" for game in GAMES}, "Gopher": "7 of 8"}
    greedy = greedy_evaluation_markdown(folder, [("H1", "A")], phase1_episodes=150)
    for game, figure in (("SpaceInvaders", "17.95 [1.18, 34.72]"), ("Pooyan", "-31.88 [-52.81, -10.94]")):
        assert figure in next(x for x in greedy.splitlines() if x.startswith(f"| {game} |"))
    usage = option_usage_markdown(folder)
    durations = [float(x.split("|")[-2]) for x in usage.splitlines() if x.startswith(tuple(f"| {g} |" for g in GAMES))]
    assert (min(durations), max(durations)) == (3.6, 41.7) and "3.6-41.7 steps per option" in section
    # the same phase 1 as the run without the floor, episode for episode, on every game and seed
    (tmp_path / "reference").mkdir()
    reference = _kept_rows(os.path.join(ROOT, "results", "atari_faithful_cpu"), tmp_path / "reference")

    def phase1(table):
        return sorted((r["setting"], int(r["seed"]), int(r["episode"]), float(r["return"]), int(r["frames"]))
                      for r in table if r["condition"] == "A" and int(r["episode"]) < 150)  # fmt: skip

    assert phase1(rows) == phase1(reference) and len(phase1(rows)) == len(GAMES) * 8 * 150
