"""Every file reader names the file and says what it expected (issue 53): empty, truncated, corrupt and
wrong-format files of every format the package reads (.npz, .h5, .pt, TensorDict directories, checkpoints, the JSON
and CSV files of a run). A truncated TensorDict directory is refused rather than read as zeros. One row per case;
``call(tmp_path)``; controls (good files) included."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from _bad_inputs import check, ids, OK
from torchrl_options import load_hierarchy, load_options, OptionHierarchy, OptionsMLP, save_hierarchy, save_options
from torchrl_options.checkpoints import load_file, save_file, tensordict_from_plain
from torchrl_options.experiments import ResultsLog
from torchrl_options.experiments.atari import demonstration_fit_markdown, option_usage_markdown
from torchrl_options.experiments.run_settings import read_run_settings
from torchrl_options.segmentation import load_trajectories, save_trajectories, TrajectoryFileError
from torchrl_options.testing import planted_corridor_demonstrations

DEMOS = planted_corridor_demonstrations(2, 5, seed=0)


def load_json_file(path, **kw):
    from torchrl_options.checkpoints import load_json_file  # new in issue 53 (imported here: the table runs on older code)

    return load_json_file(path, **kw)


def write(name, content):
    def make(tmp_path):
        path = tmp_path / name
        path.write_bytes(content() if callable(content) else content)
        return path

    return make


def saved(name, saver=None):
    def make(tmp_path):
        path = tmp_path / name
        (saver or (lambda p: save_trajectories(DEMOS, p)))(path)
        return path

    return make


def truncated(make, keep=0.5):
    def make_truncated(tmp_path):
        path = make(tmp_path)
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])
        return path

    return make_truncated


def edited(make, edit):
    def make_edited(tmp_path):
        path = make(tmp_path)
        edit(path)
        return path

    return make_edited


def npz(**arrays):
    def make(tmp_path):
        path = tmp_path / "demos.npz"
        np.savez(path, **arrays)
        return path

    return make


def h5(**arrays):
    def make(tmp_path):
        import h5py

        path = tmp_path / "demos.h5"
        with h5py.File(path, "w") as f:
            for k, v in arrays.items():
                if k == "ragged":
                    f.create_dataset("observations", data=np.array([np.zeros(2), np.zeros(3)], dtype=object),
                                     dtype=h5py.vlen_dtype(np.float64))  # fmt: skip
                else:
                    f[k] = v
        return path

    return make


def renamed(writer, written, name):
    """A file written under one name and given another (a format the suffix does not say)."""

    def make(tmp_path):
        writer(tmp_path / written)
        os.replace(tmp_path / written, tmp_path / name)
        return tmp_path / name

    return make


def read(make, reader=load_trajectories):
    return lambda tmp_path: reader(make(tmp_path))


def _truncate_memmap(path):
    f = path / "observation.memmap"
    f.write_bytes(f.read_bytes()[:5])


def _grow_memmap(path):
    f = path / "observation.memmap"
    f.write_bytes(f.read_bytes() + b"\0" * 8)


def _run_dir(tmp_path, name, text):
    folder = tmp_path / "run" / "Pong" / "seed0"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(text)
    return tmp_path / "run"


GOOD_OBS = np.random.default_rng(0).random((2, 4, 2))
GOOD_ACT = np.zeros((2, 3), dtype=np.int64)

CASES = [
    # ---- .npz
    ("load_trajectories", "issue: .npz that is not a zip archive (numpy read it as a pickle)", read(write("demos.npz", os.urandom(300))),
     TrajectoryFileError, "demos.npz: not a readable NumPy .npz file"),
    ("load_trajectories", "issue: truncated .npz", read(truncated(saved("demos.npz"))), TrajectoryFileError,
     "demos.npz: not a readable NumPy .npz file (truncated, corrupt or another format: BadZipFile"),
    ("load_trajectories", ".npz cut in its last bytes", read(truncated(saved("demos.npz"), keep=0.97)), TrajectoryFileError, "demos.npz"),
    ("load_trajectories", "empty .npz", read(write("demos.npz", b"")), TrajectoryFileError,
     "demos.npz: this NumPy .npz file is empty; expected a NumPy .npz file holding the arrays 'observations' and 'actions'"),
    ("load_trajectories", "a .npy file named .npz", read(renamed(lambda p: np.save(p, GOOD_OBS), "a.npy", "demos.npz")),
     TrajectoryFileError, "holds one array (a .npy file)"),
    ("load_trajectories", "a torch file named .npz", read(renamed(lambda p: save_trajectories(DEMOS, p), "demos.pt", "demos.npz")),
     TrajectoryFileError, "demos.npz: 'observations' is missing (found keys:"),
    ("load_trajectories", "ragged (object) arrays in .npz",
     read(lambda t: (np.savez(t / "demos.npz", observations=np.array([np.zeros(3), np.zeros(2)], dtype=object),
                              actions=GOOD_ACT), t / "demos.npz")[-1]),
     TrajectoryFileError, "'observations' is a ragged (object) array"),
    ("load_trajectories", "string observations", read(npz(observations=np.full((2, 4, 2), "a"), actions=GOOD_ACT)), TrajectoryFileError,
     "'observations' must hold numbers (or booleans), got dtype <U1"),
    ("load_trajectories", "no actions", read(npz(observations=GOOD_OBS)), TrajectoryFileError, "'actions' is missing"),
    ("load_trajectories", "control: a good .npz", read(npz(observations=GOOD_OBS, actions=GOOD_ACT)), OK, None),
    # ---- .h5
    ("load_trajectories", "issue: .h5 that is not HDF5", read(write("demos.h5", os.urandom(300))), TrajectoryFileError,
     "demos.h5: not a readable HDF5 file (truncated, corrupt or another format: OSError"),
    ("load_trajectories", "truncated .h5", read(truncated(h5(observations=np.zeros((2, 300, 10)), actions=np.zeros((2, 299), int)))),
     TrajectoryFileError, "demos.h5: not a readable HDF5 file"),
    ("load_trajectories", "empty .h5", read(write("demos.h5", b"")), TrajectoryFileError, "demos.h5: this HDF5 file is empty"),
    ("load_trajectories", "a ragged .h5 dataset", read(h5(ragged=True, actions=GOOD_ACT)), TrajectoryFileError,
     "'observations' is a ragged (variable-length) dataset"),
    ("load_trajectories", "control: a good .h5", read(h5(observations=GOOD_OBS, actions=GOOD_ACT)), OK, None),
    # ---- .pt
    ("load_trajectories", "cosmetic: truncated .pt says 'trajectories file' once", read(truncated(saved("demos.pt"))),
     TrajectoryFileError, "demos.pt: not a readable trajectories file (truncated"),
    ("load_trajectories", "empty .pt", read(write("demos.pt", b"")), TrajectoryFileError, "demos.pt: this trajectories file is empty."),
    ("load_trajectories", "random bytes as .pt", read(write("demos.pt", os.urandom(300))), TrajectoryFileError,
     "demos.pt: not a readable trajectories file"),
    ("load_trajectories", "a .pt of another kind", read(lambda t: (torch.save([1, 2], t / "l.pt"), t / "l.pt")[-1]),
     TrajectoryFileError, "l.pt: expected trajectories (a dict of tensors"),
    ("load_trajectories", "an options file as trajectories", read(lambda t: (save_options(OptionsMLP(2, 3, 2), t / "o.pt"), t / "o.pt")[-1]),
     TrajectoryFileError, "o.pt: expected trajectories"),
    ("load_trajectories", "control: a good .pt", read(saved("demos.pt")), OK, None),
    # ---- TensorDict directories
    ("load_trajectories", "a truncated tensor file (read as zeros, and the file grown on disk, before)",
     read(edited(saved("demos"), _truncate_memmap)), TrajectoryFileError,
     "observation.memmap holds 5 bytes, but entry 'observation' (torch.float32 of shape [2, 5, 2]) needs 80"),
    ("load_trajectories", "a tensor file with extra bytes", read(edited(saved("demos"), _grow_memmap)), TrajectoryFileError,
     "observation.memmap holds 88 bytes"),
    ("load_trajectories", "a tensor file missing", read(edited(saved("demos"), lambda p: (p / "observation.memmap").unlink())),
     TrajectoryFileError, "the TensorDict directory lacks"),
    ("load_trajectories", "a corrupt meta.json", read(edited(saved("demos"), lambda p: (p / "meta.json").write_text("{oops"))),
     TrajectoryFileError, "meta.json is not valid JSON"),
    ("load_trajectories", "a directory without meta.json", read(lambda t: (t / "d").mkdir() or t / "d"), TrajectoryFileError,
     "not a TensorDict directory (no meta.json)"),
    ("load_trajectories", "control: a good directory", read(saved("demos")), OK, None),
    # ---- any format
    ("load_trajectories", "a missing file", lambda t: load_trajectories(t / "nope.npz"), FileNotFoundError,
     "nope.npz: no such trajectories file or directory"),
    ("load_trajectories", "format unknown", lambda t: load_trajectories(t / "x.npz", format="csv"), ValueError,
     "format must be 'auto', 'npz', 'hdf5' or 'tensordict'"),
    ("load_trajectories", "path of another type", lambda t: load_trajectories(3), TypeError, "path must be a str or a path"),
    ("load_trajectories", "an unknown suffix", read(write("demos.csv", b"1,2")), TrajectoryFileError, "cannot tell the format from the name"),
    ("save_trajectories", "a folder that does not exist", lambda t: save_trajectories(DEMOS, t / "no" / "d.npz"), ValueError,
     "the folder"),
    # ---- options and hierarchy files, checkpoints
    ("load_options", "a hierarchy file", lambda t: load_options((save_hierarchy(OptionHierarchy(3, [OptionsMLP(2, 3, 2)]), t / "h.pt"),
     t / "h.pt")[-1]), ValueError, "h.pt: not an options file written by torchrl_options.save_options (expected format "
     "'torchrl_options/options-v1', got a file of format 'torchrl_options/hierarchy-v1')"),
    ("load_options", "random bytes", lambda t: load_options(write("o.pt", os.urandom(200))(t)), ValueError, "o.pt: not a readable options file"),
    ("load_options", "path of another type", lambda t: load_options(3), TypeError, "path must be a str or a path to the options file"),
    ("load_hierarchy", "an options file", lambda t: load_hierarchy((save_options(OptionsMLP(2, 3, 2), t / "o.pt"), t / "o.pt")[-1]),
     ValueError, "o.pt: not a hierarchy file written by torchrl_options save_hierarchy (expected format"),
    ("load_hierarchy", "truncated", lambda t: load_hierarchy(truncated(lambda t2: (save_hierarchy(OptionHierarchy(3, [OptionsMLP(2, 3, 2)]),
     t2 / "h.pt"), t2 / "h.pt")[-1])(t)), ValueError, "h.pt: not a readable hierarchy file"),
    ("load_file", "a directory (an article before a vowel)", lambda t: load_file(t, what="OptionsDQN checkpoint"), ValueError,
     "expected an OptionsDQN checkpoint file, got a directory"),
    ("load_file", "control: plain data", lambda t: (save_file({"a": 1}, t / "a.pt"), load_file(t / "a.pt"))[-1], OK, None),
    ("tensordict_from_plain", "plain data of another kind", lambda t: tensordict_from_plain({"a": 1}, "x.pt"), ValueError,
     "x.pt: not a tensordict file written by torchrl_options"),
    # ---- the JSON and CSV files of a run
    ("load_json_file", "truncated JSON", lambda t: load_json_file(write("s.json", b'{"a": 1')(t), what="run settings"), ValueError,
     "s.json: not a readable run settings file (expected JSON"),
    ("load_json_file", "empty JSON", lambda t: load_json_file(write("s.json", b"")(t)), ValueError, "s.json: this JSON file is empty"),
    ("load_json_file", "binary", lambda t: load_json_file(write("s.json", b"\xff\xfe\x00")(t)), ValueError, "s.json: not a readable JSON file"),
    ("load_json_file", "a missing file", lambda t: load_json_file(t / "n.json", what="cell info"), FileNotFoundError,
     "n.json: no such cell info file"),
    ("read_run_settings", "a half-written settings.json", lambda t: read_run_settings((write("settings.json", b'{"episodes": 2')(t), t)[-1]),
     ValueError, "settings.json: not a readable run settings file"),
    ("read_run_settings", "a settings.json that is a list", lambda t: read_run_settings((write("settings.json", b"[1]")(t), t)[-1]),
     ValueError, "settings.json: expected the run settings as a JSON object"),
    ("ResultsLog.rows", "a header of another file", lambda t: ResultsLog(write("r.csv", b"a,b\n1,2\n")(t)).rows(), ValueError,
     "r.csv: not a results file (expected the CSV columns"),
    ("ResultsLog.rows", "a row whose return is not a number",
     lambda t: ResultsLog(write("r.csv", b"setting,condition,seed,episode,return,frames\ns,A,0,0,abc,\n")(t)).rows(), ValueError,
     "r.csv, line 2: not a valid results row"),
    ("ResultsLog", "a directory", lambda t: ResultsLog(t), ValueError, "is a directory; expected a CSV file name"),
    ("ResultsLog.rows", "control: a fresh log", lambda t: ResultsLog(t / "r.csv").rows(), OK, None),
    ("demonstration_fit_markdown", "a half-written phase2.json", lambda t: demonstration_fit_markdown(str(_run_dir(t, "phase2.json", '{"a"'))),
     ValueError, "phase2.json: not a readable phase-2 info file"),
    ("option_usage_markdown", "a half-written cell json", lambda t: option_usage_markdown(str(_run_dir(t, "H1.json", '{"seconds": '))),
     ValueError, "H1.json: not a readable Atari cell info file"),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_file_readers(tmp_path, api, case, call, error, phrase):
    check(call, error, phrase, tmp_path)


def test_a_truncated_tensordict_directory_is_left_as_it_was(tmp_path):
    """Before issue 53, TensorDict mapped the short file, filled it with zeros and grew it on disk."""
    path = tmp_path / "demos"
    save_trajectories(DEMOS, path)
    _truncate_memmap(path)
    with pytest.raises(TrajectoryFileError):
        load_trajectories(path)
    assert (path / "observation.memmap").stat().st_size == 5


def test_run_files_are_written_atomically(tmp_path, monkeypatch):
    """settings.json and the results' header are replaced whole: a write interrupted half-way leaves no file."""
    from torchrl_options.experiments.run_settings import write_run_settings

    real_dump = json.dump

    def dump_then_interrupt(obj, f, **kw):
        f.write('{"half": ')
        raise KeyboardInterrupt

    monkeypatch.setattr(json, "dump", dump_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_run_settings(tmp_path, {"episodes": 3})
    monkeypatch.setattr(json, "dump", real_dump)
    assert list(tmp_path.iterdir()) == []
    write_run_settings(tmp_path, {"episodes": 3})
    assert read_run_settings(tmp_path) == {"episodes": 3}
    assert Path(tmp_path / "settings.json").exists()
