"""The GridWorld per-cell pipeline: batched-env DQN, checkpoint resume, cached discovery, greedy trajectories."""
import pytest
import torch

from torchrl_options.checkpoints import load_file
from torchrl_options.envs import ValueIterationSupervisor
from torchrl_options.experiments import Cell
from torchrl_options.experiments.gridworld import (
    cell_options,
    discover_cached,
    greedy_trajectories,
    make_agent,
    make_env,
    train_episodes,
)


def _cfg(out_dir, **kw):
    cfg = dict(
        out_dir=str(out_dir),
        env=dict(grid="two-rooms", task="goal", noise=0.3, max_steps=20, start="map", goal="map"),
        num_envs=4,
        demos=dict(num=3, length=60, env=dict(start="random", goal="random", max_steps=60)),
        discovery=dict(num_options=2, num_iterations=2, batch_size=None, lr=0.01),
        dqn=dict(hidden_sizes=[2], gamma=0.9, eps_init=0.2, eps_end=0.2, frames_per_batch=16, batch_size=16,
                 learning_starts=16, updates_per_batch=1),
        episodes=8,
        checkpoint_every=4,
        settings=dict(supervised=dict(source="supervisor")),
        conditions=dict(A=dict(mode="actions"), AO=dict(mode="both", meta_control="uniform")),
        logger=dict(backend=""),
    )  # fmt: skip
    cfg.update(kw)
    return cfg


def test_agent_runs_one_batched_env(tmp_path):
    agent = make_agent(_cfg(tmp_path), "actions", seed=0)
    assert agent.env.batch_size == torch.Size([4])  # the GridWorldEnv batch itself, no SerialEnv
    returns, frames = train_episodes(agent, 6)
    assert len(returns) == 6 and frames == sorted(frames)


def test_train_episodes_resumes_from_checkpoint(tmp_path):
    ckpt = tmp_path / "dqn.pt"
    agent = make_agent(_cfg(tmp_path), "actions", seed=0)
    first, _ = train_episodes(agent, 4, ckpt, checkpoint_every=4)
    assert "replay_buffer" not in load_file(ckpt)  # finished: what a resume needs, not the buffer
    frames = agent.frames
    resumed = make_agent(_cfg(tmp_path), "actions", seed=0)
    returns, _ = train_episodes(resumed, 10, ckpt, checkpoint_every=4)
    assert returns[:4] == first and len(returns) == 10
    assert resumed.frames > frames  # continued, not restarted
    state = load_file(ckpt)
    assert len(state["log"]["episode_returns"]) >= 10 and "replay_buffer" not in state


def test_train_episodes_keeps_the_buffer_until_the_end(tmp_path, monkeypatch):
    """Mid-run checkpoints hold the replay buffer (a bit-for-bit resume needs it); the final one only when asked
    (``final_buffer``: an agent trained on afterwards, like the exploration setting's pre-trained agent)."""
    import torchrl_options.experiments.gridworld as gridworld

    saved = []
    real_save = gridworld.save_file
    monkeypatch.setattr(gridworld, "save_file", lambda obj, path: (saved.append(obj), real_save(obj, path))[1])
    train_episodes(make_agent(_cfg(tmp_path), "actions", seed=0), 8, tmp_path / "a.pt", checkpoint_every=4)
    assert ["replay_buffer" in s for s in saved] == [True, False]
    saved.clear()
    train_episodes(make_agent(_cfg(tmp_path), "actions", seed=0), 8, tmp_path / "b.pt", checkpoint_every=4,
                   final_buffer=True)  # fmt: skip
    assert ["replay_buffer" in s for s in saved] == [True, True]


def test_discovery_is_cached(tmp_path):
    cfg = _cfg(tmp_path)
    options = cell_options(cfg, Cell("supervised", "AO", 0))
    assert options.num_options == 2
    assert (tmp_path / "cells" / "supervised-seed0" / "options-K2-uniform.pt").exists()

    def fail():
        raise AssertionError("the cached options should be loaded, not rediscovered")

    path = tmp_path / "cells" / "supervised-seed0" / "options-K2-uniform.pt"
    again = discover_cached(fail, path, num_options=2, meta_control="uniform", seed=0, discovery=cfg["discovery"])
    td = make_env(cfg["env"], 3, 0).reset()
    assert torch.equal(options(td.clone())["option_logits"], again(td.clone())["option_logits"])
    assert cell_options(cfg, Cell("supervised", "A", 0)) is None


def test_greedy_trajectories_stop_at_the_goal():
    env_cfg = dict(grid="two-rooms", task="goal", noise=0.0)
    policy = ValueIterationSupervisor(make_env(env_cfg, 1, 0), seed=0)
    data = greedy_trajectories(policy, env_cfg, num=4, length=60, seed=0)
    mask = data["collector", "mask"]
    reward = data["next", "reward"].squeeze(-1)
    assert bool((reward * mask).sum(-1).eq(1).all())  # each row: one episode, ending at its goal


def test_condition_may_override_the_number_of_episodes(tmp_path):
    from torchrl_options.experiments.gridworld import run_gridworld_cell

    cfg = _cfg(tmp_path, episodes=4)
    cfg["conditions"] = dict(A=dict(mode="actions", episodes=7), AO=dict(mode="both", meta_control="uniform"))
    assert len(run_gridworld_cell(Cell("supervised", "A", 0), cfg).returns) == 7
    assert len(run_gridworld_cell(Cell("supervised", "AO", 0), cfg).returns) == 4


def test_greedy_trajectories_with_epsilon_take_random_actions_reproducibly():
    env_cfg = dict(grid="four-rooms", task="apple", noise=0.0)

    def run(epsilon=None):  # a fresh supervisor each time: it draws from its own seeded generator
        policy = ValueIterationSupervisor(make_env(env_cfg, 1, 0), seed=0)
        kwargs = {} if epsilon is None else {"epsilon": epsilon}
        return greedy_trajectories(policy, env_cfg, num=8, length=50, seed=3, **kwargs)["action"]

    assert torch.equal(run(), run(0.0))
    assert torch.equal(run(0.5), run(0.5)) and not torch.equal(run(0.5), run())
    # with epsilon 1 every action is uniform: all four appear about equally often, unlike the supervisor's
    counts = torch.bincount(run(1.0).flatten(), minlength=4).float() / 400
    assert bool((counts - 0.25).abs().max() < 0.06)
    with pytest.raises(ValueError, match="epsilon"):
        greedy_trajectories(lambda td: td, env_cfg, num=2, length=5, seed=0, epsilon=1.5)


def test_agent_rollouts_keep_the_rewarded_pieces(tmp_path):
    from torchrl_options.experiments.gridworld import _agent_rollouts, make_agent

    cfg = _cfg(tmp_path)
    cfg["env"] = dict(grid="four-rooms", task="apple", noise=0.3, max_steps=100)
    agent = make_agent(cfg, "actions", 0)
    rollouts = {"num": 16, "length": 100, "epsilon": 1.0}
    everything = _agent_rollouts(agent, cfg, rollouts, seed=0)
    pieces = _agent_rollouts(agent, cfg, {**rollouts, "keep": "rewarded"}, seed=0)
    mask = pieces["collector", "mask"]
    assert everything.shape == torch.Size([16, 100])
    assert 0 < mask.sum() < everything["collector", "mask"].sum()
    last = mask.sum(-1) - 1
    assert bool((pieces["next", "reward"].squeeze(-1)[torch.arange(len(last)), last] > 0).all())
    assert _agent_rollouts(agent, cfg, {**rollouts, "epsilon": "agent"}, seed=0).shape == torch.Size([16, 100])
