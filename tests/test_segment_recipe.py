"""recipes/segment.py at tiny scale: every output file, from a demo source and from a file."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("hydra")
pytest.importorskip("matplotlib")
from omegaconf import OmegaConf  # noqa: E402

from torchrl_options import load_options  # noqa: E402
from torchrl_options.segmentation import reach_grasp_demonstrations, save_trajectories  # noqa: E402

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def _recipe():
    spec = importlib.util.spec_from_file_location("segment_recipe", RECIPES / "segment.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(**overrides):
    cfg = OmegaConf.load(RECIPES / "config" / "segment.yaml")
    cfg.pop("hydra")
    cfg.progress = False
    cfg.merge_with_dotlist([f"{k}={v}" for k, v in overrides.items()])
    return cfg


def _check_outputs(out: Path, n: int, with_reference: bool, num_options: int = 4):
    assert {"segmentation.npz", "options.pt", "metrics.json", "metrics.md", "segmentation.png"} <= {
        p.name for p in out.iterdir()
    }
    seg = np.load(out / "segmentation.npz")
    assert seg["options"].shape[0] == n and seg["posterior"].shape[:2] == seg["options"].shape
    assert seg["boundaries"].dtype == bool and not seg["boundaries"][:, 0].any()
    assert ("reference_boundaries" in seg.files) == with_reference
    metrics = json.loads((out / "metrics.json").read_text())
    assert np.isfinite(metrics["log_likelihood_per_step"])
    assert ("accuracy" in metrics) == with_reference
    if with_reference:
        assert 0.0 <= metrics["random"]["expected_accuracy"] <= 1.0
        assert "random accuracy" in (out / "metrics.md").read_text()
    assert (out / "segmentation.png").read_bytes()[:4] == b"\x89PNG"
    assert load_options(out / "options.pt").num_options == num_options == metrics["num_options"]


def test_recipe_on_a_file(tmp_path):
    data = reach_grasp_demonstrations(3, seed=0)
    path = save_trajectories(data, tmp_path / "demos.npz")
    out = tmp_path / "out"
    cfg = _config(**{"data.source": "file", "data.path": str(path), "discovery.num_iterations": 2,
                     "output_dir": str(out), "segmentation.baseline_samples": 5})
    metrics = _recipe().run(cfg)
    assert metrics["window"] == 2 and metrics["num_trajectories"] == 3
    _check_outputs(out, 3, with_reference=True)


def test_recipe_without_reference(tmp_path):
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "d.npz", observations=rng.random((2, 9, 3)), actions=rng.integers(0, 3, (2, 8)))
    out = tmp_path / "out"
    cfg = _config(**{"data.source": "file", "data.path": str(tmp_path / "d.npz"), "discovery.num_iterations": 2,
                     "output_dir": str(out)})
    _recipe().run(cfg)
    _check_outputs(out, 2, with_reference=False)


def test_recipe_command_line_demo(tmp_path):
    out = tmp_path / "grid"
    cmd = [sys.executable, str(RECIPES / "segment.py"), "data.source=gridworld", "data.num_trajectories=3",
           "data.length=40", "discovery.num_iterations=2", "segmentation.baseline_samples=5", "progress=false",
           f"output_dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    _check_outputs(out, 3, with_reference=True, num_options=8)  # the GridWorld benchmark's 8 options
    assert json.loads((out / "metrics.json").read_text())["window"] == 1


def test_recipe_gridworld_four_rooms(tmp_path):
    cfg = _config(**{"data.source": "gridworld", "data.grid": "four-rooms", "data.num_trajectories": 2,
                     "data.length": 30, "discovery.num_iterations": 2, "discovery.num_options": 3,
                     "output_dir": str(tmp_path), "segmentation.baseline_samples": 5})
    metrics = _recipe().run(cfg)
    assert metrics["window"] == 1 and metrics["num_steps"] == 60
    assert np.load(tmp_path / "segmentation.npz")["posterior"].shape == (2, 30, 3)


def test_recipe_bad_file_names_the_key(tmp_path):
    np.savez(tmp_path / "bad.npz", observations=np.zeros((2, 4, 1)))
    cfg = _config(**{"data.source": "file", "data.path": str(tmp_path / "bad.npz"), "output_dir": str(tmp_path)})
    with pytest.raises(ValueError, match="'actions' is missing"):
        _recipe().run(cfg)
