"""Files the package reads back: loaded without running code from them, and the random state of a run.

Every file this package writes and reads again (DQN checkpoints, discovered options, hierarchies, cached
trajectories) holds plain data only: tensors, numbers, strings, lists, tuples and dicts. :func:`load_file` reads
such a file with ``torch.load(..., weights_only=True)``, so a crafted file cannot run code on load; a file that
needs pickle is refused with an error naming it. Files written by older versions that pickled a ``TensorDict``
(cached greedy trajectories) can be converted once, by someone who trusts them, with :func:`convert_file` or
``python -m torchrl_options.checkpoints convert FILE --trust-file``.

:func:`rng_state` and :func:`set_rng_state` capture and restore every global random state a run draws from
(torch CPU and CUDA, numpy, Python's ``random``) as plain data, so that a run resumed from a checkpoint draws
the same numbers as one that was never interrupted; :func:`scoped_seed` seeds torch for a block and restores them
all after it.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import inspect
import json
import os
import pickle
import random
import re
import sys
import uuid
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_options.checks import with_article

__all__ = [
    "CheckpointFileError",
    "MissingFileError",
    "load_file",
    "save_file",
    "atomic_replace",
    "tensordict_to_plain",
    "tensordict_from_plain",
    "rng_state",
    "set_rng_state",
    "restores_global_rng",
    "scoped_seed",
    "convert_file",
    "load_json_file",
    "save_json_file",
]

_TD_FORMAT = "torchrl_options.tensordict/1"


class CheckpointFileError(ValueError):
    """A file the package cannot (or will not) read: the message names the file and what is wrong."""


class MissingFileError(CheckpointFileError, FileNotFoundError):
    """The file does not exist (both a ``ValueError`` and a ``FileNotFoundError``)."""


def _convert_hint(path: Path) -> str:
    return (
        f"If you wrote it yourself with an older torchrl_options and trust it, convert it once with "
        f"`python -m torchrl_options.checkpoints convert {os.fspath(path)} --trust-file`."
    )


def load_file(path: str | os.PathLike, *, what: str = "checkpoint", map_location: Any = None) -> Any:
    """Loads a file written by :func:`save_file` (or ``torch.save`` of plain data) without running code.

    Args:
        path (str or PathLike): the file.

    Keyword Args:
        what (str): what the file should be, for the error messages (e.g. ``"DQN checkpoint"``; a trailing
            ``" file"`` is dropped: the messages add it).
        map_location: passed to :func:`torch.load`.

    Returns:
        the plain data (dicts, lists, tuples, numbers, strings, tensors).

    Raises:
        MissingFileError: the file does not exist.
        CheckpointFileError: the file is empty, truncated or corrupt, or holds Python objects that only pickle
            could rebuild (refused: unpickling can run code).

    Examples:
        >>> import os, tempfile, torch
        >>> path = os.path.join(tempfile.mkdtemp(), "state.pt")
        >>> save_file({"step": 3, "weights": torch.ones(2)}, path)
        >>> load_file(path)["step"]
        3
        >>> open(path, "wb").close()
        >>> load_file(path)
        Traceback (most recent call last):
        ...
        torchrl_options.checkpoints.CheckpointFileError: ...state.pt: this checkpoint file is empty.
    """
    what = what[: -len(" file")] if what.endswith(" file") else what  # the messages say "... file" themselves
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or a path to the {what} file, got {type(path).__name__}.")
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"{os.fspath(path)}: no such {what} file.")
    if path.is_dir():
        raise CheckpointFileError(f"{os.fspath(path)}: expected {with_article(what)} file, got a directory.")
    if path.stat().st_size == 0:
        raise CheckpointFileError(f"{os.fspath(path)}: this {what} file is empty.")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        text = str(err)
        if not zipfile.is_zipfile(path):
            raise CheckpointFileError(
                f"{os.fspath(path)}: not a readable {what} file (corrupt, or not written by torch.save)."
            ) from None
        if "weights_only" in text or "Weights only" in text or "Unsupported global" in text:
            found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
            name = f"it needs {found.group(1)}" if found else "not plain data"
            raise CheckpointFileError(
                f"{os.fspath(path)}: refusing to load this {what} file: it holds Python objects that only pickle can "
                f"rebuild ({name}), and unpickling a file can run code. {_convert_hint(path)}"
            ) from None
        raise CheckpointFileError(f"{os.fspath(path)}: not a readable {what} file (corrupt: {err}).") from None
    except (EOFError, RuntimeError, OSError, zipfile.BadZipFile, ValueError, KeyError, IndexError) as err:
        raise CheckpointFileError(
            f"{os.fspath(path)}: not a readable {what} file (truncated or corrupt: {type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})."
        ) from None


def save_file(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save`` through a temporary file and an atomic rename (:func:`atomic_replace`: a killed run never
    leaves half a file, and concurrent writers of one path never share a temporary file).

    ``obj`` must be plain data (see :func:`load_file`); TensorDicts go through :func:`tensordict_to_plain`.

    Examples:
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "x.pt")
        >>> save_file([1, 2], path)
        >>> load_file(path)
        [1, 2]
    """
    with atomic_replace(path) as tmp:
        torch.save(obj, tmp)


def save_json_file(obj: Any, path: str | os.PathLike, **dump_kwargs: Any) -> None:
    """``json.dump`` through :func:`atomic_replace`: a run killed while writing leaves the old file or none.

    Examples:
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "info.json")
        >>> save_json_file({"seconds": 3.5}, path)
        >>> load_json_file(path, what="cell info")
        {'seconds': 3.5}
    """
    with atomic_replace(path) as tmp, open(tmp, "w") as f:
        json.dump(obj, f, **dump_kwargs)
        f.flush()
        os.fsync(f.fileno())


def load_json_file(path: str | os.PathLike, *, what: str = "JSON") -> Any:
    """Reads a JSON file, naming the file in the error when it is missing, empty or not valid JSON.

    Raises:
        MissingFileError: the file does not exist.
        CheckpointFileError: the file is empty, truncated or not JSON.

    Examples:
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "settings.json")
        >>> _ = open(path, "w").write('{"episodes": 2')
        >>> load_json_file(path, what="run settings")
        Traceback (most recent call last):
        ...
        torchrl_options.checkpoints.CheckpointFileError: ...settings.json: not a readable run settings file (expected JSON: Expecting ',' delimiter: line 1 column 15 (char 14)).
    """
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"{os.fspath(path)}: no such {what} file.")
    if path.is_dir():
        raise CheckpointFileError(f"{os.fspath(path)}: expected {with_article(what)} file, got a directory.")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise CheckpointFileError(f"{os.fspath(path)}: not a readable {what} file ({type(err).__name__}: {err}).") from None
    if not text.strip():
        raise CheckpointFileError(f"{os.fspath(path)}: this {what} file is empty (expected JSON).")
    try:
        return json.loads(text)
    except ValueError as err:
        raise CheckpointFileError(f"{os.fspath(path)}: not a readable {what} file (expected JSON: {err}).") from None


@contextlib.contextmanager
def atomic_replace(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary file name next to ``path`` (unique to this call: process, thread and a random part) for the
    block to write; when the block ends without an error, the file atomically replaces ``path``, otherwise it is
    removed. Readers (and runs that share an output folder) see the old file or the whole new one, never a part.

    Examples:
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "notes.txt")
        >>> with atomic_replace(path) as tmp:
        ...     _ = tmp.write_text("done")
        >>> open(path).read(), os.listdir(os.path.dirname(path))
        ('done', ['notes.txt'])
    """
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}-{uuid.uuid4().hex[:12]}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def tensordict_to_plain(td: TensorDictBase) -> dict[str, Any]:
    """A TensorDict as plain data (nested dicts of tensors and its batch size), for :func:`save_file`.

    Raises:
        ValueError: if the TensorDict holds non-tensor data (it would need pickle).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"a": torch.zeros(2, 3), ("next", "b"): torch.ones(2)}, [2])
        >>> back = tensordict_from_plain(tensordict_to_plain(td))
        >>> back.batch_size, bool((back["next", "b"] == 1).all())
        (torch.Size([2]), True)
    """
    td = td.to_tensordict() if td.is_memmap() else td
    tensors: dict[str, Any] = {}
    for key in td.keys(include_nested=True, leaves_only=True):
        value = td.get(key)
        if not isinstance(value, torch.Tensor):
            raise ValueError(f"tensordict_to_plain: entry {key!r} is {type(value).__name__}, not a tensor.")
        tensors["/".join((key,) if isinstance(key, str) else key)] = value
    return {"format": _TD_FORMAT, "batch_size": list(td.batch_size), "tensors": tensors}


def tensordict_from_plain(data: Any, source: str = "<data>") -> TensorDict:
    """The TensorDict saved by :func:`tensordict_to_plain` (``source`` names the file in errors)."""
    if not isinstance(data, Mapping) or data.get("format") != _TD_FORMAT:
        raise CheckpointFileError(f"{source}: not a tensordict file written by torchrl_options (no {_TD_FORMAT!r}).")
    td = TensorDict({}, batch_size=list(data["batch_size"]))
    for name, value in data["tensors"].items():
        td.set(tuple(name.split("/")), value)
    return td


# ------------------------------------------------------------------------------------------------ random state
def rng_state() -> dict[str, Any]:
    """Every global random state as plain data: torch CPU (and CUDA when initialised), numpy and Python.

    Examples:
        >>> import torch
        >>> state = rng_state()
        >>> a = torch.rand(3)
        >>> set_rng_state(state)
        >>> torch.equal(a, torch.rand(3))
        True
    """
    _, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss),
                  "cached_gaussian": float(cached)},
        "python": {"version": int(version), "internal": torch.tensor(internal, dtype=torch.int64),
                   "gauss_next": gauss_next},
    }  # fmt: skip
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restores what :func:`rng_state` captured."""
    torch.set_rng_state(state["torch"])
    np_state = state["numpy"]
    np.random.set_state(
        ("MT19937", np_state["keys"].numpy().astype(np.uint32), np_state["pos"], np_state["has_gauss"],
         np_state["cached_gaussian"])
    )  # fmt: skip
    py = state["python"]
    random.setstate((py["version"], tuple(int(v) for v in py["internal"].tolist()), py["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        cuda = list(state["cuda"])
        if len(cuda) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda)


@contextlib.contextmanager
def scoped_seed(seed: int) -> Iterator[None]:
    """``torch.manual_seed(seed)`` for the block only: afterwards every global random state (:func:`rng_state`:
    torch CPU, CUDA when already initialised, numpy, Python) is what it was before, also after an error or an
    interruption. A function that draws from the global generators (TorchRL's exploration modules and replay
    buffers do) is then reproducible from ``seed`` without changing the random numbers of its caller.

    Examples:
        >>> import torch
        >>> with scoped_seed(0):
        ...     a = torch.rand(2)
        >>> with scoped_seed(0):
        ...     b = torch.rand(2)
        >>> torch.equal(a, b)
        True
        >>> state = torch.get_rng_state()
        >>> with scoped_seed(1):
        ...     _ = torch.rand(3)
        >>> torch.equal(state, torch.get_rng_state())
        True
    """
    saved = rng_state()
    try:
        torch.manual_seed(seed)
        yield
    finally:
        set_rng_state(saved)


def restores_global_rng(func: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator for library functions that take a ``seed`` argument: when ``seed`` is given, the call may seed
    and draw from torch's global generator (module initialisation does), and every global random state
    (:func:`rng_state`) is put back as it was when the call returns or raises. Library code thus never changes
    its caller's random numbers; recipes seed the global generators themselves.

    Examples:
        >>> import torch
        >>> @restores_global_rng
        ... def init(seed=None):
        ...     torch.manual_seed(seed)
        ...     return torch.nn.Linear(2, 2).weight.detach()
        >>> state = torch.get_rng_state()
        >>> torch.equal(init(seed=0), init(seed=0)), torch.equal(state, torch.get_rng_state())
        (True, True)
    """
    signature = inspect.signature(func)
    if "seed" not in signature.parameters:
        raise TypeError(f"restores_global_rng needs a function with a `seed` parameter, got {func.__qualname__}.")

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        seed = signature.bind_partial(*args, **kwargs).arguments.get("seed")
        if seed is None:
            return func(*args, **kwargs)
        saved = rng_state()
        try:
            return func(*args, **kwargs)
        finally:
            set_rng_state(saved)

    return wrapper


# ---------------------------------------------------------------------------------------------- legacy files
def _to_plain(obj: Any) -> Any:
    if isinstance(obj, TensorDictBase):
        return tensordict_to_plain(obj)
    if isinstance(obj, Mapping):
        return {k: _to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_to_plain(v) for v in obj)
    return obj


def convert_file(path: str | os.PathLike, out: str | os.PathLike | None = None, *, trust_file: bool = False) -> Path:
    """Rewrites a file of an older torchrl_options (pickled TensorDicts) as plain data, in place or to ``out``.

    This unpickles the file, which can run code from it: it refuses unless ``trust_file=True``.

    Raises:
        ValueError: without ``trust_file=True``.
    """
    if not trust_file:
        raise ValueError(
            f"convert_file({os.fspath(path)!r}) unpickles the file, which can run code from it: pass "
            "trust_file=True only for a file you wrote yourself or otherwise trust."
        )
    path = Path(path)
    obj = torch.load(path, weights_only=False)  # explicit opt-in above: the one place that unpickles
    save_file(_to_plain(obj), out if out is not None else path)
    return Path(out) if out is not None else path


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrl_options.checkpoints")
    sub = parser.add_subparsers(dest="command", required=True)
    conv = sub.add_parser("convert", help="rewrite an old-format file as plain data (unpickles it once)")
    conv.add_argument("path")
    conv.add_argument("--out", default=None)
    conv.add_argument("--trust-file", action="store_true", help="confirm that you trust the file (required)")
    args = parser.parse_args(argv)
    try:
        target = convert_file(args.path, args.out, trust_file=args.trust_file)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"converted: {target}")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
