"""The demonstrations of a discovery run: trajectories brought into one ``[B, T]`` batch with a validity mask
(:func:`as_trajectory_batch`) and checked once, at the door (:func:`discovery_batch`); the stages of
:mod:`~torchrl_options.discovery.stages` receive the checked :class:`DiscoveryBatch` and never check it again.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from tensordict import pad_sequence, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

from torchrl_options.discovery.settings import DiscoverySettings
from torchrl_options.discovery.streaming import as_replay_buffer, trajectory_stream, TrajectoryStream
from torchrl_options.discovery.validation import (
    check_meta_control_module,
    check_options_module,
    check_step_data,
    check_trajectories,
)

__all__ = [
    "DiscoveryBatch",
    "MASK_KEY",
    "as_trajectory_batch",
    "discovery_batch",
    "infer_in_features",
    "minibatch",
    "minibatch_rows",
]

logger = logging.getLogger(__name__)

MASK_KEY: tuple[str, str] = ("collector", "mask")
"""Where a trajectory batch holds its ``[B, T]`` bool mask of valid steps (the key TorchRL's ``split_trajectories``
writes)."""


def as_trajectory_batch(
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    *,
    trajectory_key: NestedKey | None = None,
    mask_key: NestedKey = MASK_KEY,
) -> TensorDictBase:
    """Brings trajectories into the ``[B, T]`` layout with a validity mask that :class:`DDOLoss` reads.

    Accepts a ``[B, T]`` tensordict (a missing mask means all steps valid), a single ``[T]`` trajectory, a list
    of ``[T_i]`` trajectories of different lengths (padded at the end), or, with ``trajectory_key``, a flat
    ``[N]`` replay-buffer sample of trajectory slices (e.g. from a ``SliceSampler``). Slices are cut where the
    trajectory id changes or a step is ``("next", "done")`` or ``("next", "truncated")`` (the sampler marks
    each slice's end so): unlike ``split_trajectories``, two slices of one trajectory in a sample stay apart.

    Keyword Args:
        trajectory_key (NestedKey, optional): the trajectory ids of a flat sample.
        mask_key (NestedKey): where to write the mask. Defaults to ``("collector", "mask")``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> trajs = [TensorDict({"observation": torch.randn(t, 2)}, [t]) for t in (3, 5)]
        >>> batch = as_trajectory_batch(trajs)
        >>> batch.batch_size, batch["collector", "mask"].sum(1)
        (torch.Size([2, 5]), tensor([3, 5]))
        >>> flat = TensorDict({"observation": torch.randn(7, 2), "ids": torch.tensor([4, 4, 4, 1, 1, 4, 4])}, [7])
        >>> as_trajectory_batch(flat, trajectory_key="ids")["collector", "mask"].sum(1)
        tensor([3, 2, 2])
    """
    check_trajectories(trajectories, trajectory_key=trajectory_key, mask_key=mask_key)
    if isinstance(trajectories, TensorDictBase):
        td = trajectories
        if td.ndim == 1 and trajectory_key is not None:
            return as_trajectory_batch(_split_slices(td, trajectory_key), mask_key=mask_key)
        if td.ndim == 1:
            td = td.unsqueeze(0)
        if td.ndim != 2:
            raise ValueError(f"trajectories must be [B, T] (or one [T] trajectory), got batch_size {tuple(td.batch_size)}.")
        if mask_key not in td.keys(include_nested=True):
            td = td.clone(False)
            td.set(mask_key, torch.ones(td.batch_size, dtype=torch.bool, device=td.device))
        return td
    trajectories = list(trajectories)
    if not trajectories:
        raise ValueError("trajectories is an empty list: discovery needs at least one trajectory.")
    for i, t in enumerate(trajectories):
        if not isinstance(t, TensorDictBase) or t.ndim != 1 or t.numel() == 0:
            raise ValueError(f"trajectories[{i}] must be a non-empty [T] tensordict, got {type(t).__name__}.")
    lengths = torch.tensor([t.numel() for t in trajectories])
    td = pad_sequence(trajectories)
    td.set(mask_key, (torch.arange(td.shape[1])[None] < lengths[:, None]).to(td.device))
    return td


def _split_slices(flat: TensorDictBase, trajectory_key: NestedKey) -> list[TensorDictBase]:
    ids = flat.get(trajectory_key, None)
    if ids is None:
        raise KeyError(f"the sample has no {trajectory_key!r} entry (trajectory_key).")
    ids = ids.reshape(-1)
    cut = torch.zeros_like(ids, dtype=torch.bool)
    cut[1:] = ids[1:] != ids[:-1]
    for key in (("next", "done"), ("next", "truncated")):
        flag = flat.get(key, None)
        if flag is not None:
            cut[1:] |= flag.reshape(-1)[:-1].bool()
    starts = cut.nonzero().flatten().tolist()
    bounds = [0, *starts, ids.numel()]
    return [flat[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


def minibatch_rows(num_rows: int, batch_size: int | None, generator: torch.Generator) -> torch.Tensor | None:
    """The rows of a minibatch: ``batch_size`` of ``num_rows`` drawn without replacement, ``None`` for all rows."""
    if batch_size is None or batch_size >= num_rows:
        return None
    return torch.randperm(num_rows, generator=generator)[:batch_size]


def minibatch(data: TensorDictBase, batch_size: int | None, generator: torch.Generator) -> TensorDictBase:
    """``batch_size`` trajectories drawn without replacement (all of them when ``batch_size`` is ``None``)."""
    rows = minibatch_rows(data.batch_size[0], batch_size, generator)
    return data if rows is None else data[rows.to(data.device)]


def infer_in_features(td: TensorDictBase, obs_keys: Sequence[NestedKey]) -> int:
    """The number of input features of the ``obs_keys`` entries of a ``[B, T]`` (or ``[N]``) tensordict: their
    per-step sizes summed (a scalar entry counts 1).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> infer_in_features(TensorDict({"a": torch.zeros(2, 3, 4), "b": torch.zeros(2, 3)}, [2, 3]), ["a", "b"])
        5
    """
    total = 0
    for key in obs_keys:
        x = td.get(key, None)
        if x is None:
            raise KeyError(f"the trajectories have no {key!r} entry (obs_keys).")
        total += x.shape[td.ndim :].numel() if x.ndim > td.ndim else 1
    return total


@dataclass
class DiscoveryBatch:
    """The checked demonstrations of one discovery run, on the training device.

    Attributes:
        data (TensorDictBase): ``[B, T]`` trajectories with their mask at :data:`MASK_KEY` (with a replay buffer: its
            evaluation set, :mod:`~torchrl_options.discovery.streaming`).
        num_actions (int or None): A, given or inferred for default discrete options; ``None`` otherwise.
        buffer (ReplayBuffer or None): the replay buffer the trajectories are streamed from.
        trajectory_key (NestedKey): the trajectory ids of a buffer's steps.
        stream (TrajectoryStream or None): how each iteration reads the buffer's trajectories.
    """

    data: TensorDictBase
    num_actions: int | None = None
    buffer: ReplayBuffer | None = None
    trajectory_key: NestedKey = ("collector", "traj_ids")
    stream: TrajectoryStream | None = None

    @property
    def mask(self) -> torch.Tensor:
        return self.data.get(MASK_KEY)

    @property
    def device(self) -> torch.device:
        return self.data.device

    @property
    def num_trajectories(self) -> int:
        return self.data.batch_size[0]

    def with_data(self, data: TensorDictBase) -> DiscoveryBatch:
        """The same run on ``data``: rows of :attr:`data` (a training share), which stay checked."""
        return replace(self, data=data)


def discovery_batch(
    trajectories: TensorDictBase | Sequence[TensorDictBase] | ReplayBuffer,
    settings: DiscoverySettings,
    *,
    options: TensorDictModuleBase | None = None,
    meta_control: TensorDictModuleBase | None = None,
    infer_num_actions: bool = True,
) -> DiscoveryBatch:
    """The door of discovery's data: pads (or splits) the trajectories once, checks the batch once and moves it to
    the training device.

    Lists are padded, a ``[T]`` trajectory gets its batch dimension, a replay buffer is sampled once (its later
    samples are split the same way, :meth:`DiscoveryBatch.sample`). The batch is checked by
    :func:`~torchrl_options.discovery.validation.check_step_data` (entries, shapes, masks, finite observations,
    actions in range), and the given modules run once on one step of it
    (:func:`~torchrl_options.discovery.validation.check_options_module`). With ``infer_num_actions`` and discrete
    actions, a missing ``num_actions`` is ``max(action) + 1`` over the valid steps.

    Args:
        trajectories: as :func:`~torchrl_options.discover_options` takes them.
        settings (DiscoverySettings): the run's settings (keys, action space, ``num_actions``, ``device``).

    Keyword Args:
        options (TensorDictModuleBase, optional): an options module given by the caller, checked on the data.
        meta_control (TensorDictModuleBase, optional): a meta-control module given by the caller, checked too.
        infer_num_actions (bool): infer a missing ``num_actions`` for discrete actions. Defaults to ``True``.

    Examples:
        >>> from torchrl_options.discovery.settings import DiscoverySettings
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> batch = discovery_batch(planted_corridor_demonstrations(4, 10, seed=0), DiscoverySettings(2))
        >>> batch.data.batch_size, batch.num_actions, batch.mask.all().item()
        (torch.Size([4, 10]), 2, True)
    """
    obs_keys, action_key = settings.obs_key_list, settings.action_key
    buffer = trajectories if isinstance(trajectories, ReplayBuffer) else None
    num_actions = settings.num_actions
    stream = None
    if buffer is None and settings.distributed:  # each process streams its shard of the trajectories in memory
        buffer = as_replay_buffer(as_trajectory_batch(trajectories))
    if buffer is not None:
        stream, data = trajectory_stream(buffer, settings)  # checked as it is read
        if infer_num_actions:
            num_actions = stream.num_actions
    else:
        data = as_trajectory_batch(trajectories)
        check_step_data(data, obs_keys=obs_keys, action_key=action_key, action_space=settings.action_space,
                        num_actions=num_actions)  # fmt: skip
    if options is not None:
        check_options_module(options, data, settings.num_options, num_actions=num_actions,
                             action_space=settings.action_space)  # fmt: skip
    if meta_control is not None:
        check_meta_control_module(meta_control, data, settings.num_options)
    device = settings.device
    if device is None:
        device = data.device if data.device is not None else torch.device("cpu")
    data = data.to(torch.device(device))
    if infer_num_actions and settings.action_space == "categorical" and num_actions is None:
        num_actions = int(data.get(action_key)[data.get(MASK_KEY)].max()) + 1
        logger.info("num_actions not given: using max(action) + 1 = %d", num_actions)
    return DiscoveryBatch(data, num_actions=num_actions, buffer=buffer, trajectory_key=settings.trajectory_key,
                          stream=stream)  # fmt: skip
