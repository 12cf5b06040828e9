"""Fault injection (issue 53): the four-rooms PPO recipe and the Atari recipe killed with SIGKILL (no cleanup) at
chosen points (between cells, inside a cell, during DDO, while writing a checkpoint, options or a hierarchy) and at
random times resume to a results.csv byte-identical to an uninterrupted run's; a half-written file is never left
under a final name (so never read back as a good one).

The fast test kills the Atari recipe while it writes its options (the case that failed before issue 53); the others
are slow.
Each run is a subprocess: ``tests/_fault_injection.py`` installs the fault, then runs the recipe's command line.
"""
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchrl_options.checkpoints import load_file, load_json_file
from torchrl_options.experiments import ResultsLog

ROOT = Path(__file__).resolve().parents[1]
PPO = ("recipes/four_rooms_ppo.py", ["scale=tiny", "progress=false", "episodes=32", "checkpoint_every=16"])
# Atlantis with raw rewards: the returns vary, so equal files mean something
ATARI = ("recipes/atari_ram.py", ["preset=smoke", "game=Atlantis", "atari.clip_rewards=false", "atari.option_frames=false"])


def command(recipe, out: Path, fault=("none", 0)) -> list[str]:
    script, overrides = recipe
    return [sys.executable, str(ROOT / "tests" / "_fault_injection.py"), fault[0], str(fault[1]), str(ROOT / script),
            *overrides, f"out_dir={out}"]  # fmt: skip


def environment() -> dict:
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT) + (os.pathsep + path if path else "")}


def run(recipe, out: Path, fault=("none", 0)) -> subprocess.CompletedProcess:
    out.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.run(command(recipe, out, fault), capture_output=True, text=True, timeout=900, cwd=out.parent,
                          env=environment())  # fmt: skip


def finish(recipe, out: Path) -> bytes:
    done = run(recipe, out)
    assert done.returncode == 0, done.stderr[-3000:]
    return (out / "results.csv").read_bytes()


def no_half_file_under_a_final_name(out: Path) -> None:
    """Every file a resumed run reads is whole: checkpoints, options and hierarchies load, the JSON files parse and
    results.csv reads (temporary files, named ``<name>.tmp<pid>-<id>``, are never read)."""
    for path in out.rglob("*.pt"):
        load_file(path)
    for path in out.rglob("*.json"):
        if "logs" not in path.parts:
            load_json_file(path)
    if (out / "results.csv").exists():
        ResultsLog(out / "results.csv").rows()


def killed_then_resumed(recipe, reference: bytes, out: Path, fault) -> None:
    cut = run(recipe, out, fault)
    assert cut.returncode == -signal.SIGKILL, f"the fault {fault} was not reached:\n{cut.stderr[-3000:]}"
    no_half_file_under_a_final_name(out)
    assert finish(recipe, out) == reference


@pytest.fixture(scope="module")
def references(tmp_path_factory):
    """The uninterrupted runs (made once, on demand), and how long they took."""
    made = {}

    def reference(recipe):
        key = recipe[0] + " ".join(recipe[1])
        if key not in made:
            out = tmp_path_factory.mktemp("reference") / "out"
            t0 = time.time()
            data = finish(recipe, out)
            rows = [line.split(b",")[4] for line in data.splitlines()[1:]]
            assert len(set(rows)) > 1, "the returns must vary for the comparison to mean something"
            made[key] = (data, time.time() - t0)
        return made[key]

    return reference


def test_atari_killed_while_writing_the_options_resumes_byte_identical(tmp_path, references):
    """Fast: the Atari recipe's third torch.save is phase 2's options (after phase 1's partial and final
    checkpoints). Before issue 53 they were written in place: killed half-way, the run left half an options.pt,
    which the resumed run could not read. Now the write goes to a temporary file: no options.pt is left, and the
    resumed run redoes phase 2 (the same, from the seed) to the same results."""
    pytest.importorskip("ale_py")
    reference, _ = references(ATARI)
    out = tmp_path / "out"
    cut = run(ATARI, out, ("save", 3))
    assert cut.returncode == -signal.SIGKILL, cut.stderr[-3000:]
    seed_dir = out / "Atlantis" / "seed0"
    assert not (seed_dir / "options.pt").exists() and list(seed_dir.glob("options.pt.tmp*")), "the kill must come inside the write"
    no_half_file_under_a_final_name(out)
    assert finish(ATARI, out) == reference


PPO_FAULTS = [
    ("save", 1),  # cell A's first (mid-cell) checkpoint
    ("save", 3),  # H1u's discovered options
    ("save", 6),  # H2u's discovered hierarchy
    ("ddo", 2),  # during H1u's DDO fit
    ("cell", 2),  # inside cell A, after its mid-cell checkpoint
    ("cell", 5),  # inside cell H2u
    ("between", 1),  # right after cell A is written to results.csv
]
ATARI_FAULTS = [
    ("save", 1),  # phase 1's partial checkpoint
    ("save", 2),  # phase 1's checkpoint
    ("save", 3),  # phase 2's options (written in place before issue 53: a resumed run could not read them)
    ("save", 5),  # H1's partial checkpoint
    ("ddo", 4),  # during DDO
    ("cell", 12),  # inside phase 1
    ("between", 1),  # between the cells A and H1
]


@pytest.mark.slow
@pytest.mark.parametrize("fault", PPO_FAULTS, ids=[f"{p}{n}" for p, n in PPO_FAULTS])
def test_ppo_recipe_killed_at_a_chosen_point_resumes_byte_identical(tmp_path, references, fault):
    killed_then_resumed(PPO, references(PPO)[0], tmp_path / "out", fault)


@pytest.mark.slow
@pytest.mark.parametrize("fault", ATARI_FAULTS, ids=[f"{p}{n}" for p, n in ATARI_FAULTS])
def test_atari_recipe_killed_at_a_chosen_point_resumes_byte_identical(tmp_path, references, fault):
    pytest.importorskip("ale_py")
    killed_then_resumed(ATARI, references(ATARI)[0], tmp_path / "out", fault)


@pytest.mark.slow
@pytest.mark.parametrize("recipe", [PPO, ATARI], ids=["four_rooms_ppo", "atari_ram"])
def test_recipe_killed_at_random_times_resumes_byte_identical(tmp_path, references, recipe):
    """The honest version: SIGKILL at three random times (each run killed after a uniform draw in [1 s, 90% of
    the uninterrupted run's time]), then a run to the end."""
    if recipe is ATARI:
        pytest.importorskip("ale_py")
    reference, seconds = references(recipe)
    out = tmp_path / "out"
    out.parent.mkdir(parents=True, exist_ok=True)
    rng = random.Random(53)
    kills = 0
    for _ in range(3):
        process = subprocess.Popen(command(recipe, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   cwd=out.parent, env=environment())  # fmt: skip
        try:
            process.wait(timeout=rng.uniform(1.0, 0.9 * seconds))
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGKILL)
            process.wait()
            kills += 1
        no_half_file_under_a_final_name(out)
    assert kills >= 1, "no run was killed: the draws came after the runs ended"
    assert finish(recipe, out) == reference
