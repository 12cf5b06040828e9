"""Bad inputs of torchrl_options.experiments (issue 53's walk of the public API): sweeps, results, statistics,
summaries and the Atari experiment's helpers. One row per case (``call(tmp_path)``), controls included."""
import numpy as np
import pytest

from _bad_inputs import check, ids, OK
from torchrl_options.experiments import (
    aggregate_scores,
    Cell,
    CellResult,
    check_run_settings,
    compare_to_baseline,
    episodes_to_reach,
    interquartile_mean,
    interval_verdict,
    mean_interval,
    merge_results,
    paired_difference_interval,
    performance_profile,
    plot_curves,
    probability_of_improvement,
    ResultsLog,
    run_sweep,
    stratified_bootstrap_interval,
    summarize,
    summary_markdown,
)
from torchrl_options.experiments import atari as xa

NAN = float("nan")


def log(tmp_path, name="r.csv"):
    return ResultsLog(tmp_path / name)


def one_cell(_cell):
    return CellResult([1.0, 2.0])


CASES = [
    ("Cell", "seed a string", lambda t: Cell("s", "A", "0"), TypeError, "Cell: seed must be an int"),
    ("Cell", "seed negative", lambda t: Cell("s", "A", -1), ValueError, "Cell: seed must be an int >= 0"),
    ("Cell", "setting empty", lambda t: Cell("", "A", 0), TypeError, "Cell: setting must be a non-empty str"),
    ("Cell", "control: numpy seed", lambda t: Cell("s", "A", np.int64(3)), OK, None),
    ("CellResult", "frames of another length", lambda t: CellResult([1.0, 2.0], [1]), ValueError,
     "CellResult: frames has 1 entries but returns has 2"),
    ("CellResult", "a NaN return", lambda t: CellResult([NAN]), ValueError, "CellResult: returns[0] must be a number, got nan"),
    ("CellResult", "info not a dict", lambda t: CellResult([1.0], info=[1]), TypeError, "info must be a dict"),
    ("run_sweep", "backend unknown (even with nothing to run)", lambda t: run_sweep(one_cell, [], log(t), backend="gpu"), ValueError,
     "backend must be one of ('serial', 'local', 'ray'), got 'gpu'"),
    ("run_sweep", "num_workers 0", lambda t: run_sweep(one_cell, [], log(t), backend="local", num_workers=0), ValueError,
     "num_workers must be an int >= 1"),
    ("run_sweep", "fn not callable", lambda t: run_sweep(3, [Cell("s", "A", 0)], log(t)), TypeError, "fn must be a callable"),
    ("run_sweep", "cells that are not Cells", lambda t: run_sweep(one_cell, [3], log(t)), TypeError, "cells[0] must be a Cell, got int"),
    ("run_sweep", "a cell twice", lambda t: run_sweep(one_cell, [Cell("s", "A", 0)] * 2, log(t)), ValueError,
     "cells must not repeat a cell"),
    ("run_sweep", "fn returns no CellResult", lambda t: run_sweep(lambda c: None, [Cell("s", "A", 0)], log(t)), TypeError,
     "fn must return a CellResult, it returned NoneType for cell s-A-seed0"),
    ("run_sweep", "log not a ResultsLog", lambda t: run_sweep(one_cell, [], str(t / "r.csv")), TypeError, "log must be a ResultsLog"),
    ("run_sweep", "control: one cell", lambda t: run_sweep(one_cell, [Cell("s", "A", 0)], log(t)), OK, None),
    ("ResultsLog.append_cell", "a NaN return", lambda t: log(t).append_cell("s", "A", 0, [NAN]), ValueError, "returns[0] must be a number"),
    ("ResultsLog.append_cell", "no return (the cell would never count as done)", lambda t: log(t).append_cell("s", "A", 0, []), ValueError,
     "returns must not be empty"),
    ("ResultsLog.append_cell", "seed a string", lambda t: log(t).append_cell("s", "A", "x", [1.0]), TypeError, "seed must be an int"),
    ("ResultsLog.append_cell", "control: a setting with a comma (quoted)",
     lambda t: (log(t).append_cell("s,x", "A", 0, [1.0]), log(t).rows()[0]["setting"] == "s,x"), OK, None),
    ("ResultsLog", "path of another type", lambda t: ResultsLog(3), TypeError, "path must be a str or a path"),
    ("merge_results", "a missing source (named)", lambda t: merge_results(t / "m.csv", [t / "nope.csv"]), FileNotFoundError,
     "no results file at"),
    ("summarize", "final_window 0", lambda t: summarize([], final_window=0), ValueError, "final_window must be an int >= 1"),
    ("summarize", "confidence 2", lambda t: summarize([], confidence=2.0), ValueError, "confidence must be a number in (0, 1)"),
    ("compare_to_baseline", "final_window 0", lambda t: compare_to_baseline([], final_window=0), ValueError,
     "final_window must be an int >= 1"),
    ("summary_markdown", "control: no summary", lambda t: summary_markdown([]), OK, None),
    ("plot_curves", "smooth_window 0", lambda t: plot_curves(log(t), t / "c.png", smooth_window=0), ValueError,
     "smooth_window must be an int >= 1"),
    ("episodes_to_reach", "window 0", lambda t: episodes_to_reach([1.0, 2.0], 1.0, 0), ValueError, "window must be an int >= 1"),
    ("episodes_to_reach", "target NaN", lambda t: episodes_to_reach([1.0, 2.0], NAN, 1), ValueError, "target must be a number"),
    ("episodes_to_reach", "control: never reached", lambda t: episodes_to_reach([0.0, 0.0], 1.0, 1), OK, None),
    ("check_run_settings", "settings not a mapping", lambda t: check_run_settings(t / "rs", 3), TypeError, "settings must be a mapping"),
    ("check_run_settings", "allow_changes a string", lambda t: check_run_settings(t / "rs", {}, allow_changes="no"), TypeError,
     "allow_changes must be True or False"),
    ("mean_interval", "empty", lambda t: mean_interval([]), ValueError, "values needs at least one value"),
    ("mean_interval", "a NaN", lambda t: mean_interval([1.0, NAN]), ValueError, "values must be finite"),
    ("mean_interval", "confidence 2", lambda t: mean_interval([1.0, 2.0], 2.0), ValueError, "confidence"),
    ("paired_difference_interval", "lengths differ", lambda t: paired_difference_interval([1.0, 2.0], [1.0]), ValueError,
     "values and baseline must hold one value per seed"),
    ("interval_verdict", "not a triple", lambda t: interval_verdict((1.0, 2.0)), ValueError, "interval must be (mean, low, high)"),
    ("interval_verdict", "control: one seed's unbounded interval", lambda t: interval_verdict((NAN, NAN, NAN)), OK, None),
    ("interquartile_mean", "empty", lambda t: interquartile_mean([]), ValueError, "scores must be a non-empty array"),
    ("performance_profile", "no threshold", lambda t: performance_profile([1.0], []), ValueError, "thresholds must be a non-empty"),
    ("probability_of_improvement", "empty scores", lambda t: probability_of_improvement([], [1.0]), ValueError,
     "scores must be a non-empty array"),
    ("stratified_bootstrap_interval", "confidence 1.5", lambda t: stratified_bootstrap_interval(np.mean, [1.0, 2.0], confidence=1.5),
     ValueError, "confidence"),
    ("stratified_bootstrap_interval", "statistic not callable", lambda t: stratified_bootstrap_interval(3, [1.0, 2.0]), TypeError,
     "statistic must be a callable"),
    ("aggregate_scores", "no score", lambda t: aggregate_scores({}, []), ValueError, "scores must map at least one algorithm"),
    ("atari_cells", "a game name where a list is expected (one cell per letter before)", lambda t: xa.atari_cells("Pong", 1), ValueError,
     "games must be a non-empty list of game names"),
    ("atari_cells", "no game", lambda t: xa.atari_cells([], 1), ValueError, "games must be a non-empty list"),
    ("atari_cells", "seeds 0", lambda t: xa.atari_cells(["Pong"], 0), ValueError, "seeds must be an int >= 1"),
    ("atari_cells", "seeds an empty list", lambda t: xa.atari_cells(["Pong"], []), ValueError, "seeds must be a count >= 1"),
    ("atari_cells", "conditions a string", lambda t: xa.atari_cells(["Pong"], 1, "A"), ValueError, "got the string 'A'"),
    ("atari_cells", "control: a list of seeds", lambda t: xa.atari_cells(["Pong"], [3, 5], ["A"]), OK, None),
    ("atari_summary_pairs", "an unknown condition (left out silently before)", lambda t: xa.atari_summary_pairs(["A", "Z"]), ValueError,
     "conditions: unknown conditions ['Z']"),
    ("atari_comparison", "phase1_episodes negative", lambda t: xa.atari_comparison([], phase1_episodes=-1), ValueError,
     "phase1_episodes must be an int >= 0"),
    ("atari_scores", "phase1_episodes a float", lambda t: xa.atari_scores([], phase1_episodes=1.5), TypeError, "phase1_episodes must be an int"),
    ("option_usage", "num_actions 0", lambda t: xa.option_usage(None, 0), ValueError, "num_actions must be an int >= 1"),
    ("option_usage", "not an agent", lambda t: xa.option_usage(None, 2), TypeError, "option_usage expects an agent with a replay buffer"),
    ("run_atari_cell", "an unknown condition", lambda t: xa.run_atari_cell(Cell("Pong", "Z", 0), config={}, out_dir=str(t)), ValueError,
     "condition must be one of"),
    ("AtariConfig", "num_envs=3, frames_per_batch=10", lambda t: xa.AtariConfig(num_envs=3, frames_per_batch=10), ValueError,
     "frames_per_batch must be a multiple of the number of envs (num_envs=3)"),
    ("AtariConfig", "vector_env a string", lambda t: xa.AtariConfig(vector_env="yes"), TypeError, "vector_env must be True or False"),
    ("AtariConfig", "device unknown", lambda t: xa.AtariConfig(device="tpu"), ValueError, "device must be a device name"),
    ("AtariConfig", "control: 8 envs, 256 frames per batch", lambda t: xa.AtariConfig(num_envs=8, frames_per_batch=256), OK, None),
    ("store_atari_config", "group not a string", lambda t: xa.store_atari_config(group=3), TypeError, "group must be a non-empty str"),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_experiments_bad_inputs(tmp_path, api, case, call, error, phrase):
    check(call, error, phrase, tmp_path)
