"""Atomic writes of the files the package reads back: a unique temporary file per write, replaced atomically on
success and removed on failure (see ``tests/test_safe_loading.py`` for loading); a seed scoped to a block."""
import random
import threading

import numpy as np
import pytest
import torch

from torchrl_options.checkpoints import atomic_replace, load_file, save_file, scoped_seed


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


def test_scoped_seed_restores_every_global_state_also_after_an_error():
    torch.manual_seed(0)
    seeded = torch.rand(3)

    def seed_all():
        torch.manual_seed(5)
        np.random.seed(5)
        random.seed(5)

    seed_all()
    expected = (torch.rand(3), np.random.rand(3), [random.random() for _ in range(3)])
    seed_all()
    with pytest.raises(KeyboardInterrupt):
        with scoped_seed(0):
            inside = torch.rand(3)
            np.random.seed(1)  # what a checkpoint's set_rng_state does inside a cell
            random.seed(1)
            raise KeyboardInterrupt
    assert torch.equal(inside, seeded)
    after = (torch.rand(3), np.random.rand(3), [random.random() for _ in range(3)])
    assert torch.equal(after[0], expected[0]) and np.array_equal(after[1], expected[1]) and after[2] == expected[2]
