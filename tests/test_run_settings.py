"""Recorded run settings: resuming an out_dir with other settings is refused, naming each one."""
import json
import logging
from pathlib import Path

import pytest

from torchrl_options.experiments import check_run_settings, merge_results, ResultsLog
from torchrl_options.experiments.run_settings import (
    flatten_settings,
    read_run_settings,
    settings_differences,
    SETTINGS_FILE,
)

SETTINGS = {"episodes": 200, "dqn": {"lr": 0.01, "hidden_sizes": [2]}, "seeds": 3, "backend": "serial"}


def test_first_run_records_and_same_settings_resume(tmp_path):
    out = tmp_path / "run"
    assert read_run_settings(out) is None
    assert check_run_settings(out, SETTINGS, ignore=["seeds", "backend"]) == {}
    recorded = json.loads((out / SETTINGS_FILE).read_text())
    assert recorded == {"episodes": 200, "dqn.lr": 0.01, "dqn.hidden_sizes": [2]}  # ignored keys not recorded
    # resuming: same settings, or other values of the ignored ones (more seeds, another backend)
    assert check_run_settings(out, SETTINGS, ignore=["seeds", "backend"]) == {}
    assert check_run_settings(out, {**SETTINGS, "seeds": [3, 4], "backend": "ray"}, ignore=["seeds", "backend"]) == {}
    # tuples (dataclass fields) and lists (yaml) are the same setting
    assert check_run_settings(out, {**SETTINGS, "dqn": {"lr": 0.01, "hidden_sizes": (2,)}}, ignore=["seeds", "backend"]) == {}
    assert json.loads((out / SETTINGS_FILE).read_text()) == recorded


def test_other_settings_are_refused_with_each_named(tmp_path):
    check_run_settings(tmp_path, SETTINGS, ignore=["seeds"])
    changed = {**SETTINGS, "episodes": 1000, "dqn": {"lr": 0.1, "hidden_sizes": [2]}, "extra": True}
    with pytest.raises(ValueError) as info:
        check_run_settings(tmp_path, changed, ignore=["seeds"])
    message = str(info.value)
    assert "dqn.lr: 0.01 there, 0.1 now" in message
    assert "episodes: 200 there, 1000 now" in message
    assert "extra: null there, true now" in message  # a setting the first run did not have
    assert str(tmp_path) in message and "another out_dir" in message
    assert read_run_settings(tmp_path)["episodes"] == 200  # nothing recorded on refusal
    # a setting dropped since is a difference too
    with pytest.raises(ValueError, match=r"dqn.hidden_sizes: \[2\] there, null now"):
        check_run_settings(tmp_path, {"episodes": 200, "dqn": {"lr": 0.01}}, ignore=["seeds"])


def test_allow_changes_logs_and_records_the_new_settings(tmp_path, caplog):
    check_run_settings(tmp_path, SETTINGS)
    changed = {**SETTINGS, "episodes": 1000}
    with caplog.at_level(logging.WARNING, logger="torchrl_options.experiments.run_settings"):
        diffs = check_run_settings(tmp_path, changed, allow_changes=True)
    assert diffs == {"episodes": (200, 1000)}
    assert "episodes: 200 there, 1000 now" in caplog.text
    assert check_run_settings(tmp_path, changed) == {}  # the new settings are the run's now
    with pytest.raises(ValueError, match="episodes: 1000 there, 200 now"):
        check_run_settings(tmp_path, SETTINGS)


def test_ignore_covers_a_key_and_what_is_below_it_only():
    flat = flatten_settings({"scale": {"name": "tiny", "four_rooms": {"seeds": 3}}, "scales": 1})
    assert flat == {"scale.name": "tiny", "scale.four_rooms.seeds": 3, "scales": 1}
    assert flatten_settings({"scale": {"name": "tiny"}, "scales": 1}, ignore=["scale"]) == {"scales": 1}
    # ignored keys are never serialised (a Path out_dir, say)
    assert flatten_settings({"out_dir": Path("/tmp"), "episodes": 3}, ignore=["out_dir"]) == {"episodes": 3}
    assert settings_differences({"scale": {"name": "a"}, "scales": 1}, {"scale": {"name": "b"}, "scales": 1}) == {
        "scale.name": ("a", "b")
    }


def test_check_run_settings_ignore_prefix(tmp_path):
    check_run_settings(tmp_path, {"scale": {"name": "a"}, "scales": 1}, ignore=["scale"])
    assert check_run_settings(tmp_path, {"scale": {"name": "b"}, "scales": 1}, ignore=["scale"]) == {}
    with pytest.raises(ValueError, match="scales: 1 there, 2 now"):
        check_run_settings(tmp_path, {"scale": {"name": "a"}, "scales": 2}, ignore=["scale"])


def test_merge_results_requires_agreeing_settings_and_passes_them_on(tmp_path):
    for seed, (name, lr) in enumerate((("run0", 0.01), ("run1", 0.01), ("other", 0.1))):
        check_run_settings(tmp_path / name, {"dqn": {"lr": lr}})
        ResultsLog(tmp_path / name / "results.csv").append_cell("s", "A", seed, [1.0, 2.0])
    dest = tmp_path / "merged" / "results.csv"
    with pytest.raises(ValueError, match=r"run0.*other.*dqn.lr: 0.01 in the first, 0.1 in the second"):
        merge_results(dest, [tmp_path / "run0" / "results.csv", tmp_path / "other" / "results.csv"])
    assert not ResultsLog(dest).rows() and read_run_settings(dest.parent) is None  # nothing written
    added = merge_results(dest, [tmp_path / "run0" / "results.csv", tmp_path / "run1" / "results.csv"])
    assert len(added) == 2 and read_run_settings(dest.parent) == {"dqn.lr": 0.01}
    # the merged run now refuses both another run's cells and a resume with other settings
    with pytest.raises(ValueError, match="dqn.lr"):
        merge_results(dest, [tmp_path / "other" / "results.csv"])
    with pytest.raises(ValueError, match="dqn.lr: 0.01 there, 0.1 now"):
        check_run_settings(dest.parent, {"dqn": {"lr": 0.1}})
