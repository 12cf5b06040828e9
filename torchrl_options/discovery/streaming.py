"""Streamed demonstrations for discovery: the trajectories of a TorchRL replay buffer read a minibatch at a time
(:class:`TrajectoryStream`), so that memory is bounded by the minibatch, not the data set.

Each iteration of streamed DDO reads whole trajectories (:class:`~torchrl_options.data.TrajectoryReader`: never a
window of one), so each trajectory's E-step is exact. What an iteration reads:

* ``batch_size=None`` (full batch): every trajectory of the process's shard, in chunks of ``chunk_trajectories``
  trajectories (all at once without it): the chunks' gradients of ``-Q`` are summed before the step, so an
  iteration is the full-batch iteration of the in-memory path, with the memory of one chunk. Several G-steps per
  E-step (``m_steps > 1``) re-use the E-step's posterior, which a chunk gone from memory no longer has: they need
  the shard in one chunk.
* ``batch_size=b``: ``b`` trajectories drawn without replacement each iteration (as the in-memory path draws
  them); with several processes each draws its share from its own shard.

**The likelihood the stopping rule and the choice among starts read.** With the full batch, each iteration's
record is the exact log-likelihood per step of all the trajectories (summed over chunks and processes), as in
memory. With minibatches, a minibatch's likelihood is noisy and changes with the draw, so streamed discovery fixes an
*evaluation set* at the door: ``eval_trajectories`` trajectories (all when there are no more; else drawn once,
without replacement, from a generator of ``seed``, the same on every process), and evaluates the log-likelihood
per step of that set at every iteration, at the parameters before the iteration's steps (one E-step without
G-steps; with several processes each evaluates its share and the sums are all-reduced). That value is the record's
``log_likelihood_per_step`` (the minibatch's own is ``minibatch_log_likelihood_per_step``), which the stopping rule,
the choice among starts and ``keep_best`` read, and it is comparable across iterations and starts. The
evaluation set is also the door's sample: the data checks, the default modules' sizes and the segment starts
(``init="auto"``) are taken from it.
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer, TensorStorage

from torchrl_options.data import TrajectoryReader
from torchrl_options.discovery.distributed import DataParallel, SingleProcess
from torchrl_options.discovery.settings import DiscoverySettings
from torchrl_options.discovery.validation import check_step_data

__all__ = ["TrajectoryStream", "as_replay_buffer", "trajectory_stream"]

logger = logging.getLogger(__name__)


@dataclass
class TrajectoryStream:
    """This process's trajectories of a replay buffer, and how each iteration of streamed discovery reads them.

    Attributes:
        reader (TrajectoryReader): the buffer's whole trajectories.
        rows (Tensor): this process's shard (every trajectory with one process).
        probe_rows (Tensor): the evaluation set (the door's sample), the same on every process.
        eval_rows (Tensor): this process's share of the evaluation set (evaluated with minibatches).
        batch_size (int or None): this process's trajectories per iteration; ``None``: its whole shard.
        chunk (int or None): trajectories per E-step; ``None``: the iteration's trajectories at once.
        group (SingleProcess or DataParallel): the processes the gradients are summed over.
        settings (DiscoverySettings): the run's settings (the keys and action space every read is checked for).
        num_actions (int or None): A for discrete actions.
        device (torch.device): the training device.
        generator (torch.Generator or None): this process's minibatch draws with several processes (``None``: the
            run's generator, as in memory).
    """

    reader: TrajectoryReader
    rows: torch.Tensor
    probe_rows: torch.Tensor
    eval_rows: torch.Tensor
    batch_size: int | None
    chunk: int | None
    group: SingleProcess
    settings: DiscoverySettings
    num_actions: int | None
    device: torch.device
    generator: torch.Generator | None = None
    tables: dict = field(default_factory=dict)

    @property
    def full_batch(self) -> bool:
        """Whether every iteration reads the whole shard (then its record is the exact likelihood)."""
        return self.batch_size is None

    @property
    def fixed(self) -> bool:
        """Whether the iteration's trajectories stay in memory from one iteration to the next (the whole shard, one
        chunk): then they are read and tabulated once."""
        return self.full_batch and (self.chunk is None or self.chunk >= self.rows.numel())

    def read(self, rows: torch.Tensor) -> TensorDictBase:
        """Trajectories ``rows`` of the buffer as a checked ``[B, T]`` batch on the device."""
        data = self.reader.read(rows)
        try:
            self._check(data)
        except ValueError as err:
            if rows.numel() == 1:
                raise
            for row in rows.tolist():  # name the buffer's trajectory (a rare path: the data is bad)
                try:
                    self._check(self.reader.read(torch.tensor([row])))
                except ValueError as inner:
                    raise ValueError(f"trajectory {row} of the replay buffer (read alone): {inner}") from None
            raise err
        return data.to(self.device)

    def _check(self, data: TensorDictBase) -> None:
        s = self.settings
        check_step_data(data, obs_keys=s.obs_key_list, action_key=s.action_key, action_space=s.action_space,
                        num_actions=self.num_actions)  # fmt: skip

    def iteration_rows(self, generator: torch.Generator) -> torch.Tensor:
        """This process's trajectories of the next iteration: the shard, or ``batch_size`` of it drawn without
        replacement (from :attr:`generator` with several processes, else from ``generator``, as the in-memory
        path draws)."""
        if self.batch_size is None or self.batch_size >= self.rows.numel():
            return self.rows
        g = self.generator if self.generator is not None else generator
        return self.rows[torch.randperm(self.rows.numel(), generator=g)[: self.batch_size]]

    def chunks(self, rows: torch.Tensor) -> list[torch.Tensor]:
        """``rows`` cut into E-step chunks."""
        return [rows] if self.chunk is None else list(rows.split(self.chunk))


def as_replay_buffer(trajectories: TensorDictBase) -> ReplayBuffer:
    """A ``[B, T]`` trajectory batch (with its mask) as a replay buffer of ``[T]`` trajectory items, read in place.

    Examples:
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> buffer = as_replay_buffer(planted_corridor_demonstrations(3, 10))
        >>> len(buffer), TrajectoryReader(buffer).layout
        (3, 'trajectories')
    """
    return ReplayBuffer(storage=TensorStorage(trajectories))


def _probe(num: int, size: int, seed: int | None) -> torch.Tensor:
    """``size`` of ``num`` trajectories, drawn once from a generator of ``seed`` (all of them, in order, when
    ``size >= num``), sorted (reads in storage order)."""
    if size >= num:
        return torch.arange(num)
    g = torch.Generator().manual_seed(0 if seed is None else seed)
    return torch.randperm(num, generator=g)[:size].sort().values


# what every process of a data-parallel run must share: the data set's size and the settings that decide the
# collectives' number and order (a difference would hang a collective or silently train different modules)
_SHARED = ("num_options", "num_iterations", "m_steps", "tol", "patience", "restarts", "restart_iterations",
           "batch_size", "chunk_trajectories", "eval_trajectories", "lr", "seed", "init", "split_merge")  # fmt: skip


def _code(value) -> float:
    """A number standing for a setting's value, equal where the values are (``None``: -1.5, which no setting
    takes; strings: 48 bits of their hash)."""
    if value is None:
        return -1.5
    if isinstance(value, (bool, int, float)):
        return float(value)
    return float(int.from_bytes(hashlib.sha256(repr(value).encode()).digest()[:6], "big"))


def check_same_run(group: SingleProcess, reader: TrajectoryReader, settings: DiscoverySettings,
                   device: torch.device) -> None:  # fmt: skip
    """Refuses, on every process alike (so that none is left waiting in a collective), a data-parallel run whose
    processes do not see the same replay buffer (trajectories, steps) or were given different settings (those in
    :data:`_SHARED`, which decide the number and order of the collectives and the steps taken).

    Raises:
        ValueError: naming what differs, with this process's value and the range over the processes.

    Examples:
        >>> from torchrl_options.data import demonstration_buffer, write_demonstrations
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> buffer = demonstration_buffer(100)
        >>> _ = write_demonstrations(buffer, planted_corridor_demonstrations(2, 10))
        >>> check_same_run(SingleProcess(), TrajectoryReader(buffer), DiscoverySettings(2), torch.device("cpu"))
    """
    mine = {"trajectories in the buffer": reader.num_trajectories, "steps in the buffer": reader.num_steps}
    mine.update({name: getattr(settings, name) for name in _SHARED})
    codes = torch.tensor([_code(v) for v in mine.values()], dtype=torch.float64, device=device)
    high = group.max_(codes.clone())
    low = -group.max_(-codes)
    differ = []
    for i, (name, value) in enumerate(mine.items()):
        if low[i] != high[i]:
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            spread = f", from {low[i].item():g} to {high[i].item():g} over the processes" if numeric else ""
            differ.append(f"{name} (here {value!r}{spread})")
    if differ:
        raise ValueError(
            f"distributed=True: the {group.world_size} processes must stream the same replay buffer with the same "
            f"settings, but process {group.rank} sees them differ in {'; '.join(differ)}."
        )


def trajectory_stream(buffer: ReplayBuffer, settings: DiscoverySettings) -> tuple[TrajectoryStream, TensorDictBase]:
    """The door of streamed discovery: indexes the buffer's trajectories (:class:`~torchrl_options.data.
    TrajectoryReader`, refusing a wrong storage, missing ids and trajectories stored in pieces), joins the process
    group with ``settings.distributed``, takes this process's shard, infers or checks ``num_actions`` over every
    valid step, checks the settings against the data's size and reads the evaluation set.

    Returns:
        ``(stream, probe)``: the stream, and the evaluation set as a checked ``[B, T]`` batch on the device.

    Raises:
        ValueError: besides the reader's refusals, for actions out of ``[0, num_actions)``, ``m_steps > 1`` with
            E-step chunks smaller than an iteration's trajectories, and fewer trajectories than processes.

    Examples:
        >>> from torchrl_options.data import demonstration_buffer, write_demonstrations
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> buffer = demonstration_buffer(10_000)
        >>> _ = write_demonstrations(buffer, planted_corridor_demonstrations(10, 100))
        >>> stream, probe = trajectory_stream(buffer, DiscoverySettings(2, batch_size=4, eval_trajectories=3))
        >>> stream.rows.numel(), probe.batch_size, stream.num_actions
        (10, torch.Size([3, 100]), 2)
    """
    reader = TrajectoryReader(buffer, trajectory_key=settings.trajectory_key)
    group = DataParallel() if settings.distributed else SingleProcess()
    device = settings.device
    device = torch.device("cpu") if device is None else torch.device(device)
    if group.world_size > 1:
        check_same_run(group, reader, settings, device)
    rows = reader.shard(group.rank, group.world_size)
    num_actions = settings.num_actions
    if settings.action_space == "categorical":
        top = reader.scan(settings.action_key)
        top = int(top.max())
        if num_actions is None:
            num_actions = top + 1
            logger.info("num_actions not given: using max(action) + 1 = %d over the %d streamed steps", num_actions,
                        reader.num_steps)  # fmt: skip
        elif top >= num_actions:
            raise ValueError(f"the replay buffer holds action {top} at {settings.action_key!r}, outside [0, "
                             f"num_actions={num_actions}).")  # fmt: skip
    batch_size = settings.batch_size
    if batch_size is not None:
        # this process's share of the global minibatch
        batch_size = batch_size // group.world_size + (1 if group.rank < batch_size % group.world_size else 0)
        batch_size = max(batch_size, 1)
    per_iteration = rows.numel() if batch_size is None else min(batch_size, rows.numel())
    chunk = settings.chunk_trajectories
    if chunk is not None and chunk >= per_iteration:
        chunk = None
    if chunk is not None and settings.m_steps > 1:
        raise ValueError(
            f"m_steps={settings.m_steps} re-uses each E-step's posterior for several G-steps, but chunk_trajectories="
            f"{settings.chunk_trajectories} cuts an iteration's {per_iteration} trajectories into E-step chunks that do "
            "not stay in memory: use m_steps=1 (Expectation-Gradient) with chunks, or give batch_size (minibatches) "
            "no larger than chunk_trajectories."
        )
    generator = None
    if group.world_size > 1:
        seed = 0 if settings.seed is None else settings.seed
        generator = torch.Generator().manual_seed(seed * 1_000_003 + group.rank + 1)
    probe_rows = _probe(reader.num_trajectories, settings.eval_trajectories, settings.seed)
    if settings.batch_size is None and chunk is None and group.world_size == 1:
        probe_rows = rows  # the whole data set is the batch anyway: the door's sample is all of it
    stream = TrajectoryStream(
        reader=reader, rows=rows, probe_rows=probe_rows, eval_rows=probe_rows[group.rank :: group.world_size],
        batch_size=batch_size, chunk=chunk, group=group, settings=settings, num_actions=num_actions, device=device,
        generator=generator,
    )  # fmt: skip
    return stream, stream.read(probe_rows)
