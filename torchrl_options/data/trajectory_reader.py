"""Whole trajectories read on demand from a TorchRL replay buffer's storage (:class:`TrajectoryReader`), so that a
consumer (streamed discovery) holds one minibatch of trajectories in memory, never the data set.

TorchRL 0.14's samplers draw fixed-length windows (``SliceSampler``'s ``slice_len`` / ``num_slices``,
``StreamingSliceSampler``): a window cuts a trajectory, and an E-step over a window is not the E-step over the
trajectory (its first step would start a fresh option). The reader therefore finds the trajectories of the storage
once (one pass over their ids, in chunks) and reads whole ones by index, through the buffer (``buffer[index]``, so
the buffer's transforms apply). Two storage layouts are read:

* **steps** (TorchRL's own: what a collector with ``replay_buffer=`` and ``trajs_per_batch`` writes, what
  ``SliceSampler`` samples from, what :func:`~torchrl_options.data.write_demonstrations` writes): one storage item
  per step, each trajectory's steps stored one after another with the same id at ``trajectory_key``. A trajectory
  ends where the id changes or a step is ``("next", "done")`` or ``("next", "truncated")``.
* **trajectories**: one storage item per trajectory, ``[T]`` steps padded at the end, the valid ones marked by
  ``("collector", "mask")`` (e.g. a collector's ``trajs_per_batch`` batches of one fixed length, extended into
  the buffer).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer, TensorStorage

from torchrl_options.checks import check_int, check_nested_key

__all__ = ["LAYOUTS", "TrajectoryReader"]

LAYOUTS = ("steps", "trajectories")
"""The storage layouts a :class:`TrajectoryReader` reads: one item per step, or one padded ``[T]`` item per
trajectory."""

_MASK = ("collector", "mask")
_END_KEYS = (("next", "done"), ("next", "truncated"))


@dataclass
class _Index:
    """Where the trajectories lie: item of the first step (steps) or the item (trajectories), and valid steps."""

    starts: torch.Tensor
    lengths: torch.Tensor


class TrajectoryReader:
    """The whole trajectories of a TorchRL replay buffer, found once and read by index.

    Construction checks the buffer and indexes its trajectories with one pass over their ids (steps layout) or masks
    (trajectories layout), ``scan_size`` items at a time; :meth:`read` then returns any set of trajectories as a
    ``[B, T]`` batch padded at the end, with the ``("collector", "mask")`` of valid steps, as
    :func:`~torchrl_options.as_trajectory_batch` makes it. Memory: the index (two ints per trajectory) and what
    :meth:`read` returns.

    Args:
        buffer (ReplayBuffer): a TorchRL replay buffer over a ``TensorStorage`` (``LazyMemmapStorage``,
            ``LazyTensorStorage``, ``TensorStorage``) of tensordicts, one dimension indexed (``ndim=1``).

    Keyword Args:
        trajectory_key (NestedKey): the trajectory ids of the steps layout. Defaults to
            ``("collector", "traj_ids")``, what TorchRL's collectors write.
        scan_size (int): items read at a time while indexing. Defaults to ``2**20``.

    Raises:
        TypeError: for another object than a replay buffer, a storage that is not a ``TensorStorage`` (a
            ``ListStorage``), or items that are not tensordicts.
        ValueError: for an empty buffer, a storage indexed along more than one dimension, steps without
            ``trajectory_key`` (or trajectory items without their mask), a trajectory stored in pieces (its id
            comes back after other trajectories' steps without an end flag between: interleaved writes), a
            ring buffer that has overwritten its oldest steps, and masks that are not a run of valid steps
            followed by padding.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> steps = TensorDict({"x": torch.arange(7.0), ("collector", "traj_ids"): torch.tensor([4, 4, 4, 1, 1, 9, 9])}, [7])
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(100))
        >>> _ = buffer.extend(steps)
        >>> reader = TrajectoryReader(buffer)
        >>> reader.layout, reader.num_trajectories, reader.lengths.tolist()
        ('steps', 3, [3, 2, 2])
        >>> batch = reader.read(torch.tensor([2, 0]))
        >>> batch["x"].tolist(), batch["collector", "mask"].tolist()
        ([[5.0, 6.0, 0.0], [0.0, 1.0, 2.0]], [[True, True, False], [True, True, True]])
    """

    def __init__(
        self,
        buffer: ReplayBuffer,
        *,
        trajectory_key: NestedKey = ("collector", "traj_ids"),
        scan_size: int = 2**20,
    ) -> None:
        if not isinstance(buffer, ReplayBuffer):
            raise TypeError(f"buffer must be a TorchRL ReplayBuffer, got {type(buffer).__name__}.")
        self.trajectory_key = check_nested_key(trajectory_key, "trajectory_key")
        check_int(scan_size, "scan_size", minimum=1)
        storage = buffer.storage
        if not isinstance(storage, TensorStorage):
            raise TypeError(
                "the replay buffer's storage must be a TensorStorage of tensordicts (LazyMemmapStorage, "
                f"LazyTensorStorage, TensorStorage), so that whole trajectories can be read by index; got "
                f"{type(storage).__name__}."
            )
        if getattr(storage, "ndim", 1) != 1:
            raise ValueError(
                f"the replay buffer's storage must index one dimension (ndim=1: items are steps or [T] trajectories), "
                f"got ndim={storage.ndim}: store the steps flat, one trajectory after another."
            )
        num_items = len(buffer)
        if num_items == 0:
            raise ValueError("the replay buffer is empty: write demonstrations into it first (write_demonstrations).")
        first = buffer[0:1]
        if not isinstance(first, TensorDictBase):
            raise TypeError(f"the replay buffer must hold tensordicts, got {type(first).__name__} items.")
        self.buffer, self.num_items, self.scan_size = buffer, num_items, scan_size
        if first.ndim == 1:
            self.layout = "steps"
            written = getattr(buffer, "write_count", 0)
            capacity = getattr(storage, "max_size", num_items)
            if isinstance(written, int) and written > capacity:
                raise ValueError(
                    f"the replay buffer has written {written} steps into a storage of {capacity}: it has overwritten "
                    "its oldest steps, so its oldest trajectory may have lost its beginning. Give the storage room "
                    "for every step (demonstration_buffer(capacity=...))."
                )
            if self.trajectory_key not in first.keys(include_nested=True):
                raise ValueError(
                    f"the replay buffer stores steps (items of batch size [] ) but they have no trajectory ids at "
                    f"{self.trajectory_key!r} (trajectory_key): steps need the id of their trajectory (TorchRL's "
                    f"collectors write ('collector', 'traj_ids'); write_demonstrations numbers them); entries: "
                    f"{sorted(map(str, first.keys(include_nested=True, leaves_only=True)))}."
                )
            self._index = self._scan_steps()
        elif first.ndim == 2:
            self.layout = "trajectories"
            if _MASK not in first.keys(include_nested=True):
                raise ValueError(
                    f"the replay buffer stores [T] trajectories (items of batch size {list(first.batch_size[1:])}) "
                    f"without their {_MASK!r} of valid steps: store them with the mask (a collector's trajs_per_batch "
                    "batches have it), or store the steps flat with trajectory ids."
                )
            self._index = self._scan_trajectories()
        else:
            raise ValueError(
                f"the replay buffer's items must be steps (batch size []) or [T] trajectories, got items of batch "
                f"size {list(first.batch_size[1:])}."
            )

    def _items(self, start: int, stop: int) -> TensorDictBase:
        return self.buffer.storage[start:stop]

    def _scan_steps(self) -> _Index:
        """Runs of equal ids (cut after an end flag too), each a trajectory; a trajectory stored in pieces is
        refused."""
        starts, ids, closed = [], [], []  # closed: whether the run before each cut ends with an end flag
        prev_id, prev_end = None, None
        for a in range(0, self.num_items, self.scan_size):
            b = min(a + self.scan_size, self.num_items)
            chunk = self._items(a, b)
            traj = chunk.get(self.trajectory_key).reshape(b - a, -1)
            if traj.shape[1] != 1:
                raise ValueError(f"the trajectory ids {self.trajectory_key!r} must hold one id per step, got shape "
                                 f"{list(chunk.get(self.trajectory_key).shape)} for {b - a} steps.")  # fmt: skip
            traj = traj[:, 0].to(torch.int64)
            end = torch.zeros(b - a, dtype=torch.bool)
            for key in _END_KEYS:
                flag = chunk.get(key, None)
                if flag is not None:
                    end |= flag.reshape(b - a, -1).any(-1).bool()
            cut = torch.zeros(b - a, dtype=torch.bool)
            cut[1:] = (traj[1:] != traj[:-1]) | end[:-1]
            cut[0] = prev_id is None or bool(traj[0] != prev_id) or bool(prev_end)
            local = cut.nonzero().squeeze(1)
            starts.append(local + a)
            ids.append(traj[local])
            before = end[(local - 1).clamp_min(0)]
            if local.numel() and int(local[0]) == 0:
                before[0] = bool(prev_end) if prev_end is not None else False
            closed.append(before)
            prev_id, prev_end = traj[-1], end[-1]
        starts_t, run_ids = torch.cat(starts), torch.cat(ids)
        # ended[j]: run j ends with an end flag (the flag before run j + 1's start; the last run: its last step's)
        ended = torch.cat([torch.cat(closed)[1:], prev_end.reshape(1)])
        lengths = torch.diff(starts_t, append=torch.tensor([self.num_items]))
        self._check_pieces(run_ids, ended, starts_t)
        return _Index(starts_t, lengths)

    def _check_pieces(self, run_ids: torch.Tensor, ended: torch.Tensor, starts: torch.Tensor) -> None:
        """A run whose id comes back in a later run must end with an end flag, else the trajectory is in pieces."""
        order = torch.sort(run_ids, stable=True).indices
        sorted_ids = run_ids[order]
        again = torch.zeros_like(sorted_ids, dtype=torch.bool)
        again[:-1] = sorted_ids[:-1] == sorted_ids[1:]  # a later run (in storage order) has the same id
        bad = again & ~ended[order]
        if bad.any():
            i = int(bad.nonzero()[0])
            first, later = int(starts[order[i]]), int(starts[order[i + 1]])
            raise ValueError(
                f"trajectory {int(sorted_ids[i])} (ids at {self.trajectory_key!r}) is stored in pieces: its steps "
                f"start at item {first} and again at item {later}, with other steps between and no "
                "('next', 'done') or ('next', 'truncated') flag closing the first piece. Streamed discovery reads "
                "whole trajectories: write each trajectory's steps one after another (write_demonstrations, or a "
                "collector with replay_buffer= and trajs_per_batch)."
            )

    def _scan_trajectories(self) -> _Index:
        lengths = []
        for a in range(0, self.num_items, self.scan_size):
            b = min(a + self.scan_size, self.num_items)
            mask = self._items(a, b).get(_MASK)
            mask = mask.reshape(b - a, -1)
            if mask.dtype != torch.bool:
                raise ValueError(f"the mask {_MASK!r} must be bool (True at valid steps), got dtype {mask.dtype}.")
            length = mask.sum(1)
            prefix = torch.arange(mask.shape[1]) < length[:, None]
            bad = (mask != prefix).any(1) | (length == 0)
            if bad.any():
                i = int(bad.nonzero()[0])
                raise ValueError(
                    f"trajectory item {a + i} of the replay buffer has a {_MASK!r} that is not its valid steps "
                    "followed by padding (or has no valid step): each item must hold one whole trajectory from its "
                    "first step."
                )
            lengths.append(length)
        lengths_t = torch.cat(lengths).to(torch.int64)
        return _Index(torch.arange(self.num_items), lengths_t)

    @property
    def num_trajectories(self) -> int:
        """The trajectories of the buffer."""
        return int(self._index.lengths.numel())

    @property
    def lengths(self) -> torch.Tensor:
        """``[N]`` long: each trajectory's valid steps."""
        return self._index.lengths

    @property
    def num_steps(self) -> int:
        """The valid steps of all the trajectories."""
        return int(self._index.lengths.sum())

    def max_length(self, rows: torch.Tensor | None = None) -> int:
        """The longest trajectory (of ``rows``)."""
        lengths = self._index.lengths if rows is None else self._index.lengths[rows]
        return int(lengths.max())

    def read(self, rows: torch.Tensor) -> TensorDictBase:
        """Trajectories ``rows`` (in that order) as a ``[len(rows), T]`` batch, ``T`` the longest of them, padded
        with zeros at the end, with the ``("collector", "mask")`` of valid steps.

        Args:
            rows (Tensor): long, trajectory numbers in ``[0, num_trajectories)``.
        """
        rows = torch.as_tensor(rows, dtype=torch.int64).reshape(-1)
        if rows.numel() == 0:
            raise ValueError("rows is empty: read at least one trajectory.")
        if int(rows.min()) < 0 or int(rows.max()) >= self.num_trajectories:
            raise ValueError(f"rows must be in [0, {self.num_trajectories}), got {rows.min().item()}..{rows.max().item()}.")
        lengths = self._index.lengths[rows]
        T = int(lengths.max())
        B = rows.numel()
        if self.layout == "trajectories":
            return self.buffer[self._index.starts[rows]][:, :T]
        total = int(lengths.sum())
        offsets = torch.cumsum(lengths, 0) - lengths
        within = torch.arange(total) - torch.repeat_interleave(offsets, lengths)
        items = torch.repeat_interleave(self._index.starts[rows], lengths) + within
        flat = self.buffer[items]
        position = torch.repeat_interleave(torch.arange(B) * T, lengths) + within
        if total == B * T:  # no padding: already in row order
            batch = flat.reshape(B, T)
        else:
            padded = flat.apply(lambda x: x.new_zeros((B * T, *x.shape[1:])), batch_size=[B * T])
            padded[position] = flat
            batch = padded.reshape(B, T)
        batch.set(_MASK, (torch.arange(T) < lengths[:, None]).to(flat.get(self.trajectory_key).device))
        return batch

    def scan(self, key: NestedKey) -> torch.Tensor:
        """The largest value of entry ``key`` over the valid steps of every trajectory (one pass, ``scan_size``
        items at a time)."""
        best = None
        for a in range(0, self.num_items, self.scan_size):
            b = min(a + self.scan_size, self.num_items)
            chunk = self._items(a, b)
            values = chunk.get(key, None)
            if values is None:
                raise ValueError(f"the trajectories have no {key!r} entry; entries: "
                                 f"{sorted(map(str, chunk.keys(include_nested=True, leaves_only=True)))}.")  # fmt: skip
            if self.layout == "trajectories":
                values = values[chunk.get(_MASK).reshape(values.shape[:2])]
            top = values.max() if values.numel() else None
            if top is not None:
                best = top if best is None else torch.maximum(best, top)
        return best

    def shard(self, rank: int, world_size: int) -> torch.Tensor:
        """The trajectories of one of ``world_size`` disjoint shards: ``rank, rank + world_size, ...`` (lengths
        balanced when the trajectories are alike)."""
        check_int(world_size, "world_size", minimum=1)
        check_int(rank, "rank", minimum=0, maximum=world_size - 1)
        if self.num_trajectories < world_size:
            raise ValueError(
                f"the replay buffer holds {self.num_trajectories} trajectories, fewer than the {world_size} processes: "
                "each process needs at least one."
            )
        return torch.arange(rank, self.num_trajectories, world_size)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(layout={self.layout!r}, num_trajectories={self.num_trajectories}, "
                f"num_steps={self.num_steps}, max_length={self.max_length()})")  # fmt: skip
