"""Loading demonstrations from files for segmentation, and saving them in the same format.

Three formats are read by :func:`load_trajectories`:

**TensorDict** (a directory written by ``TensorDict.save`` / ``TensorDict.memmap``, or a ``.pt`` file written by
:func:`save_trajectories`): a ``[B, T]`` tensordict in :class:`~torchrl_options.DDOLoss`'s layout, with
``"observation"``, ``"action"``, ``("next", "observation")`` and optionally ``("collector", "mask")`` (missing: all
steps valid), ``("next", "terminated")``, and reference boundaries ``"true_switch"`` (bool, a segment starts at
the step) and/or reference labels ``"true_option"``. Nothing is unpickled: a ``.pt`` file is read with
``weights_only=True`` (plain data: a dict of tensors) and a directory's pickled non-tensor entries are refused.

**NumPy** ``.npz`` **and HDF5** (``.h5``/``.hdf5``, needs ``h5py``): the same arrays at the root of the file, under
these keys. ``N`` trajectories, ``T`` steps (actions) each after padding, ``D`` observation features:

===================== ================================ ===========================================================
key                   shape                            meaning
===================== ================================ ===========================================================
``observations``      ``[N, T + 1, D]`` or ``[N, T, D]`` the states ``s_0 .. s_T`` (with the final state), or
                                                       ``s_0 .. s_{T-1}`` with ``next_observations``
``actions``           ``[N, T]`` int or ``[N, T, A]``  discrete actions (``[N, T]`` integers) or continuous ones
                      float                            (float; ``[N, T]`` floats are one-dimensional actions)
``next_observations`` ``[N, T, D]``, optional          ``s_1 .. s_T``; without it and with ``T`` observations,
                                                       each trajectory's last step is dropped (its next state is
                                                       unknown) and a warning is logged
``lengths``           ``[N]`` int, optional            valid steps of each trajectory (``1 .. T``); the rest is
                                                       padding and may hold anything. Default: all ``T``
``boundaries``        ``[N, T]`` bool/0-1, optional    reference boundaries: a segment starts at the step
``labels``            ``[N, T]`` int, optional         reference segment labels (boundaries where they change)
``terminated``        ``[N]`` bool, optional           the trajectory ends with its last segment's end
===================== ================================ ===========================================================

Trajectories of different lengths may also be stored one array per trajectory, without padding:
``observations_0``, ``actions_0``, ``next_observations_0``, ``boundaries_0``, ``labels_0``, ``observations_1``, ...
(shapes as above without the leading ``N``; ``terminated_0`` a scalar). Object ("ragged") arrays are not read:
they need pickle.

Bad files raise errors naming the file and the key: a missing key, a ragged array, mismatched shapes, NaN or
infinite values at a valid step, lengths out of range.
"""
from __future__ import annotations

import importlib.util
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_options.checkpoints import (
    _TD_FORMAT,
    CheckpointFileError,
    load_file,
    save_file,
    tensordict_from_plain,
    tensordict_to_plain,
)
from torchrl_options.checks import with_article

__all__ = ["TrajectoryFileError", "load_trajectories", "save_trajectories", "trajectories_from_arrays"]

logger = logging.getLogger(__name__)

_MASK = ("collector", "mask")
_PER_TRAJ = ("observations", "actions", "next_observations", "boundaries", "labels", "terminated")


class TrajectoryFileError(ValueError):
    """A demonstrations file that cannot be read: the message names the file and the key."""


def _fail(source: str, key: str, message: str) -> TrajectoryFileError:
    return TrajectoryFileError(f"{source}: {key!r} {message}")


def _detect_format(path: Path) -> str:
    if path.is_dir():
        return "tensordict"
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return "npz"
    if suffix in (".h5", ".hdf5", ".hdf"):
        return "hdf5"
    if suffix in (".pt", ".pth"):
        return "tensordict"
    raise TrajectoryFileError(
        f"{path}: cannot tell the format from the name; use a .npz, .h5/.hdf5 or .pt file, a TensorDict directory, "
        "or pass format=..."
    )


_EXPECTED = "the arrays 'observations' and 'actions' (see torchrl_options.segmentation.io)"


def _unreadable(source: str, kind: str, err: BaseException) -> TrajectoryFileError:
    detail = str(err).splitlines()[0] if str(err) else ""
    return TrajectoryFileError(
        f"{source}: not a readable {kind} file (truncated, corrupt or another format: {type(err).__name__}"
        f"{': ' + detail if detail else ''}); expected {with_article(kind)} file holding {_EXPECTED}."
    )


def _check_not_empty(path: Path, kind: str) -> None:
    if path.stat().st_size == 0:
        raise TrajectoryFileError(f"{path}: this {kind} file is empty; expected {with_article(kind)} file holding {_EXPECTED}.")


class _NpzReader(Mapping):
    """Read-only access to an ``.npz`` archive that turns numpy's errors (pickled data, a truncated or corrupt
    archive) into ones naming the file and the key."""

    def __init__(self, path: Path):
        import zipfile

        self._source = str(path)
        _check_not_empty(path, "NumPy .npz")
        try:
            self._file = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:
            # numpy reads a file that is not a zip archive as a pickle, which allow_pickle=False refuses
            raise _unreadable(self._source, "NumPy .npz", err) from None
        if not isinstance(self._file, np.lib.npyio.NpzFile):
            raise TrajectoryFileError(
                f"{self._source}: holds one array (a .npy file), not a NumPy .npz archive of named arrays; expected "
                f"{_EXPECTED}."
            )

    def __getitem__(self, key: str) -> np.ndarray:
        import zipfile
        import zlib

        try:
            return self._file[key]
        except KeyError:
            raise
        except ValueError as err:
            if "allow_pickle" in str(err) or "Object arrays" in str(err):
                raise _fail(
                    self._source, key,
                    "is a ragged (object) array. Store padded arrays with a 'lengths' array, or one array per "
                    f"trajectory ('{key}_0', '{key}_1', ...).",
                ) from None
            raise _fail(self._source, key, f"cannot be read (truncated or corrupt archive: {err}).") from None
        except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            raise _fail(self._source, key, f"cannot be read (truncated or corrupt archive: {type(err).__name__}: {err}).") from None

    def __iter__(self):
        return iter(self._file.files)

    def __len__(self) -> int:
        return len(self._file.files)


def _read_hdf5(path: Path) -> dict[str, np.ndarray]:
    if importlib.util.find_spec("h5py") is None:
        raise ImportError(f"reading {path} needs h5py: pip install h5py")
    import h5py

    out = {}
    _check_not_empty(path, "HDF5")
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as err:
        raise _unreadable(str(path), "HDF5", err) from None
    with f:
        for key, item in f.items():
            if not isinstance(item, h5py.Dataset):
                continue
            if item.dtype.kind == "O" or h5py.check_vlen_dtype(item.dtype) is not None:
                raise _fail(
                    str(path), key,
                    "is a ragged (variable-length) dataset. Store padded arrays with a 'lengths' array, or one "
                    f"dataset per trajectory ('{key}_0', '{key}_1', ...).",
                )
            try:
                out[key] = item[()]
            except (OSError, ValueError, TypeError) as err:
                raise _fail(str(path), key, f"cannot be read (truncated or corrupt file: {err}).") from None
    return out


def _pad_ragged(arrays: Mapping[str, np.ndarray], source: str) -> dict[str, np.ndarray]:
    """Turns the one-array-per-trajectory form into padded arrays with ``lengths``."""
    pattern = re.compile(r"^(.*)_(\d+)$")
    per: dict[str, dict[int, str]] = {}
    for key in arrays:
        m = pattern.match(key)
        if m and m.group(1) in _PER_TRAJ:
            per.setdefault(m.group(1), {})[int(m.group(2))] = key
    n = len(per["observations"])
    if sorted(per["observations"]) != list(range(n)):
        raise _fail(source, "observations_<i>", f"must be numbered 0..{n - 1} without gaps.")
    out: dict[str, np.ndarray] = {}
    for name, keys in per.items():
        missing = [i for i in range(n) if i not in keys]
        if missing:
            raise _fail(source, f"{name}_{missing[0]}", f"is missing ({n} trajectories have 'observations_<i>').")
        extra = sorted(set(keys) - set(range(n)))
        if extra:
            raise _fail(source, keys[extra[0]], f"has no matching 'observations_{extra[0]}'.")
        items = [np.asarray(arrays[keys[i]]) for i in range(n)]
        if name == "terminated":
            out[name] = np.array([bool(np.asarray(x).reshape(-1)[0]) if x.size else False for x in items])
            continue
        tail = items[0].shape[1:]
        for i, x in enumerate(items):
            if x.ndim == 0 or x.shape[1:] != tail:
                raise _fail(source, keys[i], f"has shape {x.shape}; expected [T_i{', ' if tail else ''}"
                            f"{', '.join(map(str, tail))}] like {keys[0]!r}.")
        longest = max(x.shape[0] for x in items)
        padded = np.zeros((n, longest, *tail), dtype=items[0].dtype)
        for i, x in enumerate(items):
            padded[i, : x.shape[0]] = x
        out[name] = padded
    if "actions" not in out:
        raise _fail(source, "actions_0", "is missing (needed with 'observations_0', ...).")
    out["lengths"] = np.array([np.asarray(arrays[per["actions"][i]]).shape[0] for i in range(n)])
    return out


def trajectories_from_arrays(arrays: Mapping[str, np.ndarray], source: str = "arrays") -> TensorDict:
    """Builds the ``[B, T]`` trajectory tensordict from the documented arrays (see the module docstring).

    Args:
        arrays: a mapping from the documented keys to arrays (padded, or one per trajectory).
        source (str): a name for error messages (the file).

    Examples:
        >>> import numpy as np
        >>> arrays = {"observations": np.random.rand(2, 6, 3), "actions": np.zeros((2, 5), dtype=np.int64),
        ...           "lengths": np.array([5, 3]), "labels": np.array([[0, 0, 1, 1, 1], [2, 2, 2, 0, 0]])}
        >>> td = trajectories_from_arrays(arrays)
        >>> td.batch_size, td["collector", "mask"].sum(1).tolist(), td["true_switch"].nonzero().tolist()
        (torch.Size([2, 5]), [5, 3], [[0, 0], [0, 2], [1, 0]])
        >>> trajectories_from_arrays({"actions": np.zeros((2, 5))})
        Traceback (most recent call last):
        ...
        torchrl_options.segmentation.io.TrajectoryFileError: arrays: 'observations' is missing (found keys: ['actions']).
    """
    if not isinstance(arrays, Mapping):
        raise TypeError(f"{source}: arrays must be a mapping from the documented keys to arrays, got {type(arrays).__name__}.")
    if "observations" not in arrays and "observations_0" in arrays:
        arrays = _pad_ragged(arrays, source)
    for key in ("observations", "actions"):
        if key not in arrays:
            raise _fail(source, key, f"is missing (found keys: {sorted(arrays)}).")
    arr = {k: np.asarray(arrays[k]) for k in arrays if k in _PER_TRAJ or k == "lengths"}
    for k, v in arr.items():
        if v.dtype == object:
            raise _fail(source, k, "is a ragged (object) array; store padded arrays with a 'lengths' array.")
    obs, actions = arr["observations"], arr["actions"]
    if obs.ndim != 3:
        raise _fail(source, "observations", f"must be [N, T, D] (or [N, T + 1, D]), got shape {obs.shape}.")
    if actions.ndim not in (2, 3):
        raise _fail(source, "actions", f"must be [N, T] or [N, T, A], got shape {actions.shape}.")
    N, T = actions.shape[:2]
    if N == 0 or T == 0:
        raise _fail(source, "actions", f"is empty (shape {actions.shape}).")
    if obs.shape[0] != N:
        raise _fail(source, "observations", f"has {obs.shape[0]} trajectories but 'actions' has {N}.")
    for key, x in (("observations", obs), ("actions", actions), ("next_observations", arr.get("next_observations"))):
        if x is not None and x.dtype.kind not in "biuf":
            raise _fail(source, key, f"must hold numbers (or booleans), got dtype {x.dtype}.")
    if not np.issubdtype(obs.dtype, np.number) or obs.dtype == bool:
        obs = obs.astype(np.float32)
    discrete = np.issubdtype(actions.dtype, np.integer) or actions.dtype == bool
    if discrete and actions.ndim == 3 and actions.shape[2] != 1:
        raise _fail(source, "actions", f"holds integers with shape {actions.shape}: discrete actions are [N, T].")
    if discrete and actions.ndim == 3:
        actions = actions[..., 0]
    if not discrete and actions.ndim == 2:
        actions = actions[..., None]

    if "lengths" in arr:
        lengths = arr["lengths"].reshape(-1)
        if lengths.shape[0] != N or not np.issubdtype(lengths.dtype, np.integer):
            raise _fail(source, "lengths", f"must be [N] = [{N}] integers, got {lengths.dtype} {lengths.shape}.")
        if lengths.min() < 1 or lengths.max() > T:
            bad = int(np.flatnonzero((lengths < 1) | (lengths > T))[0])
            raise _fail(source, "lengths", f"[{bad}] = {int(lengths[bad])} is outside 1..{T} (T from 'actions').")
    else:
        lengths = np.full(N, T)
    lengths = lengths.astype(np.int64)

    if "next_observations" in arr:
        nxt = arr["next_observations"]
        if nxt.shape[:2] != (N, T) or nxt.shape[2:] != obs.shape[2:]:
            raise _fail(source, "next_observations", f"must have shape {(N, T, *obs.shape[2:])}, got {nxt.shape}.")
        if obs.shape[1] not in (T, T + 1):
            raise _fail(source, "observations", f"has {obs.shape[1]} steps; 'actions' has {T}.")
        obs = obs[:, :T]
    elif obs.shape[1] == T + 1:
        nxt, obs = obs[:, 1:], obs[:, :T]
    elif obs.shape[1] == T:
        # s_{t+1} of the last step is unknown: drop that step
        logger.warning(
            "%s: no 'next_observations' and as many observations as actions: the last step of each trajectory is "
            "dropped (store T + 1 observations to keep it).", source,
        )
        if (lengths < 2).any():
            raise _fail(source, "observations", "has a trajectory of one step and no next observation to pair it with.")
        nxt = np.concatenate([obs[:, 1:], np.zeros_like(obs[:, :1])], 1)
        lengths = lengths - 1
    else:
        raise _fail(source, "observations", f"has {obs.shape[1]} steps; 'actions' has {T} (expected {T} or {T + 1}).")

    mask = np.arange(T)[None] < lengths[:, None]
    for key, x in (("observations", obs), ("next_observations", nxt), ("actions", actions)):
        if np.issubdtype(x.dtype, np.floating):
            bad = ~np.isfinite(x.reshape(N, T, -1)).all(-1) & mask
            if bad.any():
                i, t = np.argwhere(bad)[0]
                what = "next observation" if key == "next_observations" and "next_observations" not in arr else "value"
                raise _fail(source, key, f"holds NaN or inf ({what}) at trajectory {i}, step {t}.")
    if discrete and (actions[mask] < 0).any():
        i, t = np.argwhere((actions < 0) & mask)[0]
        raise _fail(source, "actions", f"holds a negative discrete action at trajectory {i}, step {t}.")

    td = TensorDict(
        {
            "observation": torch.as_tensor(np.where(mask[..., None], obs, 0), dtype=torch.float32),
            "action": torch.as_tensor(np.where(mask.reshape(N, T, *([1] * (actions.ndim - 2))), actions, 0)),
            "next": {"observation": torch.as_tensor(np.where(mask[..., None], nxt, 0), dtype=torch.float32)},
            _MASK: torch.as_tensor(mask),
        },
        batch_size=[N, T],
    )
    td["action"] = td["action"].long() if discrete else td["action"].float()
    if "terminated" in arr:
        term = arr["terminated"].reshape(-1).astype(bool)
        if term.shape[0] != N:
            raise _fail(source, "terminated", f"must be [N] = [{N}], got shape {arr['terminated'].shape}.")
        flag = np.zeros((N, T, 1), dtype=bool)
        flag[np.arange(N), lengths - 1, 0] = term
        td.set(("next", "terminated"), torch.as_tensor(flag))
    for key in ("boundaries", "labels"):
        if key in arr and (arr[key].ndim != 2 or arr[key].shape[0] != N or arr[key].shape[1] not in (T, T + 1)):
            raise _fail(source, key, f"must be [N, T] = {[N, T]} like 'actions', got shape {arr[key].shape}.")
    if "labels" in arr:
        labels = arr["labels"][:, :T].reshape(N, T)
        if not np.issubdtype(labels.dtype, np.integer):
            raise _fail(source, "labels", f"must hold integers, got {labels.dtype}.")
        switch = np.ones((N, T), dtype=bool)
        switch[:, 1:] = labels[:, 1:] != labels[:, :-1]
        td.set("true_option", torch.as_tensor(np.where(mask, labels, -1)).long())
        td.set("true_switch", torch.as_tensor(switch & mask))
    if "boundaries" in arr:
        b = arr["boundaries"][:, :T].reshape(N, T)
        if b.dtype != bool and not np.isin(b[mask], (0, 1)).all():
            raise _fail(source, "boundaries", "must hold booleans (or 0/1): True where a reference segment starts.")
        switch = b.astype(bool) & mask
        switch[:, 0] = True
        td.set("true_switch", torch.as_tensor(switch))
    return td


def _check_tensordict(td: TensorDictBase, source: str) -> TensorDict:
    if not isinstance(td, TensorDictBase):
        raise TrajectoryFileError(f"{source}: expected a TensorDict, got {type(td).__name__}.")
    td = td.to_tensordict() if td.is_memmap() else td
    if td.ndim == 1:
        td = td.unsqueeze(0)
    if td.ndim != 2:
        raise TrajectoryFileError(f"{source}: expected a [B, T] TensorDict, got batch_size {tuple(td.batch_size)}.")
    keys = td.keys(include_nested=True, leaves_only=True)
    for key in ("observation", "action", ("next", "observation")):
        if key not in keys:
            raise _fail(source, key if isinstance(key, str) else key, f"is missing (found keys: {sorted(map(str, keys))}).")
    B, T = td.batch_size
    mask = td.get(_MASK, None)
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool)
        td.set(_MASK, mask)
    mask = mask.reshape(B, T).bool()
    for key in ("observation", ("next", "observation"), "action"):
        x = td.get(key)
        if x.is_floating_point():
            bad = ~torch.isfinite(x.reshape(B, T, -1)).all(-1) & mask
            if bad.any():
                i, t = bad.nonzero()[0].tolist()
                raise _fail(source, key, f"holds NaN or inf at trajectory {i}, step {t}.")
    return td


def load_trajectories(path: str | Path, *, format: str = "auto") -> TensorDict:
    """Loads demonstrations as a ``[B, T]`` tensordict ready for discovery and segmentation.

    Args:
        path: a ``.npz``, ``.h5``/``.hdf5`` or ``.pt`` file, or a directory written by ``TensorDict.save``.

    Keyword Args:
        format (str): ``"auto"`` (by the name), ``"npz"``, ``"hdf5"`` or ``"tensordict"``.

    Returns:
        TensorDict: ``"observation"``, ``"action"``, ``("next", "observation")``, ``("collector", "mask")``, and
        when the file has them ``("next", "terminated")``, ``"true_switch"`` (reference boundaries, ``True`` at
        ``t = 0`` too) and ``"true_option"`` (reference labels).

    Raises:
        TrajectoryFileError: naming the file and the key, for missing keys, ragged arrays, bad shapes, NaN.
        FileNotFoundError: when ``path`` does not exist.

    Examples:
        >>> import numpy as np, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "demos.npz")
        >>> np.savez(path, observations=np.random.rand(3, 11, 2), actions=np.random.rand(3, 10, 2))
        >>> load_trajectories(path)["action"].shape
        torch.Size([3, 10, 2])
        >>> np.savez(path, observations=np.full((3, 11, 2), np.nan), actions=np.random.rand(3, 10, 2))
        >>> load_trajectories(path)
        Traceback (most recent call last):
        ...
        torchrl_options.segmentation.io.TrajectoryFileError: ...demos.npz: 'observations' holds NaN or inf (value) at trajectory 0, step 0.
    """
    if format not in ("auto", "npz", "hdf5", "tensordict"):
        raise ValueError(f"format must be 'auto', 'npz', 'hdf5' or 'tensordict', got {format!r}.")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"load_trajectories: path must be a str or a path, got {type(path).__name__}.")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such trajectories file or directory.")
    fmt = _detect_format(path) if format == "auto" else format
    source = str(path)
    if fmt == "npz":
        return trajectories_from_arrays(_NpzReader(path), source)
    if fmt == "hdf5":
        return trajectories_from_arrays(_read_hdf5(path), source)
    if fmt == "tensordict":
        return _check_tensordict(_read_tensordict(path, source), source)
    raise ValueError(f"format must be 'auto', 'npz', 'hdf5' or 'tensordict', got {format!r}.")


def _read_tensordict(path: Path, source: str) -> TensorDictBase:
    """A TensorDict directory (memory-mapped tensors only: pickled entries are refused) or a ``.pt`` file of plain
    data (loaded with ``weights_only=True``)."""
    if path.is_dir():
        if not (path / "meta.json").exists():
            raise TrajectoryFileError(f"{source}: not a TensorDict directory (no meta.json).")
        _check_memmap_files(path, source)
        try:
            return TensorDict.load_memmap(path, allow_pickle=False).to_tensordict()
        except RuntimeError as err:
            if "pickle" in str(err).lower():
                raise TrajectoryFileError(
                    f"{source}: holds pickled (non-tensor) entries; unpickling can run code, so they are not read. "
                    "Save the trajectories with tensors only."
                ) from None
            raise TrajectoryFileError(f"{source}: not a readable TensorDict directory ({err}).") from None
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise TrajectoryFileError(f"{source}: not a readable TensorDict directory ({type(err).__name__}: {err}).") from None
    if path.is_dir() is False and path.suffix.lower() not in (".pt", ".pth") and path.stat().st_size == 0:
        raise TrajectoryFileError(f"{source}: this trajectories file is empty.")
    try:
        data = load_file(path, what="trajectories")
    except CheckpointFileError as err:
        raise TrajectoryFileError(str(err)) from None
    if isinstance(data, Mapping) and data.get("format") == _TD_FORMAT:
        return tensordict_from_plain(data, source)
    if isinstance(data, Mapping) and data and all(isinstance(v, (torch.Tensor, Mapping)) for v in data.values()):
        return TensorDict.from_dict(dict(data), auto_batch_size=True, batch_dims=2)
    raise TrajectoryFileError(
        f"{source}: expected trajectories (a dict of tensors, as save_trajectories writes), got {type(data).__name__}."
    )


def _check_memmap_files(path: Path, source: str) -> None:
    """Checks, before loading, that every tensor file of a TensorDict directory holds the bytes its ``meta.json``
    announces: TensorDict maps a short (truncated) file and fills the rest with zeros, silently, extending the file
    on disk."""
    import json

    for meta_path in sorted(path.rglob("meta.json")):
        folder = meta_path.parent
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise TrajectoryFileError(
                f"{source}: not a readable TensorDict directory: {meta_path} is not valid JSON ({err})."
            ) from None
        if not isinstance(meta, dict):
            raise TrajectoryFileError(f"{source}: not a readable TensorDict directory: {meta_path} holds no mapping.")
        for name, entry in meta.items():
            if not isinstance(entry, dict) or "shape" not in entry or "dtype" not in entry or entry.get("is_nested"):
                continue
            dtype = getattr(torch, str(entry["dtype"]).replace("torch.", ""), None)
            if not isinstance(dtype, torch.dtype) or not isinstance(entry["shape"], list):
                raise TrajectoryFileError(
                    f"{source}: not a readable TensorDict directory: {meta_path} describes {name!r} with dtype "
                    f"{entry['dtype']!r} and shape {entry['shape']!r}."
                )
            expected = int(np.prod(entry["shape"], dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
            file = folder / f"{name}.memmap"
            if not file.exists():
                if expected == 0:
                    continue
                raise TrajectoryFileError(f"{source}: the TensorDict directory lacks {file} (entry {name!r}).")
            size = file.stat().st_size
            if size != expected:
                raise TrajectoryFileError(
                    f"{source}: {file} holds {size} bytes, but entry {name!r} ({entry['dtype']} of shape "
                    f"{entry['shape']}) needs {expected}: the directory is truncated or corrupt."
                )


def save_trajectories(data: TensorDictBase, path: str | Path, *, reference_key: str | None = "true_switch") -> Path:
    """Saves ``[B, T]`` trajectories in the documented ``.npz``/HDF5 format, or as a TensorDict.

    Padded arrays with ``lengths``; ``boundaries`` from ``reference_key`` when present and ``labels`` from
    ``"true_option"`` when present; ``terminated`` from ``("next", "terminated")`` at each last step. A path
    without a ``.npz``/``.h5``/``.hdf5``/``.pt`` suffix is written as a TensorDict directory (``TensorDict.save``).

    Examples:
        >>> import tempfile, os
        >>> from torchrl_options.segmentation import reach_grasp_demonstrations
        >>> data = reach_grasp_demonstrations(3, seed=0)
        >>> path = save_trajectories(data, os.path.join(tempfile.mkdtemp(), "demos.npz"))
        >>> back = load_trajectories(path)
        >>> bool((back["true_switch"] == data["true_switch"]).all()), back.batch_size == data.batch_size
        (True, True)
    """
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"save_trajectories: data must be a [B, T] TensorDict, got {type(data).__name__}.")
    if data.ndim != 2:
        raise ValueError(f"save_trajectories: data must be a [B, T] TensorDict, got batch_size {list(data.batch_size)}.")
    missing = [k for k in ("observation", "action", ("next", "observation")) if k not in data.keys(include_nested=True)]
    if missing:
        raise ValueError(f"save_trajectories: data lacks {missing} (it needs observation, action, ('next', 'observation')).")
    if reference_key is not None and not isinstance(reference_key, str):
        raise TypeError(f"save_trajectories: reference_key must be a str or None, got {reference_key!r}.")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"save_trajectories: path must be a str or a path, got {type(path).__name__}.")
    path = Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"save_trajectories: cannot write {path}: the folder {path.parent} does not exist.")
    suffix = path.suffix.lower()
    if suffix not in (".npz", ".h5", ".hdf5", ".pt", ".pth"):
        data.save(path)
        return path
    if suffix in (".pt", ".pth"):
        save_file(tensordict_to_plain(data), path)
        return path
    B, T = data.batch_size
    mask = data.get(_MASK, torch.ones(B, T, dtype=torch.bool)).reshape(B, T)
    arrays = {
        "observations": data["observation"].cpu().numpy(),
        "next_observations": data["next", "observation"].cpu().numpy(),
        "actions": data["action"].cpu().numpy(),
        "lengths": mask.sum(1).cpu().numpy(),
    }
    lengths = arrays["lengths"]
    term = data.get(("next", "terminated"), None)
    if term is not None:
        arrays["terminated"] = term.reshape(B, T).cpu().numpy()[np.arange(B), lengths - 1]
    if reference_key is not None and reference_key in data.keys():
        arrays["boundaries"] = data[reference_key].cpu().numpy().astype(bool)
    if "true_option" in data.keys():
        arrays["labels"] = data["true_option"].cpu().numpy()
    if suffix == ".npz":
        np.savez_compressed(path, **arrays)
    else:
        if importlib.util.find_spec("h5py") is None:
            raise ImportError(f"writing {path} needs h5py: pip install h5py")
        import h5py

        with h5py.File(path, "w") as f:
            for k, v in arrays.items():
                f.create_dataset(k, data=v)
    return path
