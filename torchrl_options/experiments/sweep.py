"""Sweeps over (setting, condition, seed) cells: serially, on a local process pool, or on a Ray cluster.

The scheduling is the engine's (``concurrent.futures`` locally, Ray remotely): this module only maps a cell
function over the cells that are not finished yet and appends each finished cell to one ``results.csv``
(:class:`~torchrl_options.experiments.ResultsLog`) from the driver, so workers never write the same file and a
re-run skips finished cells.
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from torchrl_options.checks import check_callable, check_choice, check_int, check_numbers
from torchrl_options.experiments.results import ResultsLog

__all__ = ["Cell", "CellResult", "run_sweep"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Cell:
    """One unit of work: a setting (e.g. a game or a task), a condition (e.g. ``"A"`` or ``"H1u"``) and a seed."""

    setting: str
    condition: str
    seed: int

    def __post_init__(self) -> None:
        for name in ("setting", "condition"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise TypeError(f"Cell: {name} must be a non-empty str, got {value!r}.")
        check_int(self.seed, "Cell: seed", minimum=0)

    @property
    def name(self) -> str:
        return f"{self.setting}-{self.condition}-seed{self.seed}"


@dataclass
class CellResult:
    """What a cell function returns: per-episode returns, optionally the env frames at the end of each episode."""

    returns: list[float]
    frames: list[int] | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # a NaN return would be averaged into every statistic of the run without a word
        check_numbers(self.returns, "CellResult: returns")
        if self.frames is not None:
            if isinstance(self.frames, (str, bytes)) or not isinstance(self.frames, Sequence):
                raise TypeError(f"CellResult: frames must be None or a list of ints, got {type(self.frames).__name__}.")
            if len(self.frames) != len(self.returns):
                raise ValueError(
                    f"CellResult: frames has {len(self.frames)} entries but returns has {len(self.returns)} (one per episode)."
                )
        if not isinstance(self.info, dict):
            raise TypeError(f"CellResult: info must be a dict, got {type(self.info).__name__}.")


_IN_CELL = False  # in a pool worker: whether a cell is running (Ctrl-C stops a cell, never an idle worker)


def _worker_sigint(signum, frame) -> None:
    if _IN_CELL:
        raise KeyboardInterrupt


def _init_worker(torchrl_level: int = logging.NOTSET) -> None:
    """Pool workers: SIGINT (Ctrl-C reaches the whole process group, and the driver forwards SIGTERM as SIGINT)
    stops the running cell (its last checkpoint stays) and is ignored between cells, so that no worker prints a
    traceback; the driver reports the interruption once. TorchRL's logger gets the driver's level (a quiet recipe
    keeps TorchRL's own console lines out of the workers too)."""
    signal.signal(signal.SIGINT, _worker_sigint)
    if torchrl_level != logging.NOTSET:
        logging.getLogger("torchrl").setLevel(torchrl_level)


def _run_one(fn: Callable[[Cell], CellResult], cell: Cell, threads: int | None) -> tuple[Cell, CellResult]:
    global _IN_CELL
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    _IN_CELL = True
    try:
        return cell, fn(cell)
    finally:
        _IN_CELL = False


def _stop_workers(pool: cf.ProcessPoolExecutor) -> None:
    """After an interrupt in the driver: cancel the cells not started, interrupt the running ones, wait for the
    workers to exit (no orphans, no leaked semaphores)."""
    pool.shutdown(wait=False, cancel_futures=True)
    for child in multiprocessing.active_children():
        try:
            os.kill(child.pid, signal.SIGINT)
        except (ProcessLookupError, TypeError):
            pass
    pool.shutdown(wait=True, cancel_futures=True)


def run_sweep(
    fn: Callable[[Cell], CellResult],
    cells: Sequence[Cell],
    log: ResultsLog,
    *,
    backend: str = "serial",
    num_workers: int | None = None,
    ray_address: str | None = None,
    threads_per_worker: int | None = 1,
    on_result: Callable[[Cell, CellResult], None] | None = None,
) -> list[Cell]:
    """Runs ``fn`` on every cell not yet in ``log`` and appends each result as soon as it arrives.

    Args:
        fn: a picklable top-level function ``Cell -> CellResult`` (it should checkpoint inside long cells
            itself, e.g. under a directory named after ``cell.name``).
        cells: the cells of the sweep.
        log: the results file shared by every worker's cells.

    Keyword Args:
        backend (str): ``"serial"`` (default, in this process), ``"local"`` (a process pool of ``num_workers``) or
            ``"ray"`` (Ray tasks; ``ray_address`` names an existing cluster, ``None`` starts a local one).
        num_workers (int, optional): pool size for ``"local"`` (default: CPU count).
        ray_address (str, optional): passed to ``ray.init(address=...)``.
        threads_per_worker (int, optional): ``torch.set_num_threads`` in pool and Ray workers.
        on_result (callable, optional): called in the driver with each finished cell and result.

    Returns:
        The cells that ran (finished cells found in ``log`` are skipped).

    Examples:
        >>> import os, tempfile
        >>> log = ResultsLog(os.path.join(tempfile.mkdtemp(), "results.csv"))
        >>> cells = [Cell("toy", "A", s) for s in range(2)]
        >>> ran = run_sweep(_constant_cell, cells, log)
        >>> len(ran), len(run_sweep(_constant_cell, cells, log))  # the second run skips both
        (2, 0)
    """
    check_callable(fn, "fn")
    check_choice(backend, "backend", ("serial", "local", "ray"))
    check_int(num_workers, "num_workers", minimum=1, allow_none=True)
    check_int(threads_per_worker, "threads_per_worker", minimum=1, allow_none=True)
    check_callable(on_result, "on_result", allow_none=True)
    if not isinstance(log, ResultsLog):
        raise TypeError(f"log must be a ResultsLog, got {type(log).__name__}.")
    if isinstance(cells, (str, bytes)) or not isinstance(cells, Sequence):
        raise TypeError(f"cells must be a sequence of Cell, got {type(cells).__name__}.")
    for i, cell in enumerate(cells):
        if not isinstance(cell, Cell):
            raise TypeError(f"cells[{i}] must be a Cell, got {type(cell).__name__}.")
    if len(set(cells)) != len(cells):
        repeated = sorted({c.name for c in cells if cells.count(c) > 1})
        raise ValueError(f"cells must not repeat a cell (its results would be written twice), got {repeated} twice or more.")
    done = log.done_cells()
    todo = [c for c in cells if (c.setting, c.condition, c.seed) not in done]
    skipped = len(cells) - len(todo)
    if skipped:
        logger.info("sweep: %d finished cells found in %s, %d to run", skipped, log.path, len(todo))

    def record(cell: Cell, result: CellResult) -> None:
        if not isinstance(result, CellResult):
            raise TypeError(f"fn must return a CellResult, it returned {type(result).__name__} for cell {cell.name}.")
        log.append_cell(cell.setting, cell.condition, cell.seed, result.returns, result.frames)
        if on_result is not None:
            on_result(cell, result)

    if backend == "serial" or not todo:
        for cell in todo:
            record(cell, fn(cell))
    elif backend == "local":
        ctx = multiprocessing.get_context("spawn")
        pool = cf.ProcessPoolExecutor(
            max_workers=num_workers, mp_context=ctx, initializer=_init_worker,
            initargs=(logging.getLogger("torchrl").level,),
        )
        try:
            futures = [pool.submit(_run_one, fn, cell, threads_per_worker) for cell in todo]
            for future in cf.as_completed(futures):
                record(*future.result())
        except BaseException:
            _stop_workers(pool)
            raise
        pool.shutdown(wait=True)
    elif backend == "ray":
        try:
            import ray
        except ImportError as err:
            raise ImportError("backend='ray' needs Ray: pip install 'torchrl-options[ray]'.") from err
        started = False
        if not ray.is_initialized():
            main_thread = threading.current_thread() is threading.main_thread()
            previous = signal.getsignal(signal.SIGTERM) if main_thread else None
            ray.init(address=ray_address, num_cpus=num_workers if ray_address is None else None, log_to_driver=False)
            if previous is not None:  # Ray's driver handler aborts with a stack dump: keep the caller's (the recipes'
                signal.signal(signal.SIGTERM, previous)  # turns SIGTERM into a clean interruption)
            started = True
        try:
            remote = ray.remote(_run_one)
            pending = [remote.remote(fn, cell, threads_per_worker) for cell in todo]
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                record(*ray.get(ready[0]))
        finally:
            if started:
                ray.shutdown()
    else:
        raise ValueError(f"backend must be 'serial', 'local' or 'ray', got {backend!r}.")
    return todo


def _constant_cell(cell: Cell) -> CellResult:
    """A trivial cell function (for examples and tests)."""
    return CellResult(returns=[float(cell.seed)] * 3, frames=[10, 20, 30])
