"""No file the package reads runs code when loaded: a crafted file whose unpickling would create a marker file is
refused at every entry point, and the marker does not exist afterwards."""
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import NonTensorData, TensorDict

from torchrl_options import load_hierarchy, load_options, OptionsMLP, save_options
from torchrl_options.checkpoints import CheckpointFileError, convert_file, load_file
from torchrl_options.segmentation.io import load_trajectories, TrajectoryFileError


class _Payload:
    """Unpickling this calls ``open(marker, "w")``: the file appears iff the loader ran code from the file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture
def crafted(tmp_path):
    marker = tmp_path / "MARKER"

    def write(name, wrap=lambda payload: payload):
        path = tmp_path / name
        torch.save(wrap(_Payload(marker)), path)
        return path

    yield marker, write
    assert not marker.exists(), "a crafted file ran code on load"


def _dqn_agent():
    from torchrl_options.experiments.gridworld import make_agent

    cfg = {"env": {"grid": "two-rooms", "task": "goal", "max_steps": 10}, "num_envs": 2,
           "dqn": {"hidden_sizes": [2], "frames_per_batch": 8, "buffer_size": 64}}  # fmt: skip
    return make_agent(cfg, "actions", 0)


def test_options_dqn_load_refuses_pickle(crafted):
    marker, write = crafted
    path = write("dqn.pt", lambda p: {"loss_module": p})
    with pytest.raises(ValueError, match="refusing to load this OptionsDQN checkpoint.*pickle.*convert"):
        _dqn_agent().load(path)


def test_gridworld_resume_checkpoint_refuses_pickle(crafted):
    from torchrl_options.experiments.gridworld import train_episodes

    marker, write = crafted
    path = write("dqn.pt", lambda p: {"frames": 0, "log": p})
    with pytest.raises(ValueError, match="dqn.pt: refusing to load this DQN checkpoint"):
        train_episodes(_dqn_agent(), 4, path)


def test_gridworld_cached_greedy_trajectories_refuse_pickle(tmp_path, crafted):
    from torchrl_options.experiments.gridworld import cell_options, Cell

    marker, write = crafted
    cfg = {
        "out_dir": str(tmp_path / "run"), "env": {"grid": "two-rooms", "task": "goal"}, "num_envs": 2,
        "discovery": {"num_options": 2, "num_iterations": 1}, "dqn": {"hidden_sizes": [2]},
        "settings": {"exploration": {"source": "greedy", "pretrain_episodes": 2, "greedy": {"num": 2, "length": 5}}},
        "conditions": {"H1u": {"mode": "both", "meta_control": "uniform"}}, "checkpoint_every": 2,
    }  # fmt: skip
    folder = tmp_path / "run" / "cells" / "exploration-seed0"
    folder.mkdir(parents=True)
    path = write("greedy.pt")
    path.rename(folder / "greedy_trajectories.pt")
    with pytest.raises(ValueError, match="greedy_trajectories.pt: refusing to load this trajectories file"):
        cell_options(cfg, Cell("exploration", "H1u", 0))


def test_atari_cell_checkpoint_refuses_pickle(crafted):
    from torchrl_options.experiments.atari.utils import _load_if

    marker, write = crafted
    path = write("H1.partial.pt", lambda p: {"frames": p})
    with pytest.raises(ValueError, match="refusing to load this Atari DQN checkpoint"):
        _load_if(types.SimpleNamespace(device=torch.device("cpu"), load_state_dict=print), str(path))


def test_load_trajectories_pt_refuses_pickle(crafted):
    marker, write = crafted
    path = write("demos.pt", lambda p: {"observation": p})
    with pytest.raises(TrajectoryFileError, match="demos.pt: refusing to load this trajectories file"):
        load_trajectories(path)


def test_load_trajectories_tensordict_dir_refuses_pickle(tmp_path):
    marker = tmp_path / "MARKER"
    td = TensorDict({"observation": torch.zeros(2, 3, 1), "note": NonTensorData(_Payload(marker), batch_size=[2, 3])},
                    [2, 3])  # fmt: skip
    td.memmap(tmp_path / "demos")
    assert list((tmp_path / "demos").rglob("*.pickle")), "the test needs a pickled entry"
    with pytest.raises(TrajectoryFileError, match="pickled .*not read"):
        load_trajectories(tmp_path / "demos")
    assert not marker.exists()


def test_load_trajectories_npz_refuses_pickle(tmp_path):
    marker = tmp_path / "MARKER"
    obs = np.empty(2, dtype=object)
    obs[0], obs[1] = _Payload(marker), _Payload(marker)
    np.savez(tmp_path / "demos.npz", observations=obs, actions=np.zeros((2, 3)))
    with pytest.raises(TrajectoryFileError, match="'observations'"):
        load_trajectories(tmp_path / "demos.npz")
    assert not marker.exists()


def test_load_options_and_hierarchy_refuse_pickle(crafted):
    marker, write = crafted
    path = write("options.pt", lambda p: {"format": "torchrl_options/options-v1", "options": p})
    with pytest.raises(ValueError, match="options.pt: refusing to load this options"):
        load_options(path)
    with pytest.raises(ValueError, match="options.pt: refusing to load this hierarchy"):
        load_hierarchy(path)


def test_old_format_trajectories_are_converted_on_explicit_trust(tmp_path):
    td = TensorDict({"observation": torch.arange(6.0).reshape(2, 3, 1)}, [2, 3])
    path = tmp_path / "greedy_trajectories.pt"
    torch.save(td, path)  # the format of older versions: a pickled TensorDict
    with pytest.raises(CheckpointFileError, match="python -m torchrl_options.checkpoints convert .*--trust-file"):
        load_file(path, what="trajectories file")
    with pytest.raises(ValueError, match="trust_file=True"):
        convert_file(path)
    convert_file(path, trust_file=True)
    from torchrl_options.checkpoints import tensordict_from_plain

    back = tensordict_from_plain(load_file(path))
    assert back.batch_size == td.batch_size and torch.equal(back["observation"], td["observation"])


def test_saved_files_load_with_weights_only(tmp_path):
    """What the package writes is plain data: it loads without any safe globals."""
    agent = _dqn_agent()
    agent.train(total_frames=16)
    agent.save(tmp_path / "dqn.pt", include_buffer=True)
    torch.load(tmp_path / "dqn.pt", weights_only=True)
    save_options(OptionsMLP(2, 4, 2), tmp_path / "options.pt")
    torch.load(tmp_path / "options.pt", weights_only=True)
    other = _dqn_agent()
    other.load(tmp_path / "dqn.pt")
    assert other.frames == agent.frames == 16 and len(other.replay_buffer) == len(agent.replay_buffer)
