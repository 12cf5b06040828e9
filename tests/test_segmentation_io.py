"""Loading demonstrations: TensorDict, .npz and HDF5 formats, and the errors for bad files."""
import importlib.util
import logging

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_options.segmentation import (
    load_trajectories,
    reach_grasp_demonstrations,
    save_trajectories,
    TrajectoryFileError,
)

HAS_H5PY = importlib.util.find_spec("h5py") is not None


@pytest.fixture(scope="module")
def demos():
    return reach_grasp_demonstrations(5, seed=3)


def _same(a, b):
    mask = a["collector", "mask"]
    assert torch.equal(mask, b["collector", "mask"])
    for key in ("observation", ("next", "observation"), "action"):
        assert torch.allclose(a[key][mask], b[key][mask]), key
    assert torch.equal(a["true_switch"], b["true_switch"])
    assert torch.equal(a["next", "terminated"], b["next", "terminated"])


@pytest.mark.parametrize("suffix", [".npz", ".pt", ""] + ([".h5"] if HAS_H5PY else []))
def test_round_trip(tmp_path, demos, suffix):
    path = save_trajectories(demos, tmp_path / f"demos{suffix}")
    back = load_trajectories(path)
    _same(demos, back)
    if suffix in (".npz", ".h5"):
        assert torch.equal(back["true_option"], demos["true_option"])


@pytest.mark.skipif(not HAS_H5PY, reason="h5py is not installed")
def test_hdf5_ragged_dataset_is_rejected(tmp_path):
    import h5py

    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f.create_dataset("actions", data=np.zeros((2, 3)))
        ds = f.create_dataset("observations", (2,), dtype=h5py.vlen_dtype(np.float32))
        ds[0], ds[1] = np.zeros(3, np.float32), np.zeros(4, np.float32)
    with pytest.raises(TrajectoryFileError, match="'observations' is a ragged"):
        load_trajectories(tmp_path / "bad.h5")


def test_hdf5_without_h5py_says_so(tmp_path, monkeypatch):
    path = tmp_path / "x.h5"
    path.write_bytes(b"")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "h5py" else real(name, *a))
    with pytest.raises(ImportError, match="h5py"):
        load_trajectories(path)


def test_npz_with_final_state_and_lengths(tmp_path):
    obs = np.random.rand(2, 7, 3).astype(np.float32)
    np.savez(tmp_path / "d.npz", observations=obs, actions=np.ones((2, 6), dtype=np.int64), lengths=[6, 4],
             labels=np.array([[0, 0, 0, 1, 1, 1], [1, 1, 2, 2, 9, 9]]), terminated=[True, False])
    td = load_trajectories(tmp_path / "d.npz")
    assert td.batch_size == (2, 6)
    assert td["action"].dtype == torch.long
    assert torch.allclose(td["next", "observation"][0], torch.as_tensor(obs[0, 1:]))
    assert td["collector", "mask"].sum(1).tolist() == [6, 4]
    assert td["true_switch"].nonzero().tolist() == [[0, 0], [0, 3], [1, 0], [1, 2]]  # label 9 is padding
    assert td["next", "terminated"].squeeze(-1).nonzero().tolist() == [[0, 5]]


def test_npz_without_next_state_drops_last_step(tmp_path, caplog):
    np.savez(tmp_path / "d.npz", observations=np.random.rand(2, 6, 3), actions=np.random.rand(2, 6, 2))
    with caplog.at_level(logging.WARNING):
        td = load_trajectories(tmp_path / "d.npz")
    assert "dropped" in caplog.text
    assert td["collector", "mask"].sum(1).tolist() == [5, 5]


def test_ragged_per_trajectory_arrays(tmp_path):
    arrays = {}
    for i, T in enumerate((4, 7)):
        arrays[f"observations_{i}"] = np.random.rand(T + 1, 2)
        arrays[f"actions_{i}"] = np.random.rand(T, 3)
        arrays[f"boundaries_{i}"] = np.arange(T) == 2
    np.savez(tmp_path / "d.npz", **arrays)
    td = load_trajectories(tmp_path / "d.npz")
    assert td.batch_size == (2, 7)
    assert td["collector", "mask"].sum(1).tolist() == [4, 7]
    assert td["true_switch"].nonzero().tolist() == [[0, 0], [0, 2], [1, 0], [1, 2]]


@pytest.mark.parametrize(
    "arrays, key, message",
    [
        (dict(actions=np.zeros((2, 3))), "observations", "is missing"),
        (dict(observations=np.zeros((2, 4, 1))), "actions", "is missing"),
        (dict(observations=np.zeros((2, 4)), actions=np.zeros((2, 3))), "observations", "must be"),
        (dict(observations=np.zeros((3, 4, 1)), actions=np.zeros((2, 3))), "observations", "trajectories"),
        (dict(observations=np.zeros((2, 9, 1)), actions=np.zeros((2, 3))), "observations", "steps"),
        (dict(observations=np.zeros((2, 4, 1)), actions=np.zeros((2, 3)), lengths=[3, 5]), "lengths", "outside"),
        (dict(observations=np.zeros((2, 4, 1)), actions=np.zeros((2, 3)), lengths=[3]), "lengths", r"\[N\]"),
        (dict(observations=np.zeros((2, 4, 1)), actions=np.zeros((2, 3)), boundaries=np.zeros((2, 5))),
         "boundaries", "must be"),
        (dict(observations=np.zeros((2, 4, 1)), actions=np.zeros((2, 3)), labels=np.zeros((2, 3))),
         "labels", "integers"),
        (dict(observations=np.zeros((2, 4, 1)), actions=-np.ones((2, 3), dtype=int)), "actions", "negative"),
        (dict(observations_0=np.zeros((4, 1)), actions_0=np.zeros(3), observations_1=np.zeros((3, 1))),
         "actions_1", "missing"),
    ],
)
def test_bad_npz_names_the_key(tmp_path, arrays, key, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(TrajectoryFileError, match=rf"'{key}'.*{message}"):
        load_trajectories(tmp_path / "bad.npz")


def test_nan_names_key_and_step(tmp_path):
    obs = np.zeros((2, 5, 1))
    actions = np.zeros((2, 4, 2))
    actions[1, 2, 0] = np.nan
    np.savez(tmp_path / "bad.npz", observations=obs, actions=actions)
    with pytest.raises(TrajectoryFileError, match="'actions' holds NaN or inf .* trajectory 1, step 2"):
        load_trajectories(tmp_path / "bad.npz")
    # NaN in padding is fine
    np.savez(tmp_path / "ok.npz", observations=obs, actions=actions, lengths=[4, 2])
    assert load_trajectories(tmp_path / "ok.npz")["collector", "mask"].sum().item() == 6


def test_object_array_is_called_ragged(tmp_path):
    ragged = np.empty(2, dtype=object)
    ragged[0], ragged[1] = np.zeros((3, 1)), np.zeros((5, 1))
    np.savez(tmp_path / "bad.npz", observations=ragged, actions=np.zeros((2, 4)))
    with pytest.raises(TrajectoryFileError, match="'observations' is a ragged"):
        load_trajectories(tmp_path / "bad.npz")


def test_tensordict_errors(tmp_path):
    td = TensorDict({"observation": torch.zeros(2, 3, 1), "action": torch.zeros(2, 3, 1)}, [2, 3])
    torch.save(td.to_dict(), tmp_path / "a.pt")  # plain data (a pickled TensorDict is refused: test_safe_loading)
    with pytest.raises(TrajectoryFileError, match=r"\('next', 'observation'\).*missing"):
        load_trajectories(tmp_path / "a.pt")
    td["next", "observation"] = torch.full((2, 3, 1), float("nan"))
    td.save(tmp_path / "dir")
    with pytest.raises(TrajectoryFileError, match=r"\('next', 'observation'\).*NaN"):
        load_trajectories(tmp_path / "dir")
    with pytest.raises(FileNotFoundError):
        load_trajectories(tmp_path / "nope.npz")
    (tmp_path / "x.csv").write_text("")
    with pytest.raises(TrajectoryFileError, match="format"):
        load_trajectories(tmp_path / "x.csv")
