"""A GridWorld recipe's run in its ``out_dir`` (:class:`GridWorldRun`): what the script holds open around its sweep.

A recipe script reads top to bottom::

    cfg = gridworld_settings(cfg)                       # the schema, protocol=paper merged, every value checked
    with GridWorldRun(cfg, "Four rooms") as recipe:     # settings.json, the log file, the cells left to run
        run_sweep(partial(run_gridworld_cell, cfg=cfg), recipe.cells, recipe.results, on_result=recipe.finished,
                  **recipe.sweep_options)
        summary = recipe.outputs()                      # summary.md, curves.png, pictures/

Resuming: finished cells (in ``results.csv``) are skipped and logged; running cells resume from their checkpoints
(:func:`~torchrl_options.experiments.gridworld.run_gridworld_cell`); an ``out_dir`` made with other settings is
refused (:func:`~torchrl_options.experiments.run_settings.check_run_settings`).
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torchrl_options.experiments.gridworld import resume_logger, write_option_pictures, write_summary
from torchrl_options.experiments.recipe_runner import log_to_file
from torchrl_options.experiments.results import ResultsLog
from torchrl_options.experiments.run_settings import check_run_settings
from torchrl_options.experiments.sweep import Cell, CellResult

__all__ = ["GridWorldRun", "RUN_ONLY_SETTINGS"]

logger = logging.getLogger(__name__)

#: Recipe keys that choose which cells run, how they run or how the summary reads: a run may be resumed with
#: other values of these; every other key defines the cells (:func:`check_run_settings`). ``checkpoint_every``
#: defines them too: each checkpoint ends a chunk of training, whose episodes restart.
RUN_ONLY_SETTINGS = (
    "out_dir", "seeds", "settings_to_run", "conditions_to_run", "backend", "num_workers", "ray_address",
    "stop_after_cells", "progress", "verbose", "logger", "pictures", "summary", "scale",
    "allow_changed_settings", "log_file",
)  # fmt: skip


class GridWorldRun:
    """A GridWorld recipe's run in ``settings["out_dir"]``, held open by a ``with`` block around the sweep.

    Entering records the settings that define the cells in ``settings.json`` (refusing an ``out_dir`` made with
    others, any key but :data:`RUN_ONLY_SETTINGS`, unless ``allow_changed_settings``), opens the log file
    (``log_file``, default ``recipe.log``), and lists :attr:`cells`: those not finished in :attr:`results`, cut at
    ``stop_after_cells`` (which the tests use to interrupt a run), the finished ones logged as skipped. With
    ``progress`` and a pool backend a bar counts finished cells (:meth:`finished`). :meth:`outputs` writes
    ``summary.md``, ``curves.png`` and ``pictures/`` (the discovered options of the first seed: pictures and
    videos) and returns the summary, or ``None`` when the run stopped early.

    Args:
        settings (Mapping): the recipe's checked settings
            (:func:`~torchrl_options.experiments.gridworld_config.gridworld_settings`).
        title (str): the summary's title.

    Keyword Args:
        quiet (bool): keep the console to progress bars, warnings, resume messages and the summary unless
            ``verbose`` (the package's INFO records go to the log file only). Defaults to ``False``.

    Examples:
        >>> import tempfile
        >>> settings = {"out_dir": tempfile.mkdtemp(), "seeds": 2, "settings_to_run": ["supervised"],
        ...             "conditions_to_run": ["A", "H1u"], "episodes": 10}
        >>> with GridWorldRun(settings, "Demo") as recipe:
        ...     [cell.name for cell in recipe.cells]
        ['supervised-A-seed0', 'supervised-A-seed1', 'supervised-H1u-seed0', 'supervised-H1u-seed1']
    """

    def __init__(self, settings: Mapping[str, Any], title: str, *, quiet: bool = False) -> None:
        if not isinstance(settings, Mapping):
            raise TypeError(f"settings must be a mapping (gridworld_settings(cfg)), got {type(settings).__name__}.")
        self.settings, self.title = dict(settings), title
        self.quiet = bool(quiet) and not self.settings.get("verbose", False)
        self.out = Path(self.settings["out_dir"])
        seeds = self.settings["seeds"]
        self.seeds = list(range(int(seeds))) if isinstance(seeds, int) else list(seeds)
        self.results: ResultsLog | None = None
        self.cells: list[Cell] = []
        self.stopped = False
        self._stack = contextlib.ExitStack()
        self._bar = None

    @property
    def sweep_options(self) -> dict[str, Any]:
        """:func:`~torchrl_options.experiments.run_sweep`'s ``backend``, ``num_workers`` and ``ray_address``."""
        s = self.settings
        return {"backend": s.get("backend", "serial"), "num_workers": s.get("num_workers"),
                "ray_address": s.get("ray_address")}  # fmt: skip

    def __enter__(self) -> GridWorldRun:
        s = self.settings
        if self.quiet:
            logging.getLogger("torchrl").setLevel(logging.WARNING)  # TorchRL logs to its own console handler
            resume_logger.setLevel(logging.INFO)
        allow = bool(s.get("allow_changed_settings", False))
        check_run_settings(self.out, s, ignore=RUN_ONLY_SETTINGS, allow_changes=allow)
        self._stack.enter_context(log_to_file(self.out / (s.get("log_file") or "recipe.log"), quiet_console=self.quiet))
        self.results = ResultsLog(self.out / "results.csv")
        cells = [Cell(a, c, seed) for a in s["settings_to_run"] for c in s["conditions_to_run"] for seed in self.seeds]
        done = self.results.done_cells()
        self.cells = [c for c in cells if (c.setting, c.condition, c.seed) not in done]
        skipped = [c.name for c in cells if (c.setting, c.condition, c.seed) in done]
        if skipped:
            resume_logger.info(
                "resuming %s: %d finished cells skipped (%s)", self.out, len(skipped), ", ".join(skipped)
            )
        stop = s.get("stop_after_cells")
        self.stopped = stop is not None and len(self.cells) > int(stop)
        if self.stopped:
            self.cells = self.cells[: int(stop)]
        names = ", ".join(c.name for c in self.cells) or "none"
        logger.info("%s: %d cells to run in %s (%s)", self.title, len(self.cells), self.out, names)
        if s.get("progress", False) and s.get("backend", "serial") != "serial":
            from tqdm.auto import tqdm

            self._bar = self._stack.enter_context(tqdm(total=len(self.cells), desc=f"{self.title}: cells", unit="cell"))
        return self

    def finished(self, cell: Cell, result: CellResult) -> None:
        """``run_sweep``'s ``on_result``: logs the cell and moves the progress bar."""
        logger.info("cell %s finished: %d episodes", cell.name, len(result.returns))
        if self._bar is not None:
            self._bar.update(1)

    def outputs(self) -> str | None:
        """Writes ``summary.md``, ``curves.png`` and ``pictures/``; returns the summary (``None``, and nothing
        written, when ``stop_after_cells`` stopped the run early)."""
        if self._bar is not None:
            self._bar.close()
        if self.stopped:
            logger.warning("stopped after %d cells (stop_after_cells); run again to resume.", len(self.cells))
            return None
        s = self.settings
        order = list(s["conditions"])
        text = write_summary(self.results, self.out, self.title, s.get("summary"), condition_order=order)
        pictures = write_option_pictures(s, min(self.seeds))
        logger.info("summary:\n%s", text)
        logger.info("wrote results.csv, summary.md, curves.png and %d pictures/videos in %s", len(pictures), self.out)
        return text

    def __exit__(self, *exc: Any) -> None:
        self._stack.close()
