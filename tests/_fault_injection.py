"""Runs a recipe that kills itself with SIGKILL (no cleanup, no ``finally``) at a chosen point (issue 53).

    python tests/_fault_injection.py POINT N RECIPE [hydra overrides ...]

``POINT`` and ``N``: ``save N`` while writing the N-th file through ``torch.save`` (checkpoints, options,
hierarchies: half the bytes are on disk, then the process dies), ``ddo N`` at the N-th optimizer step of a DDO fit,
``cell N`` at the N-th agent update (PPO or DQN: inside a cell), ``between N`` right after the N-th finished cell is
written to ``results.csv``, ``none 0`` (no fault). The recipe then runs as ``python RECIPE [overrides]``.
"""
from __future__ import annotations

import os
import runpy
import signal
import sys


class _Counter:
    def __init__(self, count: int):
        self.count, self.calls = count, 0

    def due(self) -> bool:
        self.calls += 1
        return self.calls == self.count


def _die() -> None:
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)


def install(point: str, count: int) -> None:
    """Installs the fault ``point`` at its ``count``-th occurrence in this process."""
    counter = _Counter(count)
    if point == "save":
        import io

        import torch

        real_save = torch.save

        def save(obj, f, *args, **kwargs):
            if not counter.due():
                return real_save(obj, f, *args, **kwargs)
            buffer = io.BytesIO()
            real_save(obj, buffer, *args, **kwargs)
            data = buffer.getvalue()
            with open(f, "wb") as out:  # half a file on disk, then the kill
                out.write(data[: len(data) // 2])
                out.flush()
                os.fsync(out.fileno())
            _die()

        torch.save = save
    elif point == "ddo":
        import torchrl_options.discovery.discover as discover
        import torchrl_options.hierarchy.discover as hierarchy_discover

        real_fit = discover.fit_ddo

        def fit_ddo(loss_module, optimizer, *args, **kwargs):
            real_step = optimizer.step

            def step(*a, **k):
                if counter.due():
                    _die()
                return real_step(*a, **k)

            optimizer.step = step
            return real_fit(loss_module, optimizer, *args, **kwargs)

        discover.fit_ddo = fit_ddo
        hierarchy_discover.fit_ddo = fit_ddo
    elif point == "cell":
        from torchrl_options.agents import OptionsDQN, OptionsPPO

        for cls, name in ((OptionsPPO, "update"), (OptionsDQN, "_update")):
            real = getattr(cls, name)

            def update(self, *args, _real=real, **kwargs):
                if counter.due():
                    _die()
                return _real(self, *args, **kwargs)

            setattr(cls, name, update)
    elif point == "between":
        from torchrl_options.experiments import ResultsLog

        real_append = ResultsLog.append_cells

        def append_cells(self, cells):
            real_append(self, cells)
            if counter.due():
                _die()

        ResultsLog.append_cells = append_cells
    elif point != "none":
        raise SystemExit(f"unknown fault point {point!r}")


if __name__ == "__main__":
    point, count, recipe = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    sys.argv = [recipe] + sys.argv[4:]
    install(point, count)
    runpy.run_path(recipe, run_name="__main__")
