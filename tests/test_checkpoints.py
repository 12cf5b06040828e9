"""Atomic writes of the files the package reads back: a unique temporary file per write, replaced atomically on
success and removed on failure (see ``tests/test_safe_loading.py`` for loading)."""
import threading

import pytest
import torch

from torchrl_options.checkpoints import atomic_replace, load_file, save_file


def test_atomic_replace_names_are_unique_per_call(tmp_path):
    path = tmp_path / "state.pt"
    with atomic_replace(path) as a, atomic_replace(path) as b:
        assert a != b and a.parent == b.parent == tmp_path
        a.write_text("a")
        b.write_text("b")
    assert path.read_text() == "a"  # the outer block ended last
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.pt"]


def test_atomic_replace_keeps_the_old_file_on_error(tmp_path):
    path = tmp_path / "state.pt"
    save_file({"step": 1}, path)
    with pytest.raises(KeyboardInterrupt):
        with atomic_replace(path) as tmp:
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert load_file(path) == {"step": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"]


def test_concurrent_saves_of_one_path_from_threads(tmp_path):
    path = tmp_path / "state.pt"
    errors = []

    def save(i):
        try:
            for _ in range(5):
                save_file({"writer": i, "weights": torch.full((1000,), float(i))}, path)
        except Exception as err:  # a shared temporary name makes os.replace fail or mixes two writers' bytes
            errors.append(err)

    threads = [threading.Thread(target=save, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    state = load_file(path)
    assert torch.equal(state["weights"], torch.full((1000,), float(state["writer"])))
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"]
