"""The settings a resumable run was made with, so that resuming it with other settings is refused.

A recipe's ``out_dir`` holds finished cells (``results.csv``) and checkpoints that later cells reuse (a seed's
pre-trained DQN, its discovered options). Running the recipe again skips the finished cells and reloads the
checkpoints: that is how a killed run resumes, and how conditions or seeds are added to a run. If the second
command changes a setting that defines the cells (more episodes, another network, another DDO fit), the skipped
cells and the reloaded checkpoints were made with the old value while the summary is written as if they had the
new one. :func:`check_run_settings` records the defining settings in ``<out_dir>/settings.json`` on the first run
and, on every later run into the same folder, raises with each setting that differs.
"""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Mapping
from typing import Any

from torchrl_options.checkpoints import CheckpointFileError, load_json_file, save_json_file
from torchrl_options.checks import check_bool

__all__ = [
    "check_run_settings",
    "describe_differences",
    "flatten_settings",
    "read_run_settings",
    "settings_differences",
    "write_run_settings",
]

logger = logging.getLogger(__name__)

SETTINGS_FILE = "settings.json"


def flatten_settings(settings: Mapping[str, Any], *, ignore: Iterable[str] = (), prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``, with values as JSON gives them back (tuples become lists), leaving
    out the dotted names in ``ignore`` and everything below them.

    Examples:
        >>> flatten_settings({"dqn": {"lr": 0.01, "hidden_sizes": (2,)}, "episodes": 200, "seeds": 3}, ignore=["seeds"])
        {'dqn.lr': 0.01, 'dqn.hidden_sizes': [2], 'episodes': 200}
    """
    ignore = tuple(ignore)
    flat: dict[str, Any] = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if _ignored(name, ignore):
            continue
        if isinstance(value, Mapping) and value:
            flat.update(flatten_settings(value, ignore=ignore, prefix=f"{name}."))
        else:
            flat[name] = json.loads(json.dumps(value))
    return flat


def _ignored(name: str, ignore: Iterable[str]) -> bool:
    return any(name == i or name.startswith(f"{i}.") for i in ignore)


def read_run_settings(out_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The settings recorded in ``<out_dir>/settings.json`` by :func:`check_run_settings`, or ``None``.

    Examples:
        >>> import tempfile
        >>> out = tempfile.mkdtemp()
        >>> read_run_settings(out) is None
        True
        >>> _ = check_run_settings(out, {"dqn": {"lr": 0.01}})
        >>> read_run_settings(out)
        {'dqn.lr': 0.01}
    """
    path = os.path.join(out_dir, SETTINGS_FILE)
    if not os.path.exists(path):
        return None
    settings = load_json_file(path, what="run settings")
    if not isinstance(settings, dict):
        raise CheckpointFileError(f"{path}: expected the run settings as a JSON object, got {type(settings).__name__}.")
    return settings


def settings_differences(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """``{name: (recorded value, value now)}`` for every setting that differs between two (nested or flattened)
    settings; a setting missing on one side is ``None`` there, so a setting left out and one set to ``None`` (the
    reader's default either way: how the recipes' schemas leave a key) do not differ.

    Examples:
        >>> settings_differences({"dqn": {"lr": 0.01, "gamma": 0.9}}, {"dqn.lr": 0.1, "dqn.gamma": 0.9, "seed": 1})
        {'dqn.lr': (0.01, 0.1), 'seed': (None, 1)}
        >>> settings_differences({"dqn": {"lr": 0.01, "max_decisions": None}}, {"dqn.lr": 0.01})
        {}
    """
    old, new = flatten_settings(recorded), flatten_settings(now)
    diffs = {}
    for name in sorted(set(old) | set(new)):
        a, b = old.get(name), new.get(name)
        if a != b:
            diffs[name] = (a, b)
    return diffs


def describe_differences(diffs: Mapping[str, tuple[Any, Any]], first: str = "there", second: str = "now") -> str:
    """``"name: <a> there, <b> now; ..."`` for error messages.

    Examples:
        >>> describe_differences({"episodes": (200, 1000)})
        'episodes: 200 there, 1000 now'
    """
    return "; ".join(f"{name}: {json.dumps(a)} {first}, {json.dumps(b)} {second}" for name, (a, b) in diffs.items())


def check_run_settings(
    out_dir: str | os.PathLike,
    settings: Mapping[str, Any],
    *,
    ignore: Iterable[str] = (),
    allow_changes: bool = False,
) -> dict[str, tuple[Any, Any]]:
    """Records the settings that define a resumable run's cells in ``<out_dir>/settings.json``, and refuses to
    resume the run with other values.

    On the first call for ``out_dir`` the settings (nested mappings, flattened to dotted names) are written. On a
    later call they are compared with the recorded ones, leaving out the names in ``ignore`` (and everything below
    them): settings that only choose which cells run (seeds, conditions), how they run (workers, device, threads)
    or how the summary is written. Any difference raises, unless ``allow_changes``, in which case it is logged
    and the new settings are recorded.

    Args:
        out_dir (str or PathLike): the run's folder (created if missing).
        settings (Mapping): the run's configuration, as plain nested mappings (e.g. ``OmegaConf.to_container``).

    Keyword Args:
        ignore (Iterable[str]): dotted names left out of the comparison, with everything below them.
        allow_changes (bool): log the differences and record the new settings instead of raising.
            Defaults to ``False``.

    Returns:
        the differences, ``{name: (recorded, now)}`` (empty when the settings match or none were recorded).

    Raises:
        ValueError: the recorded settings differ from ``settings`` and ``allow_changes`` is ``False``. The message
            names each differing setting with both values.

    Examples:
        >>> import tempfile
        >>> out = tempfile.mkdtemp()
        >>> check_run_settings(out, {"episodes": 200, "dqn": {"lr": 0.01}, "seeds": 3}, ignore=["seeds"])
        {}
        >>> check_run_settings(out, {"episodes": 200, "dqn": {"lr": 0.01}, "seeds": 5}, ignore=["seeds"])
        {}
        >>> check_run_settings(out, {"episodes": 1000, "dqn": {"lr": 0.01}, "seeds": 3}, ignore=["seeds"])
        Traceback (most recent call last):
        ...
        ValueError: out_dir ... holds a run made with other settings: episodes: 200 there, 1000 now. ...
    """
    if not isinstance(settings, Mapping):
        raise TypeError(f"settings must be a mapping (e.g. OmegaConf.to_container(cfg)), got {type(settings).__name__}.")
    check_bool(allow_changes, "allow_changes")
    os.makedirs(out_dir, exist_ok=True)
    now = flatten_settings(settings, ignore=ignore)
    recorded = read_run_settings(out_dir)
    diffs = {} if recorded is None else settings_differences(flatten_settings(recorded, ignore=ignore), now)
    if diffs:
        message = (
            f"out_dir {os.fspath(out_dir)!r} holds a run made with other settings: {describe_differences(diffs)}. "
            "Its finished cells would be skipped and its checkpoints reused as if they had the new values. Write to "
            "another out_dir, or pass allow_changes=True (allow_changed_settings=true in the recipes) to mix them "
            "knowingly."
        )
        if not allow_changes:
            raise ValueError(message)
        logger.warning(message)
    if diffs or recorded is None:
        write_run_settings(out_dir, now)
    return diffs


def write_run_settings(out_dir: str | os.PathLike, settings: Mapping[str, Any]) -> None:
    """Writes ``<out_dir>/settings.json`` (flattened, sorted); :func:`check_run_settings` and
    :func:`~torchrl_options.experiments.merge_results` call it."""
    os.makedirs(out_dir, exist_ok=True)
    save_json_file(flatten_settings(settings), os.path.join(out_dir, SETTINGS_FILE), indent=1, sort_keys=True)
