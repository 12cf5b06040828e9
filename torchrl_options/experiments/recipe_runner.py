"""How a recipe script runs and ends: its log in a file of its output folder (:func:`log_to_file`); bad settings
as one line, Ctrl-C (SIGINT) and SIGTERM as one line naming what was saved and how to resume, never a traceback
(:func:`recipe_guard`).

A recipe saves as it goes: each finished cell is appended to ``<out_dir>/results.csv`` and each running cell
checkpoints under ``<out_dir>/`` (every ``checkpoint_every`` episodes); running the same command again skips the
finished cells and resumes the others from their last checkpoint, bit for bit.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["log_to_file", "recipe_guard", "run_recipe_main", "setting_error_line"]

logger = logging.getLogger(__name__)

#: set to 1 to see the traceback of a refused setting instead of the one-line message
TRACEBACK_ENV = "TORCHRL_OPTIONS_TRACEBACK"


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def _interruption(err: BaseException | None) -> bool:
    """Whether ``err`` is an interruption, or was raised while one unwound the stack (a context manager whose
    ``__exit__`` fails on the way out, as tensordict's ``to_module`` inside TorchRL's losses can)."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__context__
    return False


def _finished_cells(out_dir: str | os.PathLike) -> int:
    path = Path(out_dir, "results.csv")
    if not path.exists():
        return 0
    from torchrl_options.experiments.results import ResultsLog

    try:
        return len(ResultsLog(path).done_cells())
    except Exception:  # the count is a courtesy: never mask the interruption
        return 0


@contextlib.contextmanager
def recipe_guard(out_dir: str | os.PathLike | None, checkpoints: str = "cells") -> Iterator[None]:
    """Wraps a recipe's work: SIGTERM becomes an interruption like Ctrl-C; an interruption (also one hidden by an
    error raised on its way out) exits with status 130 and one line (``interrupted: N finished cells in
    <out_dir>/results.csv, ...; run the same command again to resume.``); a refused setting (``ValueError``/``TypeError``,
    or an OmegaConf/Hydra error: an unknown key, a wrong type) exits with status 2 and one line ``error: ...``
    (:func:`setting_error_line`).

    Args:
        out_dir: the recipe's output folder (named in the message).
        checkpoints (str): where under ``out_dir`` the running cells' checkpoints are.

    Examples:
        >>> with recipe_guard("outputs/demo"):
        ...     pass
        >>> try:
        ...     with recipe_guard("outputs/demo"):
        ...         raise ValueError("episodes must be an int >= 1, got -5.")
        ... except SystemExit as stop:
        ...     print(stop.code)
        2
    """
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    except BaseException as err:
        if isinstance(err, SystemExit) or not _interruption(err):
            refused = isinstance(err, (ValueError, TypeError)) or _is_config_error(err)
            if not refused or os.environ.get(TRACEBACK_ENV, "") not in ("", "0"):
                raise
            print(f"error: {setting_error_line(err)}", file=sys.stderr)
            raise SystemExit(2) from None
        where = os.fspath(out_dir) if out_dir is not None else "the output folder"
        n = _finished_cells(out_dir) if out_dir is not None else 0
        print(
            f"interrupted: {n} finished cell{'s' if n != 1 else ''} saved in {where}/results.csv and the running "
            f"cells' last checkpoints under {where}/{checkpoints}; run the same command again to resume.",
            file=sys.stderr,
        )
        raise SystemExit(130) from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _is_config_error(err: BaseException) -> bool:
    """An OmegaConf error (an unknown key, a wrong type) or Hydra's failure to compose a config."""
    return any(c.__module__.split(".")[0] in ("omegaconf", "hydra") and c.__name__ in (
        "OmegaConfBaseException", "ConfigCompositionException", "HydraException") for c in type(err).__mro__)


def setting_error_line(err: BaseException) -> str:
    """One line for a refused setting: the message of a ``ValueError``/``TypeError``; for an OmegaConf error the
    key (``full_key``) and the first line of its message; for Hydra's composition error its message (e.g. the
    options of a config group) and its cause's.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"dqn": {"lr": 0.01}})
        >>> OmegaConf.set_struct(cfg, True)
        >>> try:
        ...     cfg.dqn.lrr = 1
        ... except Exception as err:
        ...     print(setting_error_line(err))
        dqn.lrr: Key 'lrr' is not in struct
    """
    if _is_config_error(err) and getattr(err, "full_key", None) is not None:
        return f"{err.full_key}: {str(getattr(err, 'msg', err)).splitlines()[0]}"
    lines = [line.strip() for line in str(err).splitlines()]
    if "Config search path:" in lines:  # Hydra's list of where it looked: not what was wrong
        lines = lines[: lines.index("Config search path:")]
    lines = [line for line in lines if line and not line.startswith(("full_key:", "reference_type=", "object_type="))]
    first = " ".join(lines) or type(err).__name__
    cause = err.__cause__
    if cause is not None and _is_config_error(err):
        return f"{first.rstrip('.')}: {setting_error_line(cause)}"
    return first if _is_config_error(err) else str(err)


def run_recipe_main(main: Callable[[], Any]) -> None:
    """Runs a recipe's ``@hydra.main`` function so that Hydra's own refusals (an unknown key, a value of the wrong
    type for the schema, found while composing) end as one line through :func:`recipe_guard` too, not Hydra's
    report: ``HYDRA_FULL_ERROR`` is set (unless already set) so that Hydra hands its errors on. The recipe's work
    inside ``main`` runs in its own :func:`recipe_guard` (the one that names ``out_dir``).

    Examples:
        >>> def main():
        ...     raise ValueError("dqn.lr must be a number, got 'abc'.")
        >>> try:
        ...     run_recipe_main(main)
        ... except SystemExit as stop:
        ...     print(stop.code)
        2
    """
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    with recipe_guard(None):
        main()


class _QuietConsole(logging.Filter):
    """Lets through warnings and errors, the resume messages, and the records of other libraries."""

    def __init__(self, names: tuple[str, ...]) -> None:
        super().__init__()
        self.names = names

    def filter(self, record: logging.LogRecord) -> bool:
        ours = any(record.name == n or record.name.startswith(n + ".") for n in self.names)
        return not ours or record.levelno >= logging.WARNING or record.name == "torchrl_options.resume"


@contextlib.contextmanager
def log_to_file(
    path: str | os.PathLike, *, quiet_console: bool = False, loggers: tuple[str, ...] = ("torchrl_options",)
) -> Iterator[Path]:
    """Appends the log of ``loggers`` (the package's, INFO and above) to ``path`` while the block runs.

    The loggers are lowered to INFO if they were set higher (and restored after). With ``quiet_console``, the
    console (the stream handlers of the root logger, e.g. Hydra's) shows only their warnings and the resume
    messages (``torchrl_options.resume``); the file still gets everything. Runs in worker processes
    (``backend=local`` or ``ray``) log in their own process, not into this file.

    Examples:
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "recipe.log")
        >>> with log_to_file(path):
        ...     logging.getLogger("torchrl_options.demo").info("cell %s finished", "A-seed0")
        >>> open(path).read().strip().endswith("cell A-seed0 finished")
        True
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
    levels = {}
    for name in loggers:
        package = logging.getLogger(name)
        levels[name] = package.level
        if package.getEffectiveLevel() > logging.INFO:
            package.setLevel(logging.INFO)
        package.addHandler(handler)
    quiet = _QuietConsole(tuple(loggers))
    consoles = [
        h for h in logging.getLogger().handlers
        if quiet_console and isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)
    ]  # fmt: skip
    for h in consoles:
        h.addFilter(quiet)
    try:
        yield path
    finally:
        for h in consoles:
            h.removeFilter(quiet)
        for name, level in levels.items():
            logging.getLogger(name).removeHandler(handler)
            logging.getLogger(name).setLevel(level)
        handler.close()
