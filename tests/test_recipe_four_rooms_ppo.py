"""The four-rooms PPO recipe at the tiny scale: outputs, resume, refused settings (the command the docs give)."""
import csv
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def _cfg(out, *overrides):
    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        return compose("four_rooms_ppo", overrides=["scale=tiny", f"out_dir={out}", "progress=false", *overrides])


def test_four_rooms_ppo_recipe_tiny_and_resume(tmp_path):
    out = tmp_path / "ppo"
    spec = importlib.util.spec_from_file_location("recipe_four_rooms_ppo", RECIPES / "four_rooms_ppo.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    assert recipe.run(_cfg(out, "stop_after_cells=1")) is None  # stopped after one cell
    result = subprocess.run(  # the command line finishes the run
        [sys.executable, str(RECIPES / "four_rooms_ppo.py"), "scale=tiny", f"out_dir={out}", "progress=false"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    for condition in ("A", "H1u", "H2u"):
        assert f"| supervised | {condition} |" in result.stdout
    assert "| supervised | H1u - A |" in result.stdout
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {r["condition"] for r in rows} == {"A", "H1u", "H2u"}
    assert len([r for r in rows if r["condition"] == "A"]) == 16
    assert len((out / "cells" / "ran.txt").read_text().split()) == 3  # the finished cell was not run again
    assert (out / "cells" / "supervised-A-seed0" / "ppo.pt").exists()
    assert (out / "cells" / "supervised-seed0" / "hierarchy-K4x2-uniform.pt").exists()
    assert (out / "curves.png").exists() and (out / "summary.md").exists()


@pytest.mark.parametrize(
    "override, match",
    [("ppo.clip_epsilon=-1", "ppo.clip_epsilon"), ("+ppo.bogus=1", "ppo.bogus: Key 'bogus' not in 'PPOSection'"),
     ("algorithm=a2c", "algorithm"), ("+settings.exploration={source: greedy}", "supervised settings only")],
)  # fmt: skip
def test_four_rooms_ppo_recipe_refuses_bad_settings(tmp_path, override, match):
    from torchrl_options.experiments.gridworld_config import gridworld_settings
    from torchrl_options.experiments.recipe_runner import setting_error_line

    cfg = OmegaConf.to_container(_cfg(tmp_path / "bad", override), resolve=True)
    if "exploration" in override:
        cfg["settings_to_run"] = ["supervised", "exploration"]
    with pytest.raises((ValueError, KeyError)) as info:
        gridworld_settings(cfg)
    assert match in setting_error_line(info.value)
