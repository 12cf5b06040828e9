"""The data-parallel recipe is one command: ``python recipes/discover_distributed.py`` (one process) and
``torchrun --nproc-per-node 2 recipes/discover_distributed.py`` (two gloo processes, slow) write the options and the
metrics, on planted demonstrations the recipe writes itself."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_options import load_options

ROOT = Path(__file__).resolve().parents[1]
TINY = ["data.planted_trajectories=4", "data.planted_length=50", "discovery.num_options=2", "discovery.batch_size=null",
        "discovery.num_iterations=3", "discovery.tol=null", "discovery.init=random", "discovery.num_cells=4",
        "progress=false"]  # fmt: skip


def _run(command, out):
    done = subprocess.run(command + TINY + [f"output_dir={out}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 3 and metrics["steps"] == 200
    assert load_options(out / "options.pt") is not None
    return metrics


def test_the_recipe_runs_in_one_process(tmp_path):
    metrics = _run([sys.executable, "recipes/discover_distributed.py"], tmp_path / "one")
    assert metrics["processes"] == 1


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("torchrun") is None, reason="torchrun is not on the PATH")
def test_the_torchrun_command_runs_two_processes(tmp_path):
    command = ["torchrun", "--standalone", "--nproc-per-node", "2", "recipes/discover_distributed.py"]
    two = _run(command, tmp_path / "two")
    one = _run([sys.executable, "recipes/discover_distributed.py"], tmp_path / "one")
    assert two["processes"] == 2
    assert two["log_likelihood_per_step"] == pytest.approx(one["log_likelihood_per_step"], abs=1e-4)
