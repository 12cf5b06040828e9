"""Shared experiment plumbing: resumable results, summaries with Student-t intervals, paired comparisons, plots."""
import numpy as np
import pytest

from torchrl_options.experiments import (
    compare_to_baseline,
    comparison_markdown,
    episodes_to_reach,
    mean_interval,
    merge_results,
    plot_curves,
    ResultsLog,
    summarize,
    summary_markdown,
)


def test_results_log_is_resumable(tmp_path):
    path = tmp_path / "out" / "results.csv"
    log = ResultsLog(path)
    log.append_cell("s", "A", 0, [0.0, 1.0], frames=[10, 20])
    again = ResultsLog(path)  # a new run opens the same file
    assert again.is_done("s", "A", 0) and not again.is_done("s", "A", 1)
    with pytest.raises(ValueError, match="already"):
        again.append_cell("s", "A", 0, [1.0])
    again.append_cell("s", "H1u", 0, [2.0])
    rows = again.rows()
    assert [(r["condition"], r["episode"], r["return"], r["frames"]) for r in rows] == [
        ("A", 0, 0.0, 10), ("A", 1, 1.0, 20), ("H1u", 0, 2.0, None)
    ]
    with pytest.raises(ValueError, match="frames"):
        again.append_cell("s", "H1s", 0, [1.0, 2.0], frames=[1])


def test_append_cells_writes_all_or_nothing(tmp_path):
    log = ResultsLog(tmp_path / "results.csv")
    log.append_cells([("s", "A", 0, [0.0, 1.0], [1, 2]), ("s", "A", 1, [2.0], None)])
    assert log.returns("s", "A") == {0: [0.0, 1.0], 1: [2.0]}
    before = open(log.path).read()
    with pytest.raises(ValueError, match="already"):  # the second cell repeats the first: nothing is written
        log.append_cells([("s", "H1u", 0, [1.0], None), ("s", "H1u", 0, [1.0], None)])
    with pytest.raises(ValueError, match="frames"):
        log.append_cells([("s", "H1u", 0, [1.0], None), ("s", "H1s", 0, [1.0], [1, 2])])
    assert open(log.path).read() == before


def test_merge_results_joins_runs_split_over_seeds(tmp_path):
    a, b = ResultsLog(tmp_path / "a.csv"), ResultsLog(tmp_path / "b.csv")
    a.append_cell("s", "A", 0, [0.0, 1.0], frames=[10, 20])
    a.append_cell("s", "H1u", 0, [1.0, 1.0], frames=[10, 20])
    b.append_cell("s", "A", 1, [0.5, 0.5, 0.5])  # no frames column values
    b.append_cell("s", "A", 0, [0.0, 1.0], frames=[10, 20])  # the same cell again, identical: kept once
    dest = tmp_path / "out" / "results.csv"
    added = merge_results(dest, [a.path, b.path])
    assert added == [("s", "A", 0), ("s", "H1u", 0), ("s", "A", 1)]
    merged = ResultsLog(dest)
    assert merged.returns("s", "A") == {0: [0.0, 1.0], 1: [0.5, 0.5, 0.5]}
    assert [r["frames"] for r in merged.rows() if r["seed"] == 0 and r["condition"] == "A"] == [10, 20]
    # the merged summary is the summary of all the rows together
    rows = a.rows() + [r for r in b.rows() if r["seed"] == 1]
    assert summarize(merged, final_window=1, smooth_window=1) == summarize(rows, final_window=1, smooth_window=1)
    # merging again adds nothing; a source that disagrees on a cell is refused, and nothing is written
    assert merge_results(dest, [a.path, b.path]) == []
    c = ResultsLog(tmp_path / "c.csv")
    c.append_cell("s", "H1s", 3, [1.0])
    c.append_cell("s", "A", 1, [0.5, 0.5, 0.7])
    before = open(dest).read()
    with pytest.raises(ValueError, match=r"condition='A', seed=1\) differs"):
        merge_results(dest, [c.path])
    assert open(dest).read() == before
    with pytest.raises(FileNotFoundError, match="sources"):
        merge_results(dest, [tmp_path / "missing.csv"])
    with pytest.raises(ValueError, match="non-empty"):
        merge_results(dest, [])


def test_summary_intervals_are_t_intervals_over_seeds():
    finals = {0: 0.2, 1: 0.5, 2: 0.3}
    rows = [{"setting": "s", "condition": "A", "seed": seed, "episode": i, "return": v}
            for seed, v in finals.items() for i in range(4)]
    [a] = summarize(rows, final_window=2, smooth_window=2)
    assert a.final_return == pytest.approx(mean_interval(list(finals.values())))
    half = 4.302653 * np.std(list(finals.values()), ddof=1) / np.sqrt(3)  # t(0.975, 2) * s / sqrt(3)
    assert a.final_return[2] - a.final_return[0] == pytest.approx(half, rel=1e-6)


def test_episode_count_intervals_stay_within_the_possible_counts():
    # seed 0 reaches the target at once, seed 1 at episode 5, seed 2 never: counts 2, 5, 10 (its length)
    rows = [{"setting": "s", "condition": c, "seed": seed, "episode": i, "return": v}
            for seed, first in ((0, 0), (1, 3), (2, 99)) for c in ("A", "H1u") for i, v in
            enumerate([float(i >= first) for i in range(10)] if c == "H1u" else [1.0] * 10)]
    by = {x.condition: x for x in summarize(rows, final_window=2, smooth_window=2)}
    m, lo, hi = by["H1u"].episodes_to_baseline
    raw = mean_interval([2, 5, 10])
    assert m == pytest.approx(17 / 3) and raw[1] < 2 and raw[2] > 10  # the bare t-interval leaves [2, 10]
    assert (lo, hi) == (2.0, 10.0) and by["H1u"].reached == 2


def test_compare_to_baseline_pairs_by_seed(tmp_path):
    log = ResultsLog(tmp_path / "results.csv")
    gains = {0: 0.10, 1: 0.12, 2: 0.08, 3: 0.11}
    for seed, gain in gains.items():
        base = 0.3 * seed  # seeds differ a lot; the per-seed gain is small and steady
        log.append_cell("sup", "A", seed, [base] * 4)
        log.append_cell("sup", "H1u", seed, [base + gain] * 4)
        log.append_cell("sup", "H1s", seed, [base + (-1) ** seed * 0.2] * 4)
    log.append_cell("sup", "H1u", 9, [5.0] * 4)  # a seed A did not run: left out of the pairing
    log.append_cell("other", "H1u", 0, [1.0] * 4)  # a setting without the baseline: no comparison
    by = {c.condition: c for c in compare_to_baseline(log, final_window=2)}
    assert set(by) == {"H1u", "H1s"}
    assert by["H1u"].num_seeds == 4 and by["H1u"].verdict == "ahead"
    assert by["H1u"].difference == pytest.approx(mean_interval(list(gains.values())))
    assert by["H1s"].verdict == "no evidence either way" and by["H1s"].difference[0] == pytest.approx(0.0)
    worse = compare_to_baseline(log, baseline="H1u", final_window=2)
    assert {c.condition: c.verdict for c in worse} == {"A": "behind", "H1s": "no evidence either way"}
    table = comparison_markdown(list(by.values()), final_window=2)
    assert "Student-t" in table and "| sup | H1u - A | +0.103 [" in table and "| ahead | 4 |" in table


def test_episodes_to_reach():
    assert episodes_to_reach([0, 0, 0, 1, 1, 1, 1], 1.0, window=3) == 6
    assert episodes_to_reach([1, 1, 1], 1.0, window=1) == 1
    assert episodes_to_reach([0, 0.5], 1.0, window=1) is None


def test_summary_against_hand_computed_figures(tmp_path):
    log = ResultsLog(tmp_path / "results.csv")
    # actions only: slow ramp to 1; options: reach 1 after 3 episodes
    for seed in range(3):
        log.append_cell("sup", "A", seed, [0.0] * 6 + [1.0] * 4)
        log.append_cell("sup", "H1u", seed, [0.0] * 2 + [1.0] * 8)
    summaries = summarize(log, final_window=2, smooth_window=2)
    by = {s.condition: s for s in summaries}
    assert by["A"].final_return == (1.0, 1.0, 1.0)
    assert by["A"].episodes_to_baseline[0] == 8 and by["H1u"].episodes_to_baseline[0] == 4
    assert by["H1u"].reached == 3
    table = summary_markdown(summaries, final_window=2)
    assert "| sup | H1u | 3 | 10 | 1.000 [1.000, 1.000] | 4 [4, 4] | 3/3 |" in table


def test_plot_curves_writes_png(tmp_path):
    pytest.importorskip("matplotlib")
    log = ResultsLog(tmp_path / "results.csv")
    for seed in range(2):
        log.append_cell("sup", "A", seed, list(np.linspace(0, 1, 30)))
        log.append_cell("sup", "H1u", seed, list(np.linspace(0, 2, 30)))
    log.append_cell("sup", "H1s", 0, list(np.linspace(0, 2, 30)))  # one seed: no band
    from _figures import assert_explained, caption

    fig = plot_curves(log, tmp_path / "curves.png", smooth_window=5)
    data = (tmp_path / "curves.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert_explained(fig)
    assert "5 episodes (1/2 seeds per condition)" in caption(fig) and "95% Student-t interval" in caption(fig)
    [ax] = fig.axes
    assert "95% Student-t interval of the mean over seeds" in ax.get_title()
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["A: mean of 2 seeds", "A: 95% t-interval over 2 seeds", "H1s: mean of 1 seed",
                      "H1u: mean of 2 seeds", "H1u: 95% t-interval over 2 seeds"]


@pytest.mark.parametrize("backend", ["serial", "local"])
def test_sweep_runs_each_cell_once_and_resumes(tmp_path, backend):
    from torchrl_options.experiments.sweep import _constant_cell, Cell, run_sweep

    log = ResultsLog(tmp_path / "results.csv")
    cells = [Cell("toy", c, s) for c in ("A", "H1u") for s in range(2)]
    # a previous, killed run finished one cell
    log.append_cell("toy", "A", 0, [0.0, 0.0, 0.0])
    ran = run_sweep(_constant_cell, cells, log, backend=backend, num_workers=2)
    assert sorted(c.name for c in ran) == ["toy-A-seed1", "toy-H1u-seed0", "toy-H1u-seed1"]
    assert log.done_cells() == {(c.setting, c.condition, c.seed) for c in cells}
    assert log.returns("toy", "H1u") == {0: [0.0] * 3, 1: [1.0] * 3}
    assert run_sweep(_constant_cell, cells, log, backend=backend) == []


def _torchrl_level_cell(cell):
    """A cell that returns the level of TorchRL's logger in the process that runs it."""
    import logging

    from torchrl_options.experiments.sweep import CellResult

    return CellResult(returns=[float(logging.getLogger("torchrl").level)], frames=[1])


def test_local_workers_take_the_drivers_torchrl_log_level(tmp_path):
    """A quiet recipe silences TorchRL's console lines in the driver; the pool's workers get the same level."""
    import logging

    from torchrl_options.experiments.sweep import Cell, run_sweep

    logger = logging.getLogger("torchrl")
    before = logger.level
    logger.setLevel(logging.WARNING)
    try:
        log = ResultsLog(tmp_path / "results.csv")
        run_sweep(_torchrl_level_cell, [Cell("toy", "A", 0)], log, backend="local", num_workers=1)
    finally:
        logger.setLevel(before)
    assert log.returns("toy", "A") == {0: [float(logging.WARNING)]}


def test_sweep_on_ray_local_cluster(tmp_path):
    pytest.importorskip("ray")
    from torchrl_options.experiments.sweep import _constant_cell, Cell, run_sweep

    log = ResultsLog(tmp_path / "results.csv")
    cells = [Cell("toy", "A", s) for s in range(3)]
    assert len(run_sweep(_constant_cell, cells, log, backend="ray", num_workers=2)) == 3
    assert log.returns("toy", "A")[2] == [2.0] * 3


def test_sweep_bad_backend(tmp_path):
    from torchrl_options.experiments.sweep import _constant_cell, Cell, run_sweep

    with pytest.raises(ValueError, match="backend"):
        run_sweep(_constant_cell, [Cell("t", "A", 0)], ResultsLog(tmp_path / "r.csv"), backend="slurm")


# Figures re-derived from the results kept under results/: quoted on docs/experiments/gridworld.md (the GridWorld
# experiment log), the headline ones also in the README's results table.
KEPT_GRIDWORLD_FIGURES = [
    ("intervals_old_vs_new/four_rooms_default", {"A": "0.283 [0.147, 0.420]",
                                                 "H1u - A": "+0.180 [+0.072, +0.288] | ahead",
                                                 "H1s - A": "+0.167 [-0.045, +0.378] | no evidence either way"}),
    ("intervals_old_vs_new/four_rooms_dqn64", {"A": "0.340 [0.146, 0.534]",
                                               "H1u - A": "+0.067 [-0.271, +0.404] | no evidence"}),
    ("intervals_old_vs_new/four_rooms_default_1000", {"H2u": "0.830 [0.679, 0.981]",
                                                      "H2u - A": "+0.427 [+0.302, +0.552] | ahead"}),
    ("four_rooms_default", {"A": "0.260 [0.097, 0.423]", "H1u - A": "+0.170 [-0.033, +0.373] | no evidence",
                            "H1s - A": "+0.150 [+0.019, +0.281] | ahead"}),
    ("four_rooms_dqn64", {"A": "0.350 [0.284, 0.416]", "H1u - A": "+0.090 [-0.211, +0.391] | no evidence"}),
    ("four_rooms_paper_1000", {"A": "0.409 [0.356, 0.461]", "H1u": "0.777 [0.693, 0.860]",
                               "H1s": "0.507 [0.439, 0.575]", "H1u - A": "+0.368 [+0.262, +0.474] | ahead",
                               "H1s - A": "+0.099 [+0.030, +0.168] | ahead", "H2u": "1.091 [1.009, 1.172]",
                               "H2u - A": "+0.682 [+0.572, +0.792] | ahead",
                               "H2s": "0.782 [0.703, 0.861]", "H2s - A": "+0.373 [+0.285, +0.462] | ahead",
                               "exploration/A": "0.323 [0.280, 0.366]", "exploration/H1u": "0.323 [0.294, 0.353]",
                               "exploration/H1u - A": "+0.000 [-0.045, +0.045] | no evidence"}),
    ("four_rooms_paper_5000_A", {"A": "0.345 [0.310, 0.380]"}),
    ("three_rooms_paper_1000", {"exploration/A": "0.036 [0.023, 0.050]", "exploration/H1u": "0.011 [-0.004, 0.026]",
                                "exploration/H1u - A": "-0.026 [-0.039, -0.012] | behind"}),
    # protocol=ours (issue 49): the main job with discover_options' defaults; the exploration setting on the agent's
    # rewarded one-episode rollouts
    ("four_rooms_default_ours", {"A": "0.273 [0.195, 0.351]", "H1u": "2.998 [2.585, 3.412]", "H1s": "1.450 [1.221, 1.679]",
                                 "H1u - A": "+2.725 [+2.316, +3.134] | ahead", "H1s - A": "+1.177 [+0.920, +1.433] | ahead"}),
    ("four_rooms_exploration_ours", {"exploration/A": "0.323 [0.280, 0.366]", "exploration/H1u": "0.451 [0.390, 0.511]",
                                     "exploration/H2u": "0.439 [0.374, 0.504]",
                                     "exploration/H1u - A": "+0.127 [+0.057, +0.198] | ahead",
                                     "exploration/H2u - A": "+0.115 [+0.035, +0.195] | ahead"}),
    ("four_rooms_exploration_floor", {"exploration/A": "0.323 [0.280, 0.366]", "exploration/H1u": "0.493 [0.432, 0.555]",
                                      "exploration/H1u - A": "+0.170 [+0.098, +0.242] | ahead"}),
    ("three_rooms_ours_1000", {"exploration/A": "0.036 [0.023, 0.050]", "exploration/H1u": "0.033 [0.002, 0.064]",
                               "exploration/H1u - A": "-0.003 [-0.036, +0.029] | no evidence"}),
    ("four_rooms_exploration_variants/segdef", {"exploration/H1u": "0.480 [0.385, 0.575]",
                                                "exploration/H1u - A": "+0.134 [+0.074, +0.194] | ahead"}),
    ("four_rooms_exploration_variants/segdefH2", {"exploration/H2u": "0.434 [0.313, 0.555]",
                                                  "exploration/H2u - A": "+0.088 [-0.043, +0.219] | no evidence"}),
    ("four_rooms_exploration_variants/greedydef", {"exploration/H1u": "0.330 [0.304, 0.356]",
                                                   "exploration/H1u - A": "+0.007 [-0.122, +0.137] | no evidence"}),
    ("four_rooms_exploration_variants/segpaper", {"exploration/H1u": "0.422 [0.305, 0.539]",
                                                  "exploration/H1u - A": "+0.076 [-0.035, +0.187] | no evidence"}),
    ("four_rooms_exploration_variants/epsall", {"exploration/H1u": "0.393 [0.351, 0.434]",
                                                "exploration/H1u - A": "+0.070 [-0.053, +0.193] | no evidence"}),
]
SEEDS = {  # the others: 3
    "four_rooms_paper_1000": 15, "four_rooms_paper_5000_A": 15, "three_rooms_paper_1000": 10, "four_rooms_ppo_15seeds": 15,
    "four_rooms_default_ours": 6, "four_rooms_exploration_ours": 15, "four_rooms_exploration_floor": 15,
    "three_rooms_ours_1000": 10, "four_rooms_exploration_variants/segdef": 5,
    "four_rooms_exploration_variants/segdefH2": 5, "four_rooms_exploration_variants/greedydef": 4,
    "four_rooms_exploration_variants/segpaper": 5, "four_rooms_exploration_variants/epsall": 4,
}
KEPT_PPO_FIGURES = [  # quoted on docs/ppo.md, the paired ones in the README's results table
    ("four_rooms_ppo_15seeds", {"A": "0.517 [0.471, 0.563]", "H1u": "0.713 [0.665, 0.760]",
                                "H2u": "1.038 [0.967, 1.109]", "H1u - A": "+0.196 [+0.131, +0.261] | ahead",
                                "H2u - A": "+0.521 [+0.442, +0.601] | ahead"}),
]
NOT_QUOTED = {"0.340 [0.146, 0.534]"}  # recomputed from the kept run, not quoted on any page
README_HEADLINES = {"+0.150 [+0.019, +0.281]", "+0.170 [-0.033, +0.373]", "0.830 [0.679, 0.981]",
                    "+0.427 [+0.302, +0.552]", "+0.368 [+0.262, +0.474]",
                    "1.091 [1.009, 1.172]", "0.782 [0.703, 0.861]", "+0.000 [-0.045, +0.045]", "0.345 [0.310, 0.380]",
                    "-0.026 [-0.039, -0.012]", "0.273 [0.195, 0.351]", "+2.725 [+2.316, +3.134]", "+1.177 [+0.920, +1.433]",
                    "+0.127 [+0.057, +0.198]", "+0.115 [+0.035, +0.195]", "-0.003 [-0.036, +0.029]"}


@pytest.mark.parametrize("folder, expected", KEPT_GRIDWORLD_FIGURES + KEPT_PPO_FIGURES)
def test_kept_results_back_the_readme(tmp_path, folder, expected):
    """The GridWorld figures quoted in the docs and README, recomputed from the results kept under results/."""
    import gzip
    import os

    from torchrl_options.experiments.gridworld import write_summary

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with gzip.open(os.path.join(root, "results", *folder.split("/"), "results.csv.gz"), "rt") as f:
        (tmp_path / "results.csv").write_text(f.read())
    text = write_summary(tmp_path / "results.csv", tmp_path / "out", "kept", {"final_window": 100, "smooth_window": 50})
    for key, figure in expected.items():
        setting, name = key.split("/") if "/" in key else ("supervised", key)
        seeds = SEEDS.get(folder, 3)
        row = f"| {setting} | {name} |" if " - " in name else f"| {setting} | {name} | {seeds} |"
        assert any(line.startswith(row) and figure in line for line in text.splitlines()), (name, figure)


def test_kept_figures_are_quoted():
    """Each recomputed figure is the one its page quotes (signs aside: pages write [0.072, 0.288] for [+0.072, ...])."""
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def read(*parts):
        with open(os.path.join(root, *parts)) as f:
            return f.read().replace("+", "")

    page, readme = read("docs", "experiments", "gridworld.md"), read("README.md")
    figures = {figure.split(" |")[0] for _, expected in KEPT_GRIDWORLD_FIGURES for figure in expected.values()}
    assert README_HEADLINES <= figures
    for figure in sorted(figures - NOT_QUOTED):
        assert figure.replace("+", "") in page, f"{figure} is not on docs/experiments/gridworld.md"
    for figure in sorted(README_HEADLINES):
        assert figure.replace("+", "") in readme, f"{figure} is not in the README's results table"
    ppo = read("docs", "ppo.md")
    for name, expected in KEPT_PPO_FIGURES[0][1].items():
        figure = expected.split(" |")[0]
        assert figure.replace("+", "") in ppo, f"{figure} is not on docs/ppo.md"
        if " - " in name:
            assert figure.replace("+", "") in readme, f"{figure} is not in the README's results table"


@pytest.mark.parametrize("folder, expected", [
    ("four_rooms_paper_5000_A", "-0.063 [-0.118, -0.009]"),  # Adam 0.01: A declines from 1000 to 5000 episodes
    ("four_rooms_A_lr1e-3", "+0.043 [-0.031, +0.118]"),  # Adam 0.001: it does not
])
def test_kept_long_run_of_actions_only(folder, expected):
    """A after 5000 episodes minus A after 1000 (episodes 4900-5000 against 900-1000), paired by seed over the 15
    seeds of the kept run, as docs/experiments/gridworld.md quotes it."""
    import csv
    import gzip
    import os
    from collections import defaultdict

    from torchrl_options.experiments import mean_interval

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    returns = defaultdict(dict)
    with gzip.open(os.path.join(root, "results", folder, "results.csv.gz"), "rt") as f:
        for row in csv.DictReader(f):
            if row["condition"] == "A":
                returns[int(row["seed"])][int(row["episode"])] = float(row["return"])
    assert len(returns) == 15 and all(len(r) >= 5000 for r in returns.values())

    def window(r, start):
        return sum(r[e] for e in range(start, start + 100)) / 100

    diff = mean_interval([window(r, 4900) - window(r, 900) for r in returns.values()])
    assert "%+.3f [%+.3f, %+.3f]" % diff == expected
    with open(os.path.join(root, "docs", "experiments", "gridworld.md")) as f:
        assert expected in f.read()


def test_kept_usage_floor_against_no_floor():
    """The four-rooms exploration setting with ``discovery.usage_floor=0.5`` (issue 49) against the same protocol
    without it: the same A episode for episode, and H1u's paired difference as docs/experiments/gridworld.md quotes."""
    import csv
    import gzip
    import os

    from torchrl_options.experiments import paired_difference_interval

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def finals(folder, condition):
        with gzip.open(os.path.join(root, "results", folder, "results.csv.gz"), "rt") as f:
            rows = [r for r in csv.DictReader(f) if r["setting"] == "exploration" and r["condition"] == condition]
        by_seed = {}
        for r in rows:
            by_seed.setdefault(int(r["seed"]), []).append((int(r["episode"]), float(r["return"])))
        return {seed: sorted(v) for seed, v in by_seed.items()}

    floor, ours = finals("four_rooms_exploration_floor", "A"), finals("four_rooms_exploration_ours", "A")
    assert floor == {s: ours[s] for s in floor} and len(floor) == 15
    with_floor, without = finals("four_rooms_exploration_floor", "H1u"), finals("four_rooms_exploration_ours", "H1u")
    seeds = sorted(with_floor)
    mean, low, high = paired_difference_interval(
        [sum(x for _, x in with_floor[s][-100:]) / 100 for s in seeds], [sum(x for _, x in without[s][-100:]) / 100 for s in seeds]
    )
    figure = f"{mean:+.3f} [{low:+.3f}, {high:+.3f}]"
    assert figure == "+0.043 [-0.004, +0.089]"
    with open(os.path.join(root, "docs", "experiments", "gridworld.md")) as f:
        assert figure in f.read()
