"""A recipe cell interrupted right after a mid-cell checkpoint and resumed writes the same results.csv, byte for
byte, as the run that was never interrupted (every random state travels in the checkpoint)."""
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import torchrl_options.experiments.gridworld as gridworld
from torchrl_options.checkpoints import load_file

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        cfg = compose(
            config_name="four_rooms",
            overrides=[
                "scale=tiny", f"out_dir={out_dir}", "progress=false", "logger.backend=", "episodes=48",
                "settings_to_run=[supervised]", "env.max_steps=40", "checkpoint_every=16", "num_envs=4",
                "dqn.learning_starts=16", "dqn.frames_per_batch=16", "dqn.batch_size=16", "dqn.updates_per_batch=1",
                "dqn.eps_init=0.5", "dqn.eps_end=0.5", *overrides,
            ],
        )  # fmt: skip
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_container(cfg, resolve=True)
    cfg["pictures"] = None
    return cfg


def _run(cfg):
    from torchrl_options.experiments.results import ResultsLog
    from torchrl_options.experiments.sweep import run_sweep

    out = Path(cfg["out_dir"])
    log = ResultsLog(out / "results.csv")
    cells = [gridworld.Cell("supervised", c, 0) for c in cfg["conditions_to_run"]]
    import functools

    before = torch.get_rng_state()
    run_sweep(functools.partial(gridworld.run_gridworld_cell, cfg=cfg), cells, log)
    assert torch.equal(torch.get_rng_state(), before), "a cell left the caller's random state changed"
    return (out / "results.csv").read_bytes()


@pytest.mark.parametrize("condition", ["A", "H1u"])
def test_gridworld_cell_resumes_bit_for_bit(tmp_path, monkeypatch, condition):
    whole = _run(_cfg(tmp_path / "whole", f"conditions_to_run=[{condition}]"))
    returns = [line.split(b",")[4] for line in whole.splitlines()[1:]]
    assert len(set(returns)) > 1, "the returns must vary for the comparison to mean something"

    saves = []
    real_save = gridworld.save_file

    def save_then_interrupt(obj, path):
        real_save(obj, path)
        if Path(path).name == "dqn.pt":
            saves.append(len(obj["log"]["episode_returns"]))
            if len(saves) == 2:  # Ctrl-C right after the second mid-cell checkpoint
                raise KeyboardInterrupt

    cfg = _cfg(tmp_path / "cut", f"conditions_to_run=[{condition}]")
    monkeypatch.setattr(gridworld, "save_file", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        _run(cfg)
    assert not (tmp_path / "cut" / "results.csv").exists() or b"supervised" not in (tmp_path / "cut" / "results.csv").read_bytes()
    ckpt = tmp_path / "cut" / "cells" / f"supervised-{condition}-seed0" / "dqn.pt"
    cut = load_file(ckpt)
    assert 16 <= len(cut["log"]["episode_returns"]) < 48  # interrupted mid-cell
    assert "replay_buffer" in cut  # an unfinished cell keeps its buffer: a bit-for-bit resume needs it
    monkeypatch.setattr(gridworld, "save_file", real_save)
    torch.manual_seed(1234)  # the resumed process's global random state is whatever it is
    resumed = _run(cfg)
    assert resumed == whole
    finished = load_file(ckpt)
    assert len(finished["log"]["episode_returns"]) >= 48
    assert "replay_buffer" not in finished  # a finished cell keeps no buffer
    assert ckpt.stat().st_size < 100_000


def test_checkpoint_carries_random_state(tmp_path):
    cfg = _cfg(tmp_path, "conditions_to_run=[A]")
    _run(cfg)
    state = load_file(tmp_path / "cells" / "supervised-A-seed0" / "dqn.pt")
    assert set(state["rng"]) >= {"torch", "numpy", "python"}


def _atari_run(out_dir, condition):
    import functools

    import torchrl_options.experiments.atari as atari
    from torchrl_options.experiments.results import ResultsLog
    from torchrl_options.experiments.sweep import Cell, run_sweep

    config = atari.AtariConfig(
        max_episode_steps=60, noop_max=5, phase1_episodes=3, phase3_episodes=4, num_demonstrations=2,
        demo_max_steps=60, options_num_cells=(8,), ddo_iterations=2, ddo_batch_size=None, hidden_sizes=(8, 8, 8),
        learning_starts=16, frames_per_batch=16, updates_per_batch=1, hard_update_interval=20, checkpoint_every=1,
        option_frames=False, ram_encoding="bytes", eps_init=0.3, eps_end=0.3, clip_rewards=False,
    )  # fmt: skip
    log = ResultsLog(Path(out_dir) / "results.csv")
    before, threads = torch.get_rng_state(), torch.get_num_threads()
    config.torch_threads = threads + 1  # the recipe's to set: the cell leaves the thread count alone
    run_sweep(functools.partial(atari.run_atari_cell, config=config, out_dir=str(out_dir)), [Cell("Atlantis", condition, 0)], log)
    assert torch.equal(torch.get_rng_state(), before), "a cell left the caller's random state changed"
    assert torch.get_num_threads() == threads
    return (Path(out_dir) / "results.csv").read_bytes()


@pytest.mark.parametrize("condition, phase", [pytest.param("A", "phase1", marks=pytest.mark.slow), ("H1", "H1")])
def test_atari_cell_resumes_bit_for_bit(tmp_path, monkeypatch, condition, phase):
    """Interrupted right after the first checkpoint inside phase 1 (A) or phase 3 (H1: options, executor)."""
    pytest.importorskip("ale_py")
    import torchrl_options.experiments.atari.pipeline as pipeline

    whole = _atari_run(tmp_path / "whole", condition)
    returns = [line.split(b",")[4] for line in whole.splitlines()[1:]]
    assert len(set(returns)) > 1, "the returns must vary for the comparison to mean something"
    real_save, saves = pipeline.save_file, []

    def save_then_interrupt(obj, path):
        real_save(obj, path)
        if path.endswith(f"{phase}.partial.pt"):
            saves.append(path)
            raise KeyboardInterrupt  # Ctrl-C right after the first checkpoint inside the phase

    monkeypatch.setattr(pipeline, "save_file", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        _atari_run(tmp_path / "cut", condition)
    assert saves
    monkeypatch.setattr(pipeline, "save_file", real_save)
    torch.manual_seed(4321)
    assert _atari_run(tmp_path / "cut", condition) == whole
