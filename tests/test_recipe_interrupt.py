"""Ctrl-C (SIGINT) and SIGTERM end a recipe with one line naming what was saved and how to resume (no traceback,
no leaked semaphores), for the serial and the local-pool backends; the resumed run says where it resumes."""
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


class _Run:
    """The two-rooms recipe in a subprocess (its own process group, as a shell job), its output read as it comes."""

    def __init__(self, out: Path, *overrides):
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
        cmd = [sys.executable, str(ROOT / "recipes" / "two_rooms.py"), "scale=tiny", f"out_dir={out}",
               "progress=false", "logger.backend=", "episodes=4000", "checkpoint_every=16", "conditions_to_run=[A]",
               f"hydra.run.dir={out}/hydra", *overrides]  # fmt: skip
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     start_new_session=True)  # fmt: skip
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")))
        self._reader.start()

    def wait_until(self, condition, timeout=120.0):
        t0 = time.time()
        while not condition():
            assert self.proc.poll() is None, "".join(self.lines)
            assert time.time() - t0 < timeout, "".join(self.lines)
            time.sleep(0.1)

    def finish(self, timeout=120.0) -> str:
        self.proc.wait(timeout)
        self._reader.join(timeout)
        return "".join(self.lines)


CASES = [
    ("serial", signal.SIGTERM, "driver"),
    pytest.param("serial", signal.SIGINT, "group", marks=pytest.mark.slow),  # Ctrl-C in a terminal
    pytest.param("local", signal.SIGINT, "group", marks=pytest.mark.slow),
    pytest.param("local", signal.SIGTERM, "driver", marks=pytest.mark.slow),  # `kill PID`: forwarded to the workers
    pytest.param("ray", signal.SIGINT, "group", marks=pytest.mark.slow),
    pytest.param("ray", signal.SIGTERM, "driver", marks=pytest.mark.slow),  # Ray's own handler would abort
]


@pytest.mark.parametrize("backend, sig, target", CASES)
def test_interrupt_prints_one_line_and_resumes(tmp_path, backend, sig, target):
    if backend == "ray":
        pytest.importorskip("ray")
    out = tmp_path / "run"
    checkpoint = out / "cells" / "supervised-A-seed0" / "dqn.pt"
    run = _Run(out, f"backend={backend}", "num_workers=1")
    run.wait_until(checkpoint.exists)
    os.killpg(run.proc.pid, sig) if target == "group" else run.proc.send_signal(sig)
    text = run.finish()
    assert run.proc.returncode == 130, text
    assert "Traceback" not in text and "leaked" not in text, text
    last = [line for line in text.splitlines() if line.strip()][-1]
    assert last.startswith(f"interrupted: 0 finished cells saved in {out}/results.csv") and last.endswith(
        "run the same command again to resume."
    ), text
    if backend != "serial":
        return
    # the same command again resumes the cell from its checkpoint, and says so
    run = _Run(out, f"backend={backend}", "num_workers=1")
    run.wait_until(lambda: any("resuming from" in line for line in run.lines))
    run.proc.send_signal(signal.SIGTERM)
    text = run.finish()
    assert f"supervised-A-seed0: resuming from {checkpoint} at episode" in text, text
    assert run.proc.returncode == 130


class _FailingExit:
    """A context manager whose ``__exit__`` fails, as tensordict's ``to_module`` does when an interruption unwinds
    through TorchRL's DQN loss."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        raise RuntimeError("Converting a tensordict to boolean value is not permitted")


def test_interruption_hidden_by_a_failing_exit_is_still_one_line(tmp_path, capsys):
    from torchrl_options.experiments.recipe_runner import recipe_guard

    with pytest.raises(SystemExit) as stop:
        with recipe_guard(tmp_path), _FailingExit():
            raise KeyboardInterrupt
    assert stop.value.code == 130
    assert capsys.readouterr().err.startswith("interrupted: 0 finished cells saved in")
    with pytest.raises(RuntimeError, match="to boolean"):  # the same error without an interruption stays an error
        with recipe_guard(tmp_path), _FailingExit():
            pass
    with pytest.raises(SystemExit) as stop:
        with recipe_guard(tmp_path):
            raise ValueError("episodes must be an int >= 1, got -5.")
    assert stop.value.code == 2
