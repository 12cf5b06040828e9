"""Demonstrations on disk for streamed discovery: a replay buffer over ``LazyMemmapStorage`` that holds whole
trajectories (:func:`demonstration_buffer`), filled from tensordicts or a collector's batches
(:func:`write_demonstrations`) or from demonstration files (:func:`write_demonstration_files`), and opened again
by another process (:func:`open_demonstrations`).

The layout is TorchRL's own "steps" layout: one storage item per step, each trajectory's steps one after another,
numbered by ``("collector", "traj_ids")``; a collector given ``replay_buffer=demonstration_buffer(...)`` and
``trajs_per_batch`` writes the same layout itself. :class:`~torchrl_options.data.TrajectoryReader` reads whole
trajectories back; :func:`~torchrl_options.discover_options` takes the buffer and streams minibatches of them.

Examples:
    >>> import tempfile
    >>> from torchrl_options.testing import planted_corridor_demonstrations
    >>> path = tempfile.mkdtemp() + "/demos"
    >>> buffer = demonstration_buffer(10_000, path=path)
    >>> write_demonstrations(buffer, planted_corridor_demonstrations(4, 100, seed=0))
    400
    >>> write_demonstrations(buffer, planted_corridor_demonstrations(2, 50, seed=1))
    100
    >>> reopened = open_demonstrations(path)
    >>> len(reopened), TrajectoryReader(reopened).lengths.tolist()
    (500, [100, 100, 100, 100, 50, 50])
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import torch
from tensordict import pad_sequence, TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyMemmapStorage, ReplayBuffer, TensorStorage

from torchrl_options.checks import check_int, check_nested_key
from torchrl_options.data.trajectory_reader import TrajectoryReader

__all__ = [
    "MANIFEST",
    "demonstration_buffer",
    "open_demonstrations",
    "write_demonstration_files",
    "write_demonstrations",
]

MANIFEST = "demonstrations.json"
"""The file :func:`write_demonstrations` keeps next to a buffer's memory-mapped files: the steps and trajectories
written so far (``{"steps": ..., "trajectories": ..., "trajectory_key": [...]}``), read by
:func:`open_demonstrations`."""

_MASK = ("collector", "mask")


def demonstration_buffer(capacity: int, *, path: str | os.PathLike | None = None, batch_size: int | None = None) -> ReplayBuffer:
    """A replay buffer for ``capacity`` demonstration steps, memory-mapped on disk (``LazyMemmapStorage``).

    Fill it with :func:`write_demonstrations` / :func:`write_demonstration_files`, or give it to a collector
    (``Collector(env, policy, replay_buffer=buffer, trajs_per_batch=n, ...)`` writes whole trajectories into it).

    Args:
        capacity (int): the most steps it holds (the files are sized for them when the first steps arrive).

    Keyword Args:
        path (str or path, optional): the directory of its files, kept after the process ends (then
            :func:`open_demonstrations` opens them again, in this process or another). ``None``: a temporary
            directory, removed at exit.
        batch_size (int, optional): the buffer's own ``sample()`` size (streamed discovery does not use it).

    Raises:
        ValueError: for a ``path`` that already holds files (open it with :func:`open_demonstrations`).

    Examples:
        >>> buffer = demonstration_buffer(1000)
        >>> len(buffer), type(buffer.storage).__name__
        (0, 'LazyMemmapStorage')
    """
    check_int(capacity, "capacity", minimum=1)
    check_int(batch_size, "batch_size", minimum=1, allow_none=True)
    if path is not None:
        path = Path(path)
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise ValueError(
                f"path {str(path)!r} already holds files: open written demonstrations with open_demonstrations(path), "
                "or give a new directory."
            )
    storage = LazyMemmapStorage(capacity, scratch_dir=None if path is None else str(path))
    return ReplayBuffer(storage=storage, batch_size=batch_size)


def open_demonstrations(path: str | os.PathLike, *, batch_size: int | None = None) -> ReplayBuffer:
    """The demonstrations that :func:`write_demonstrations` wrote at ``path``, as a replay buffer over their
    memory-mapped files (nothing is read into memory, nothing is unpickled).

    Every process of a distributed run can open the same directory: streamed discovery reads each process's shard
    of trajectories from it.

    Args:
        path (str or path): the ``path`` given to :func:`demonstration_buffer`.

    Keyword Args:
        batch_size (int, optional): the buffer's own ``sample()`` size.

    Raises:
        FileNotFoundError: when ``path`` or its manifest (:data:`MANIFEST`) does not exist.
        ValueError: for a manifest or files that cannot be read.
    """
    path = Path(path)
    manifest = path / MANIFEST
    if not manifest.exists():
        raise FileNotFoundError(
            f"{manifest} does not exist: {str(path)!r} holds no demonstrations written by write_demonstrations."
        )
    try:
        info = json.loads(manifest.read_text())
        steps = int(info["steps"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{manifest}: not a demonstrations manifest ({type(err).__name__}: {err}).") from None
    try:
        data = TensorDict.load_memmap(path, allow_pickle=False)
    except (RuntimeError, OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not readable memory-mapped demonstrations ({type(err).__name__}: {err}).") from None
    if not 0 < steps <= data.batch_size[0]:
        raise ValueError(f"{manifest}: says {steps} steps, but the files hold {data.batch_size[0]}.")
    return ReplayBuffer(storage=TensorStorage(data[:steps]), batch_size=batch_size)


def _trajectory_list(trajectories: TensorDictBase | Sequence[TensorDictBase], trajectory_key: NestedKey,
                     mask_key: NestedKey) -> TensorDictBase:  # fmt: skip
    """The valid steps of ``trajectories``, flat, one trajectory after another, with each step's trajectory number
    (from 0) at ``trajectory_key``."""
    if isinstance(trajectories, TensorDictBase):
        td = trajectories
        if td.ndim == 1 and trajectory_key in td.keys(include_nested=True):  # flat steps: split at the ids
            ids = td.get(trajectory_key).reshape(td.shape[0], -1)[:, 0]
            cut = torch.ones_like(ids, dtype=torch.bool)
            cut[1:] = ids[1:] != ids[:-1]
            for key in (("next", "done"), ("next", "truncated")):
                flag = td.get(key, None)
                if flag is not None:
                    cut[1:] |= flag.reshape(td.shape[0], -1)[:-1].any(-1).bool()
            number = torch.cumsum(cut.long(), 0) - 1
            flat = td.exclude(mask_key) if mask_key in td.keys(include_nested=True) else td.clone(False)
            flat.set(trajectory_key, number)
            return flat
        if td.ndim == 1:
            td = td.unsqueeze(0)
        if td.ndim != 2:
            raise ValueError(f"trajectories must be [B, T], [T] or flat [N] steps with {trajectory_key!r}, got batch "
                             f"size {list(td.batch_size)}.")  # fmt: skip
    else:
        if isinstance(trajectories, (str, bytes)) or not isinstance(trajectories, Sequence) or not trajectories:
            raise TypeError(
                "trajectories must be a TensorDict ([B, T] with its mask, one [T] trajectory, or flat steps with "
                f"trajectory ids) or a non-empty list of [T_i] TensorDicts, got {type(trajectories).__name__}."
            )
        for i, t in enumerate(trajectories):
            if not isinstance(t, TensorDictBase) or t.ndim != 1 or t.shape[0] == 0:
                raise ValueError(f"trajectories[{i}] must be a non-empty [T] TensorDict, got {type(t).__name__}.")
        lengths = torch.tensor([t.shape[0] for t in trajectories])
        td = pad_sequence(list(trajectories))
        td.set(mask_key, torch.arange(td.shape[1])[None] < lengths[:, None])
    B, T = td.batch_size
    mask = td.get(mask_key, None)
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool)
    if mask.dtype != torch.bool or mask.numel() != B * T:
        raise ValueError(f"the mask {mask_key!r} must be bool of shape {[B, T]}, got {mask.dtype} {list(mask.shape)}.")
    mask = mask.reshape(B, T)
    length = mask.sum(1)
    if ((torch.arange(T) < length[:, None]) != mask).any() or (length == 0).any():
        row = int((((torch.arange(T) < length[:, None]) != mask).any(1) | (length == 0)).nonzero()[0])
        raise ValueError(
            f"trajectory {row}'s mask {mask_key!r} is not its valid steps followed by padding (or it has no valid "
            "step): give each row one whole trajectory from its first step."
        )
    flat = td.exclude(mask_key)[mask] if mask_key in td.keys(include_nested=True) else td[mask]
    flat.set(trajectory_key, torch.repeat_interleave(torch.arange(B), length))
    return flat


def write_demonstrations(
    buffer: ReplayBuffer,
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    *,
    trajectory_key: NestedKey = ("collector", "traj_ids"),
    mask_key: NestedKey = _MASK,
) -> int:
    """Appends whole trajectories to a demonstration buffer, flat in TorchRL's steps layout.

    Accepts what :func:`~torchrl_options.discover_options` accepts: a ``[B, T]`` tensordict with its mask (padded at
    the end; missing: all steps valid), e.g. a collector's ``trajs_per_batch`` batch (``traj_format="padded"``) or
    :func:`~torchrl_options.segmentation.load_trajectories`'s result; one ``[T]`` trajectory; a list of ``[T_i]``
    trajectories; or flat steps with trajectory ids (``traj_format="cat"``), cut where the id changes or a step is
    done / truncated. The padding is dropped, each trajectory gets a new id at ``trajectory_key`` (the next after the
    buffer's last), and the steps are written one trajectory after another. When the buffer has a :data:`MANIFEST`
    directory (:func:`demonstration_buffer` with ``path``), the manifest is updated.

    Args:
        buffer (ReplayBuffer): a buffer over a ``TensorStorage`` of steps (:func:`demonstration_buffer`).
        trajectories: as above.

    Keyword Args:
        trajectory_key (NestedKey): where the trajectory ids go. Defaults to ``("collector", "traj_ids")``.
        mask_key (NestedKey): the mask of a ``[B, T]`` batch. Defaults to ``("collector", "mask")``.

    Returns:
        The number of steps written.

    Raises:
        ValueError: when the steps would not fit (a ring buffer would overwrite the oldest trajectories), when their
            entries, per-step shapes or dtypes differ from those already in the buffer, or for a mask that is not
            valid steps followed by padding.

    Examples:
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> buffer = demonstration_buffer(1000)
        >>> write_demonstrations(buffer, planted_corridor_demonstrations(3, 20, seed=0))
        60
        >>> buffer[:]["collector", "traj_ids"].unique().tolist()
        [0, 1, 2]
    """
    if not isinstance(buffer, ReplayBuffer):
        raise TypeError(f"buffer must be a TorchRL ReplayBuffer, got {type(buffer).__name__}.")
    trajectory_key = check_nested_key(trajectory_key, "trajectory_key")
    mask_key = check_nested_key(mask_key, "mask_key")
    storage = buffer.storage
    if not isinstance(storage, TensorStorage):
        raise TypeError(f"the buffer's storage must be a TensorStorage of steps (demonstration_buffer), got "
                        f"{type(storage).__name__}.")  # fmt: skip
    flat = _trajectory_list(trajectories, trajectory_key, mask_key)
    n = flat.shape[0]
    held = len(buffer)
    capacity = storage.max_size
    if held + n > capacity:
        raise ValueError(
            f"{n} steps do not fit: the buffer holds {held} of {capacity}, and writing past its capacity would "
            "overwrite its oldest trajectories. Make it larger (demonstration_buffer(capacity=...))."
        )
    first_id = 0
    if held:
        last = buffer[held - 1 : held]
        if last.ndim != 1:
            raise ValueError(f"write_demonstrations writes steps, but the buffer holds [T] trajectory items "
                             f"(batch size {list(last.batch_size[1:])}).")  # fmt: skip
        _check_same_entries(last, flat)
        if trajectory_key not in last.keys(include_nested=True):
            raise ValueError(f"the buffer's steps have no {trajectory_key!r} (trajectory_key) entry.")
        first_id = int(last.get(trajectory_key).reshape(-1)[0]) + 1
    number = flat.get(trajectory_key)
    flat.set(trajectory_key, number + first_id)
    buffer.extend(flat)
    scratch = getattr(storage, "scratch_dir", None)
    if scratch is not None:
        manifest = Path(scratch) / MANIFEST
        trajectories_written = int(number.max()) + 1 + first_id
        key = [trajectory_key] if isinstance(trajectory_key, str) else list(trajectory_key)
        manifest.write_text(json.dumps({"steps": held + n, "trajectories": trajectories_written, "trajectory_key": key}))
    return n


def _check_same_entries(held: TensorDictBase, new: TensorDictBase) -> None:
    """The new steps have the entries, per-step shapes and dtypes of those in the buffer."""
    def layout(td):
        return {k: (tuple(v.shape[1:]), v.dtype) for k, v in td.items(include_nested=True, leaves_only=True)}

    old, now = layout(held), layout(new)
    old.pop("index", None)
    if set(old) != set(now):
        raise ValueError(
            f"the trajectories' entries differ from those in the buffer: missing {sorted(map(str, set(old) - set(now)))}, "
            f"extra {sorted(map(str, set(now) - set(old)))}."
        )
    for key, (shape, dtype) in now.items():
        if old[key] != (shape, dtype):
            raise ValueError(f"entry {key!r}: the buffer holds per-step shape {list(old[key][0])} of {old[key][1]}, "
                             f"the trajectories {list(shape)} of {dtype}.")  # fmt: skip


def write_demonstration_files(
    buffer: ReplayBuffer,
    paths: Iterable[str | os.PathLike],
    *,
    format: str = "auto",
    trajectory_key: NestedKey = ("collector", "traj_ids"),
) -> int:
    """Appends the demonstrations of files, one file in memory at a time, to a demonstration buffer.

    Each file is read by :func:`~torchrl_options.segmentation.load_trajectories` (``.npz``, HDF5, a TensorDict
    directory or a ``.pt`` file of plain tensors; nothing is unpickled) and written by :func:`write_demonstrations`.

    Args:
        buffer (ReplayBuffer): a buffer over a ``TensorStorage`` of steps (:func:`demonstration_buffer`).
        paths (iterable of paths): the files, in order.

    Keyword Args:
        format (str): as :func:`~torchrl_options.segmentation.load_trajectories` takes it. Defaults to ``"auto"``.
        trajectory_key (NestedKey): where the trajectory ids go.

    Returns:
        The number of steps written.

    Examples:
        >>> import tempfile, os
        >>> from torchrl_options.segmentation import save_trajectories
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> folder = tempfile.mkdtemp()
        >>> files = [save_trajectories(planted_corridor_demonstrations(2, 30, seed=s), os.path.join(folder, f"{s}.npz"))
        ...          for s in range(3)]
        >>> buffer = demonstration_buffer(1000)
        >>> write_demonstration_files(buffer, files), TrajectoryReader(buffer).num_trajectories
        (180, 6)
    """
    from torchrl_options.segmentation.io import load_trajectories

    if not isinstance(buffer, ReplayBuffer):
        raise TypeError(f"buffer must be a TorchRL ReplayBuffer, got {type(buffer).__name__}.")
    if isinstance(paths, (str, bytes, os.PathLike)) or not isinstance(paths, Iterable):
        raise TypeError(f"paths must be an iterable of file paths (a list, even of one file), got {paths!r}.")
    total = 0
    for path in paths:
        total += write_demonstrations(buffer, load_trajectories(path, format=format), trajectory_key=trajectory_key)
    return total
