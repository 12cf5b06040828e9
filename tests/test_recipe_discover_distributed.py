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


@pytest.mark.parametrize(
    "override, phrase",
    [("discovery.init=kmean", "discovery.init must be one of 'random', 'kmeans', 'segments', 'auto', got 'kmean'"),
     ("device=tpu", "device must be one of ('auto', 'cpu', 'cuda'), got 'tpu'"),
     ("threads=0", "threads must be an int >= 1, got 0"),
     ("+discovery.bogus=1", "bogus"),
     ("discovery.num_options=two", "discovery.num_options"),
     ("discovery.lr=-0.1", "discovery.lr must be a positive finite number, got -0.1"),
     ("discovery.num_cells=[4,-1]", "discovery.num_cells must be one positive int or a non-empty sequence of them")],
)  # fmt: skip
def test_the_schema_refuses_bad_settings_in_one_line(tmp_path, override, phrase):
    """The recipe's settings go through its Hydra schema (issue 51 part 4): an unknown key, a wrong type or a value
    out of range ends the run with one line naming it, before any process group or data."""
    done = subprocess.run([sys.executable, "recipes/discover_distributed.py", override, f"output_dir={tmp_path / 'o'}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode != 0
    assert phrase in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "o" / "demonstrations").exists()


def test_the_yaml_is_the_schema_defaults():
    """Every key of recipes/config/discover_distributed.yaml is the schema's, with the schema's default."""
    import dataclasses

    from omegaconf import OmegaConf

    from torchrl_options.experiments.discover_distributed_config import DiscoverDistributedConfig

    yaml = OmegaConf.to_container(OmegaConf.load(ROOT / "recipes" / "config" / "discover_distributed.yaml"))
    yaml = {k: v for k, v in yaml.items() if k not in ("defaults", "hydra")}
    assert yaml == dataclasses.asdict(DiscoverDistributedConfig())
