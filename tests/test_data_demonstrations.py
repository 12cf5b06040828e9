"""Demonstrations in a replay buffer: written whole (from tensordicts, lists, flat collector output, files), opened
again from disk, read back as whole trajectories by TrajectoryReader, and bad storages refused at the door."""
import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, ListStorage, ReplayBuffer, TensorStorage

from torchrl_options.data import (
    demonstration_buffer,
    MANIFEST,
    open_demonstrations,
    TrajectoryReader,
    write_demonstration_files,
    write_demonstrations,
)
from torchrl_options.segmentation import save_trajectories
from torchrl_options.testing import planted_corridor_demonstrations, write_planted_corridor

MASK = ("collector", "mask")
IDS = ("collector", "traj_ids")


def _ragged(seed=0):
    """Five corridor trajectories of lengths 7, 3, 10, 1, 5 as a padded [5, 10] batch."""
    data = planted_corridor_demonstrations(5, 10, seed=seed)
    lengths = torch.tensor([7, 3, 10, 1, 5])
    data[MASK] = torch.arange(10)[None] < lengths[:, None]
    return data, lengths


def test_a_padded_batch_round_trips_through_a_memmap_buffer(tmp_path):
    data, lengths = _ragged()
    buffer = demonstration_buffer(100, path=tmp_path / "demos")
    assert write_demonstrations(buffer, data) == int(lengths.sum())
    assert isinstance(buffer.storage, LazyMemmapStorage)
    reader = TrajectoryReader(open_demonstrations(tmp_path / "demos"))
    assert reader.layout == "steps" and reader.lengths.tolist() == lengths.tolist()
    back = reader.read(torch.arange(5))
    assert back.batch_size == (5, 10)
    assert torch.equal(back[MASK], data[MASK])
    for key in ("observation", "action", ("next", "observation")):
        assert torch.equal(back[key][back[MASK]], data[key][data[MASK]])
        assert (back[key][~back[MASK]] == 0).all()  # zero padding
    manifest = json.loads((tmp_path / "demos" / MANIFEST).read_text())
    assert manifest == {"steps": int(lengths.sum()), "trajectories": 5, "trajectory_key": ["collector", "traj_ids"]}


def test_reads_come_in_the_order_asked_and_are_as_long_as_their_longest():
    data, lengths = _ragged()
    buffer = demonstration_buffer(100)
    write_demonstrations(buffer, data)
    reader = TrajectoryReader(buffer)
    batch = reader.read(torch.tensor([3, 1, 0]))
    assert batch.batch_size == (3, 7)
    assert batch[MASK].sum(1).tolist() == [1, 3, 7]
    assert torch.equal(batch["observation"][0, :1], data["observation"][3, :1])
    assert torch.equal(batch["action"][2], data["action"][0, :7])
    with pytest.raises(ValueError, match=r"rows must be in \[0, 5\)"):
        reader.read(torch.tensor([5]))


def test_writes_append_with_new_ids_and_accept_lists_single_trajectories_and_flat_steps():
    buffer = demonstration_buffer(1000)
    data = planted_corridor_demonstrations(3, 8, seed=0)
    write_demonstrations(buffer, data)
    write_demonstrations(buffer, [data[0, :4], data[1, :6]])  # a list of [T_i]
    write_demonstrations(buffer, data[2])  # one [T]
    flat = data[:2].reshape(-1).exclude(MASK)  # a collector's traj_format="cat": ids, no mask
    flat[IDS] = torch.tensor([7] * 8 + [9] * 8)
    write_demonstrations(buffer, flat)
    reader = TrajectoryReader(buffer)
    assert reader.lengths.tolist() == [8, 8, 8, 4, 6, 8, 8, 8]
    assert buffer[:][IDS].unique().tolist() == list(range(8))
    assert torch.equal(reader.read(torch.tensor([7]))["action"][0], data["action"][1])


def test_a_trajectory_done_in_the_middle_is_two_trajectories():
    data = planted_corridor_demonstrations(1, 10, seed=0)
    data["next", "done"] = torch.zeros(1, 10, 1, dtype=torch.bool)
    data["next", "done"][0, 3] = True
    buffer = demonstration_buffer(100)
    write_demonstrations(buffer, data)
    assert TrajectoryReader(buffer).lengths.tolist() == [4, 6]


def test_write_demonstration_files_reads_one_file_at_a_time(tmp_path):
    files = [save_trajectories(planted_corridor_demonstrations(2, 15, seed=s), tmp_path / f"{s}.npz") for s in range(3)]
    buffer = demonstration_buffer(1000)
    assert write_demonstration_files(buffer, files) == 90
    reader = TrajectoryReader(buffer)
    assert reader.num_trajectories == 6 and reader.num_steps == 90


def test_write_planted_corridor_writes_in_chunks_and_matches_the_generator():
    buffer = demonstration_buffer(10_000)
    assert write_planted_corridor(buffer, 5, 20, chunk_trajectories=2, seed=3) == 100
    reader = TrajectoryReader(buffer)
    assert reader.num_trajectories == 5
    second_chunk = planted_corridor_demonstrations(2, 20, seed=4)
    assert torch.equal(reader.read(torch.tensor([2, 3]))["observation"], second_chunk["observation"])


def test_the_writer_refuses_what_would_overwrite_or_mix_entries(tmp_path):
    buffer = demonstration_buffer(50)
    write_demonstrations(buffer, planted_corridor_demonstrations(2, 20))
    with pytest.raises(ValueError, match="do not fit: the buffer holds 40 of 50.*overwrite"):
        write_demonstrations(buffer, planted_corridor_demonstrations(1, 20))
    other = planted_corridor_demonstrations(1, 5).exclude("true_option")
    with pytest.raises(ValueError, match="missing.*true_option"):
        write_demonstrations(buffer, other)
    wrong_dtype = planted_corridor_demonstrations(1, 5)
    wrong_dtype["action"] = wrong_dtype["action"].float()
    with pytest.raises(ValueError, match="entry 'action'.*torch.int64.*torch.float32"):
        write_demonstrations(buffer, wrong_dtype)
    gap = planted_corridor_demonstrations(1, 5)
    gap[MASK] = torch.tensor([[True, False, True, True, True]])
    with pytest.raises(ValueError, match="not its valid steps followed by padding"):
        write_demonstrations(demonstration_buffer(50), gap)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ValueError, match="already holds files.*open_demonstrations"):
        demonstration_buffer(10, path=tmp_path / "full")
    with pytest.raises(FileNotFoundError, match="demonstrations.json"):
        open_demonstrations(tmp_path / "full")
    with pytest.raises(TypeError, match="ReplayBuffer"):
        write_demonstrations(planted_corridor_demonstrations(1, 5), planted_corridor_demonstrations(1, 5))


def test_the_reader_refuses_wrong_storages_and_missing_entries():
    with pytest.raises(TypeError, match="TorchRL ReplayBuffer"):
        TrajectoryReader(planted_corridor_demonstrations(2, 5))
    listed = ReplayBuffer(storage=ListStorage(10))
    listed.extend([1, 2, 3])
    with pytest.raises(TypeError, match="TensorStorage of tensordicts.*got ListStorage"):
        TrajectoryReader(listed)
    with pytest.raises(ValueError, match="empty"):
        TrajectoryReader(ReplayBuffer(storage=LazyTensorStorage(10)))
    two_dims = ReplayBuffer(storage=LazyTensorStorage(100, ndim=2))
    two_dims.extend(planted_corridor_demonstrations(2, 5))
    with pytest.raises(ValueError, match="ndim=2"):
        TrajectoryReader(two_dims)
    no_ids = ReplayBuffer(storage=LazyTensorStorage(100))
    no_ids.extend(planted_corridor_demonstrations(2, 5).reshape(-1))
    with pytest.raises(ValueError, match=r"no trajectory ids at \('collector', 'traj_ids'\)"):
        TrajectoryReader(no_ids)
    no_mask = ReplayBuffer(storage=LazyTensorStorage(10))
    no_mask.extend(planted_corridor_demonstrations(2, 5).exclude(MASK))
    with pytest.raises(ValueError, match=r"without their \('collector', 'mask'\)"):
        TrajectoryReader(no_mask)


def test_the_reader_refuses_trajectories_stored_in_pieces():
    """Two envs written flat without trajs_per_batch: the ids interleave, no done between the pieces."""
    steps = planted_corridor_demonstrations(1, 12).reshape(-1).exclude(MASK)
    steps[IDS] = torch.tensor([0, 0, 0, 1, 1, 1, 0, 0, 0, 1, 1, 1])
    buffer = ReplayBuffer(storage=LazyTensorStorage(100))
    buffer.extend(steps)
    with pytest.raises(ValueError, match="trajectory 0 .* stored in pieces: its steps start at item 0 and again at item 6"):
        TrajectoryReader(buffer)
    # the same ids, each piece closed by a done: separate trajectories (a collector re-using an id), accepted
    steps["next", "done"] = torch.zeros(12, 1, dtype=torch.bool)
    steps["next", "done"][[2, 5, 8, 11]] = True
    closed = ReplayBuffer(storage=LazyTensorStorage(100))
    closed.extend(steps)
    assert TrajectoryReader(closed).lengths.tolist() == [3, 3, 3, 3]


def test_the_reader_refuses_a_ring_buffer_that_overwrote_its_oldest_steps():
    buffer = ReplayBuffer(storage=LazyTensorStorage(10))
    steps = planted_corridor_demonstrations(3, 5).reshape(-1).exclude(MASK)
    steps[IDS] = torch.arange(3).repeat_interleave(5)
    buffer.extend(steps)
    with pytest.raises(ValueError, match="written 15 steps into a storage of 10.*overwritten"):
        TrajectoryReader(buffer)


def test_a_storage_of_padded_trajectories_is_read_too():
    data, lengths = _ragged()
    buffer = ReplayBuffer(storage=TensorStorage(data))
    reader = TrajectoryReader(buffer)
    assert reader.layout == "trajectories" and reader.lengths.tolist() == lengths.tolist()
    batch = reader.read(torch.tensor([1, 4]))
    assert batch.batch_size == (2, 5) and torch.equal(batch["action"], data["action"][[1, 4], :5])
    bad = data.clone()
    bad[MASK][1] = torch.tensor([False] * 9 + [True])
    with pytest.raises(ValueError, match="trajectory item 1 .* not its valid steps followed by padding"):
        TrajectoryReader(ReplayBuffer(storage=TensorStorage(bad)))


def test_the_index_is_made_in_chunks():
    """A scan_size smaller than a trajectory and than the buffer finds the same trajectories."""
    buffer = demonstration_buffer(1000)
    data, lengths = _ragged()
    write_demonstrations(buffer, data)
    write_demonstrations(buffer, data)
    for scan_size in (1, 2, 3, 7, 1000):
        reader = TrajectoryReader(buffer, scan_size=scan_size)
        assert reader.lengths.tolist() == lengths.tolist() * 2, scan_size
        assert int(reader.scan("action")) == int(data["action"][data[MASK]].max())
    steps = TensorDict({"x": torch.arange(6.0), IDS: torch.tensor([0, 0, 1, 0, 0, 1])}, [6])
    interleaved = ReplayBuffer(storage=LazyTensorStorage(10))
    interleaved.extend(steps)
    with pytest.raises(ValueError, match="stored in pieces"):
        TrajectoryReader(interleaved, scan_size=2)
