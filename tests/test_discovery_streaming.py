"""Streamed discovery: demonstrations read from a replay buffer a minibatch (or chunk) of whole trajectories at a
time give what the in-memory path gives where they should agree, read no more than the minibatch, use the
evaluation set's likelihood for the stopping rule, and refuse bad input at the door."""
import pytest
import torch
from torchrl.data import LazyTensorStorage, ListStorage, ReplayBuffer, SliceSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_options import DDOLoss, discover_options
from torchrl_options.data import demonstration_buffer, TrajectoryReader, write_demonstrations
from torchrl_options.discovery import converged_at
from torchrl_options.discovery.settings import DiscoverySettings
from torchrl_options.discovery.stream_fit import fit_stream
from torchrl_options.discovery.streaming import trajectory_stream
from torchrl_options.modules import OptionsMLP
from torchrl_options.testing import planted_corridor_demonstrations

MASK = ("collector", "mask")
QUIET = dict(progress=False, return_info=True)


@pytest.fixture
def data():
    return planted_corridor_demonstrations(12, 40, seed=0)


def _buffer(data, path=None):
    buffer = demonstration_buffer(10_000, path=path)
    write_demonstrations(buffer, data)
    return buffer


def _same_parameters(a, b):
    return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def _max_difference(a, b):
    return max(float((x - y).abs().max()) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def test_full_batch_streaming_is_the_in_memory_run_bit_for_bit(data, tmp_path):
    """The defaults' machinery (segment starts, restarts chosen by likelihood, 5 G-steps, stopping rule, best
    iteration): when the minibatch is the whole data set (one chunk holds every trajectory), the streamed run is
    the in-memory run, bit for bit (torch.equal on every parameter, == on every record)."""
    kw = dict(num_iterations=60, restarts=2, restart_iterations=15, seed=0, **QUIET)
    memory = discover_options(data, 2, **kw)
    streamed = discover_options(_buffer(data, tmp_path / "demos"), 2, **kw)
    assert len(memory.restart_log_likelihoods) == 2
    assert streamed.restart_log_likelihoods == memory.restart_log_likelihoods
    assert [h["log_likelihood_per_step"] for h in streamed.history] == [h["log_likelihood_per_step"] for h in memory.history]
    assert _same_parameters(streamed.options, memory.options)


def test_a_minibatch_of_the_whole_data_set_is_the_full_batch(data):
    """batch_size = every trajectory: each iteration's minibatch is the data set, so the streamed minibatch run
    takes the in-memory full-batch steps bit for bit, and its evaluation set (all 12 trajectories) gives the
    full batch's likelihood (== on every record)."""
    kw = dict(num_iterations=20, restarts=1, init="random", seed=3, tol=None, **QUIET)
    memory = discover_options(data, 2, **kw)
    streamed = discover_options(_buffer(data), 2, batch_size=12, eval_trajectories=12, **kw)
    assert _same_parameters(streamed.options, memory.options)
    for a, b in zip(streamed.history, memory.history):
        assert a["minibatch_log_likelihood_per_step"] == b["log_likelihood_per_step"]
        assert a["log_likelihood_per_step"] == b["log_likelihood_per_step"]


def test_padded_trajectories_of_different_lengths_stream_as_in_memory(data):
    data = data.clone()
    lengths = torch.tensor([40, 13, 27, 40, 5, 33, 40, 40, 21, 9, 40, 17])
    data[MASK] = torch.arange(40)[None] < lengths[:, None]
    kw = dict(num_iterations=30, restarts=1, init="random", seed=1, **QUIET)
    memory = discover_options(data, 2, **kw)
    for buffer in (ReplayBuffer(storage=TensorStorage(data)), _buffer(data)):  # [T] items, and flat steps
        streamed = discover_options(buffer, 2, **kw)
        assert TrajectoryReader(buffer).lengths.tolist() == lengths.tolist()
        assert _same_parameters(streamed.options, memory.options)


def test_a_slice_sampler_buffer_is_read_as_whole_trajectories(data):
    """The buffer's sampler would cut the trajectories into windows of 10 steps; streamed discovery reads its
    storage's whole trajectories instead."""
    flat = data.exclude(MASK).reshape(-1)
    flat["collector", "traj_ids"] = torch.arange(12).repeat_interleave(40)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=SliceSampler(slice_len=10), batch_size=40)
    rb.extend(flat)
    kw = dict(num_iterations=20, restarts=1, init="random", seed=0, **QUIET)
    assert _same_parameters(discover_options(rb, 2, **kw).options, discover_options(data, 2, **kw).options)


def test_chunked_full_batch_equals_the_in_memory_full_batch_to_float_rounding(data):
    kw = dict(num_iterations=30, m_steps=1, restarts=1, init="random", seed=0, tol=None, **QUIET)
    memory = discover_options(data, 3, **kw)
    chunked = discover_options(_buffer(data), 3, chunk_trajectories=5, **kw)
    assert not _same_parameters(chunked.options, memory.options)  # summed over chunks: another rounding
    assert _max_difference(chunked.options, memory.options) < 1e-4
    for a, b in zip(chunked.history, memory.history):
        assert a["log_likelihood_per_step"] == pytest.approx(b["log_likelihood_per_step"], abs=1e-5)
        assert a["option_duration"] == pytest.approx(b["option_duration"], rel=1e-4)
        assert a["termination_probability"] == pytest.approx(b["termination_probability"], rel=1e-4)


def test_streamed_minibatches_draw_the_in_memory_minibatches(data):
    kw = dict(num_iterations=25, batch_size=4, restarts=1, init="random", seed=0, tol=None, **QUIET)
    memory = discover_options(data, 2, **kw)
    streamed = discover_options(_buffer(data), 2, eval_trajectories=6, **kw)
    assert _same_parameters(streamed.options, memory.options)
    assert [h["minibatch_log_likelihood_per_step"] for h in streamed.history] == [
        h["log_likelihood_per_step"] for h in memory.history
    ]


def test_the_evaluation_set_is_what_the_record_and_the_stopping_rule_read(data):
    settings = DiscoverySettings(2, batch_size=3, eval_trajectories=5, seed=4)
    stream, probe = trajectory_stream(_buffer(data), settings)
    assert probe.batch_size == (5, 40) and stream.probe_rows.tolist() == sorted(stream.probe_rows.tolist())
    torch.manual_seed(0)
    loss = DDOLoss(OptionsMLP(2, 2, 2))
    expected = -float(loss(probe)["loss_ddo"].detach())  # the evaluation set's likelihood at the starting parameters
    records = fit_stream(loss, torch.optim.Adam(loss.parameters(), lr=0.0), stream, torch.Generator(), 2,
                         progress=False, probe=probe)  # fmt: skip
    assert records[0]["log_likelihood_per_step"] == pytest.approx(expected, abs=1e-6)
    assert records[0]["minibatch_log_likelihood_per_step"] != records[0]["log_likelihood_per_step"]

    result = discover_options(_buffer(data), 2, batch_size=3, eval_trajectories=5, num_iterations=400, tol=1e-3,
                              patience=10, restarts=1, init="random", seed=4, **QUIET)  # fmt: skip
    lls = [h["log_likelihood_per_step"] for h in result.history]
    assert result.converged and len(lls) < 400
    assert converged_at(lls, 1e-3, 10) == len(lls) - 1  # stopped where the rule fires on the evaluation set
    # keep_best: the returned modules are those of the best evaluated iteration
    final = -float(DDOLoss(result.options)(probe)["loss_ddo"].detach())
    assert final == pytest.approx(max(lls), abs=1e-5)


def test_an_iteration_reads_no_more_than_its_minibatch_or_chunk_and_whole_trajectories(data, monkeypatch):
    """Memory bounded by the minibatch: each read holds at most the minibatch's (or chunk's) trajectories, and each
    of them whole (its valid steps are all the steps the buffer holds for it: the E-step is never cut)."""
    data = data.clone()
    lengths = torch.tensor([40, 13, 27, 40, 5, 33, 40, 40, 21, 9, 40, 17])
    data[MASK] = torch.arange(40)[None] < lengths[:, None]
    reads = []
    original = TrajectoryReader.read

    def counting(self, rows):
        rows = torch.as_tensor(rows)
        reads.append(int(rows.numel()))
        out = original(self, rows)
        assert torch.equal(out[MASK].sum(1), lengths[rows])  # whole trajectories, in the order asked
        assert out.batch_size[1] == int(lengths[rows].max())  # padded to the longest read, not to the data set's
        return out

    monkeypatch.setattr(TrajectoryReader, "read", counting)
    buffer = _buffer(data)
    discover_options(buffer, 2, batch_size=3, eval_trajectories=4, num_iterations=6, restarts=2,
                     restart_iterations=3, init="random", tol=None, **QUIET)  # fmt: skip
    # the evaluation set is read once; then one minibatch per iteration: 2 starts of 3, the best one 3 more
    assert reads[0] == 4 and max(reads[1:]) == 3 and len(reads) == 1 + 9
    reads.clear()
    discover_options(buffer, 2, chunk_trajectories=5, m_steps=1, eval_trajectories=4, num_iterations=2, restarts=1,
                     init="random", tol=None, **QUIET)  # fmt: skip
    assert reads == [4, 5, 5, 2, 5, 5, 2]  # the door's sample, then 12 trajectories in chunks of 5, twice


def test_the_door_refuses_bad_streams(data):
    buffer = _buffer(data)
    with pytest.raises(ValueError, match="m_steps=5 re-uses each E-step's posterior.*chunk_trajectories=4"):
        discover_options(buffer, 2, chunk_trajectories=4, **QUIET)
    with pytest.raises(ValueError, match="not a replay buffer"):
        discover_options(buffer, 2, split_merge=1, **QUIET)
    with pytest.raises(ValueError, match="num_cells='auto'.*replay buffer"):
        discover_options(buffer, 2, num_cells="auto", **QUIET)
    with pytest.raises(ValueError, match="distributed=True needs an initialised torch.distributed process group"):
        discover_options(buffer, 2, distributed=True, **QUIET)
    with pytest.raises(TypeError, match="eval_trajectories must be an int"):
        discover_options(buffer, 2, eval_trajectories=2.5, **QUIET)
    listed = ReplayBuffer(storage=ListStorage(10))
    listed.extend([data[0], data[1]])
    with pytest.raises(TypeError, match="TensorStorage of tensordicts.*ListStorage"):
        discover_options(listed, 2, **QUIET)
    no_ids = ReplayBuffer(storage=LazyTensorStorage(1000))
    no_ids.extend(data.exclude(MASK).reshape(-1))
    with pytest.raises(ValueError, match="no trajectory ids"):
        discover_options(no_ids, 2, **QUIET)
    with pytest.raises(ValueError, match="no 'pixels' entry"):
        discover_options(buffer, 2, obs_keys="pixels", **QUIET)


def test_bad_steps_outside_the_evaluation_set_are_named(data):
    """The door checks the actions of every step and the evaluation set in full; a trajectory read later is
    checked as it is read, and the error names it."""
    bad = data.clone()
    bad["action"][9, 20] = 2
    with pytest.raises(ValueError, match=r"holds action 2 at 'action', outside \[0, num_actions=2\)"):
        discover_options(_buffer(bad), 2, num_actions=2, batch_size=2, eval_trajectories=2, **QUIET)
    nan = data.clone()
    nan["observation"][11, 3, 0] = float("nan")
    settings = dict(batch_size=4, eval_trajectories=1, num_iterations=30, restarts=1, init="random", seed=0)
    with pytest.raises(ValueError, match=r"trajectory 11 of the replay buffer \(read alone\): 'observation' holds NaN"):
        discover_options(_buffer(nan), 2, **settings, **QUIET)
