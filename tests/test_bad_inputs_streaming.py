"""Bad inputs of streamed discovery (issue 52): the demonstration buffer and its writers and reader, the streamed and
data-parallel settings of ``discover_options``. One row per case (tests/_bad_inputs.py), controls included. The
refusals that need two processes (processes with another buffer or other settings) are in
tests/test_discovery_distributed.py."""
import pytest
import torch
from torchrl.data import LazyTensorStorage, ListStorage, ReplayBuffer, TensorStorage

from _bad_inputs import check, ids, OK
from torchrl_options import discover_options
from torchrl_options.data import (
    demonstration_buffer,
    open_demonstrations,
    TrajectoryReader,
    write_demonstration_files,
    write_demonstrations,
)
from torchrl_options.testing import planted_corridor_demonstrations, write_planted_corridor

MASK = ("collector", "mask")
QUIET = dict(progress=False, num_iterations=2, restarts=1, init="random")


def demos(n: int = 4, T: int = 10):
    return planted_corridor_demonstrations(n, T, seed=0)


def buffer(n: int = 4, T: int = 10, path=None):
    rb = demonstration_buffer(1000, path=path)
    write_demonstrations(rb, demos(n, T))
    return rb


def listed():
    rb = ReplayBuffer(storage=ListStorage(10))
    rb.extend([demos()[0], demos()[1]])
    return rb


def without_ids():
    rb = ReplayBuffer(storage=LazyTensorStorage(100))
    rb.extend(demos().exclude(MASK).reshape(-1))
    return rb


def without(key):
    rb = demonstration_buffer(1000)
    write_demonstrations(rb, demos().exclude(key))
    return rb


CASES = [
    # ---- demonstration_buffer
    ("demonstration_buffer", "control", lambda: demonstration_buffer(10), OK, None),
    ("demonstration_buffer", "capacity 0", lambda: demonstration_buffer(0), ValueError, "capacity must be an int >= 1, got 0"),
    ("demonstration_buffer", "capacity a float", lambda: demonstration_buffer(10.0), TypeError,
     "capacity must be an int"),
    ("demonstration_buffer", "batch_size 0", lambda: demonstration_buffer(10, batch_size=0), ValueError, "batch_size"),
    # ---- write_demonstrations
    ("write_demonstrations", "control", lambda: write_demonstrations(demonstration_buffer(100), demos()), OK, None),
    ("write_demonstrations", "buffer a tensordict", lambda: write_demonstrations(demos(), demos()), TypeError,
     "buffer must be a TorchRL ReplayBuffer, got TensorDict"),
    ("write_demonstrations", "a buffer over a ListStorage",
     lambda: write_demonstrations(ReplayBuffer(storage=ListStorage(10)), demos()), TypeError,
     "storage must be a TensorStorage of steps"),
    ("write_demonstrations", "more steps than the capacity", lambda: write_demonstrations(demonstration_buffer(30), demos()),
     ValueError, "do not fit"),
    ("write_demonstrations", "trajectories a tensor", lambda: write_demonstrations(demonstration_buffer(100), torch.zeros(4, 10)),
     TypeError, "trajectories must be a TensorDict"),
    ("write_demonstrations", "trajectory_key an int",
     lambda: write_demonstrations(demonstration_buffer(100), demos(), trajectory_key=3), TypeError, "trajectory_key"),
    # ---- write_demonstration_files
    ("write_demonstration_files", "control (no file)", lambda: write_demonstration_files(demonstration_buffer(10), []),
     OK, None),
    ("write_demonstration_files", "paths one string (would be read character by character)",
     lambda: write_demonstration_files(demonstration_buffer(10), "demos.npz"), TypeError,
     "paths must be an iterable of file paths"),
    ("write_demonstration_files", "buffer a list", lambda: write_demonstration_files([], []), TypeError,
     "buffer must be a TorchRL ReplayBuffer, got list"),
    # ---- TrajectoryReader
    ("TrajectoryReader", "control", lambda: TrajectoryReader(buffer()), OK, None),
    ("TrajectoryReader", "buffer a tensordict", lambda: TrajectoryReader(demos()), TypeError,
     "buffer must be a TorchRL ReplayBuffer, got TensorDict"),
    ("TrajectoryReader", "a ListStorage", lambda: TrajectoryReader(listed()), TypeError,
     "TensorStorage of tensordicts"),
    ("TrajectoryReader", "an empty buffer", lambda: TrajectoryReader(demonstration_buffer(10)), ValueError,
     "the replay buffer is empty"),
    ("TrajectoryReader", "steps without trajectory ids", lambda: TrajectoryReader(without_ids()), ValueError,
     "no trajectory ids"),
    ("TrajectoryReader", "scan_size 0", lambda: TrajectoryReader(buffer(), scan_size=0), ValueError, "scan_size"),
    ("TrajectoryReader.read", "a row outside", lambda: TrajectoryReader(buffer()).read(torch.tensor([4])), ValueError,
     "rows must be in [0, 4)"),
    ("TrajectoryReader.read", "no row", lambda: TrajectoryReader(buffer()).read(torch.tensor([], dtype=torch.long)),
     ValueError, "rows is empty"),
    ("TrajectoryReader.shard", "rank = world_size", lambda: TrajectoryReader(buffer()).shard(2, 2), ValueError,
     "rank must be an int in [0, 1]"),
    ("TrajectoryReader.shard", "world size above the trajectories", lambda: TrajectoryReader(buffer()).shard(0, 5),
     ValueError, "holds 4 trajectories, fewer than the 5 processes"),
    ("TrajectoryReader.shard", "world_size 0", lambda: TrajectoryReader(buffer()).shard(0, 0), ValueError,
     "world_size must be an int"),
    # ---- open_demonstrations
    ("open_demonstrations", "a folder without demonstrations", lambda tmp: open_demonstrations(tmp), FileNotFoundError,
     "demonstrations"),
    # ---- write_planted_corridor
    ("write_planted_corridor", "control", lambda: write_planted_corridor(demonstration_buffer(100), 2, 10), OK, None),
    ("write_planted_corridor", "num_trajectories 0", lambda: write_planted_corridor(demonstration_buffer(100), 0, 10),
     ValueError, "num_trajectories must be an int >= 1, got 0"),
    ("write_planted_corridor", "chunk_trajectories a float",
     lambda: write_planted_corridor(demonstration_buffer(100), 2, 10, chunk_trajectories=1.5), TypeError,
     "chunk_trajectories must be an int"),
    # ---- discover_options on a replay buffer: the streamed settings and the buffer at the door
    ("discover_options", "control: streamed minibatches",
     lambda: discover_options(buffer(), 2, batch_size=2, eval_trajectories=2, **QUIET), OK, None),
    ("discover_options", "a buffer over a ListStorage", lambda: discover_options(listed(), 2, **QUIET), TypeError,
     "TensorStorage of tensordicts"),
    ("discover_options", "a buffer without trajectory ids", lambda: discover_options(without_ids(), 2, **QUIET),
     ValueError, "no trajectory ids"),
    ("discover_options", "a buffer without the action key", lambda: discover_options(without("action"), 2, **QUIET),
     ValueError, "the trajectories have no 'action' entry"),
    ("discover_options", "a buffer without the observation key",
     lambda: discover_options(buffer(), 2, obs_keys="pixels", **QUIET), ValueError, "no 'pixels' entry"),
    ("discover_options", "chunk_trajectories 0", lambda: discover_options(buffer(), 2, chunk_trajectories=0, **QUIET),
     ValueError, "chunk_trajectories must be an int >= 1, got 0"),
    ("discover_options", "eval_trajectories a float",
     lambda: discover_options(buffer(), 2, eval_trajectories=2.5, **QUIET), TypeError,
     "eval_trajectories must be an int"),
    ("discover_options", "distributed a string", lambda: discover_options(buffer(), 2, distributed="yes", **QUIET),
     TypeError, "distributed must be True or False, got 'yes'"),
    ("discover_options", "distributed without a process group",
     lambda: discover_options(buffer(), 2, distributed=True, **QUIET), ValueError,
     "distributed=True needs an initialised torch.distributed process group"),
    ("discover_options", "chunks with m_steps > 1", lambda: discover_options(buffer(), 2, chunk_trajectories=2, **QUIET),
     ValueError, "m_steps=5 re-uses each E-step's posterior"),
    ("discover_options", "control: chunks with m_steps=1",
     lambda: discover_options(buffer(), 2, chunk_trajectories=2, m_steps=1, **QUIET), OK, None),
    ("discover_options", "num_actions below the buffer's actions",
     lambda: discover_options(buffer(), 2, num_actions=1, **QUIET), ValueError, "outside [0, num_actions=1)"),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_streaming_bad_inputs(api, case, call, error, phrase, tmp_path):
    if call.__code__.co_argcount:
        check(call, error, phrase, tmp_path)
    else:
        check(call, error, phrase)
