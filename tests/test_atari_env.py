"""The Atari RAM env factory and the RAM encoders (torchrl_options.envs.atari)."""
import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import SerialEnv
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_options.envs.atari import (
    ATARI_GAMES,
    EpisodicLife,
    NoopStart,
    PAPER_NUM_OPTIONS,
    RAMBytesEncoder,
    RAMOneHotEncoder,
    atari_available,
    make_atari_ram_env,
    ram_q_network,
    render_frame,
)

needs_ale = pytest.mark.skipif(not atari_available(), reason="needs ale-py (the atari extra)")


def test_one_hot_encoder_equals_linear_on_explicit_one_hot():
    torch.manual_seed(0)
    enc = RAMOneHotEncoder(8)
    ram = torch.randint(0, 256, (5, 3, 128), dtype=torch.uint8)
    one_hot = torch.nn.functional.one_hot(ram.long(), 256).flatten(-2).float()  # [5, 3, 32768]
    linear = torch.nn.Linear(128 * 256, 8)
    with torch.no_grad():
        linear.weight.copy_(enc.weight.T)
        linear.bias.copy_(enc.bias)
    torch.testing.assert_close(enc(ram), linear(one_hot), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(enc(ram.float() / 255.0), enc(ram))  # bytes / 255 is decoded exactly
    # gradients reach only the rows of the bytes seen
    enc(ram[0, 0]).sum().backward()
    assert (enc.weight.grad.abs().sum(1) > 0).sum() == 128


def test_bytes_encoder_and_q_network():
    ram = torch.randint(0, 256, (4, 128), dtype=torch.uint8)
    enc = RAMBytesEncoder(6)
    torch.testing.assert_close(enc(ram), enc(ram.float() / 255.0))
    for encoding in ("bytes", "one_hot"):
        net = ram_q_network(9, encoding=encoding, num_cells=[16, 8, 8])
        assert net(ram).shape == (4, 9)
        assert sum(isinstance(m, torch.nn.Tanh) for m in net) == 3
    with pytest.raises(ValueError):
        ram_q_network(3, encoding="pixels")


def test_paper_option_counts():
    assert set(PAPER_NUM_OPTIONS) == set(ATARI_GAMES)
    assert PAPER_NUM_OPTIONS["Pooyan"] == 7 and PAPER_NUM_OPTIONS["Seaquest"] == 5


class _LivesEnv(gym.Env):
    """Three lives, one lost every 3 steps; game over when none is left."""

    observation_space = gym.spaces.Box(0, 255, (2,), np.uint8)
    action_space = gym.spaces.Discrete(2)

    class _ALE:
        def __init__(self):
            self.n = 3

        def lives(self):
            return self.n

    def __init__(self):
        self.ale = self._ALE()
        self.t = 0
        self.resets = 0

    def reset(self, *, seed=None, options=None):
        self.ale.n, self.t = 3, 0
        self.resets += 1
        return np.zeros(2, np.uint8), {}

    def step(self, action):
        self.t += 1
        if self.t % 3 == 0:
            self.ale.n -= 1
        return np.zeros(2, np.uint8), 1.0, self.ale.n == 0, False, {}


def test_episodic_life_ends_episodes_at_life_loss_and_resets_only_at_game_over():
    inner = _LivesEnv()
    env = EpisodicLife(inner)
    env.reset()
    lengths = []
    for _ in range(3):
        n, terminated = 0, False
        while not terminated:
            _, _, terminated, _, _ = env.step(0)
            n += 1
        lengths.append(n)
        env.reset()
    assert lengths == [3, 2, 2]  # the reset after a life loss spends one no-op step of the same game
    assert inner.resets == 2  # one at the start, one after the game over


@needs_ale
def test_make_atari_ram_env_bytes_and_uint8():
    env = make_atari_ram_env("Seaquest", max_episode_steps=20, noop_max=3, seed=0)
    check_env_specs(env)
    data = env.rollout(30)
    obs = data["observation"]
    assert obs.dtype == torch.float32 and obs.shape == (20, 128)
    assert obs.min() >= 0 and obs.max() <= 1
    assert torch.equal((obs * 255).round(), (obs * 255))  # exact bytes
    assert data["next", "truncated"][-1].all() and data["next", "step_count"][-1].item() == 20
    assert env.action_spec.n == 18
    raw = make_atari_ram_env("Pooyan", ram_encoding="uint8", max_episode_steps=5, seed=0)
    assert raw.rollout(5)["observation"].dtype == torch.uint8
    with pytest.raises(ValueError):
        make_atari_ram_env("Pooyan", ram_encoding="one_hot")


@needs_ale
def test_reward_clipping_and_frame_skip():
    torch.manual_seed(0)
    clipped = make_atari_ram_env("Atlantis", max_episode_steps=150, noop_max=0, seed=1)
    raw = make_atari_ram_env("Atlantis", max_episode_steps=150, noop_max=0, clip_rewards=False, seed=1)
    rc, rr = clipped.rollout(150)["next", "reward"], raw.rollout(150)["next", "reward"]
    assert rc.abs().max() <= 1
    assert rr.max() > 1  # Atlantis scores hundreds per hit
    one = make_atari_ram_env("Atlantis", frame_skip=1, noop_max=0, max_episode_steps=10, seed=0)
    assert one.rollout(10).shape == (10,)


@needs_ale
def test_batched_env_specs_and_render():
    env = SerialEnv(2, lambda: make_atari_ram_env("Gopher", max_episode_steps=10, noop_max=2))
    check_env_specs(env)
    env.close()
    env = make_atari_ram_env("SpaceInvaders", render=True, episodic_life=True, max_episode_steps=5, seed=0)
    env.rollout(2)
    frame = render_frame(env)
    assert frame.shape == (210, 160, 3) and frame.dtype == np.uint8


class _CountingEnv(gym.Env):
    """Counts steps since reset (the observation); ends after ``horizon`` steps."""

    observation_space = gym.spaces.Box(0, 1000, (1,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self, horizon=1000):
        self.horizon, self.t, self.resets, self.actions = horizon, 0, 0, []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.resets = 0, self.resets + 1
        return np.array([0.0], np.float32), {}

    def step(self, action):
        self.t += 1
        self.actions.append(int(action))
        return np.array([self.t], np.float32), 0.0, self.t >= self.horizon, False, {}


def test_noop_start_draws_uniform_counts_and_resets_at_game_over():
    inner = _CountingEnv()
    env = NoopStart(inner, noop_max=4)
    counts = []
    for i in range(400):
        obs, _ = env.reset(seed=i)
        counts.append(int(obs[0]))
    assert set(counts) == {0, 1, 2, 3}  # [0, noop_max), as TorchRL's NoopResetEnv(random=True)
    assert all(a == 0 for a in inner.actions)  # no-ops only
    assert abs(np.mean(counts) - 1.5) < 0.25
    # the same seed gives the same start
    assert env.reset(seed=3)[0][0] == env.reset(seed=3)[0][0]
    # a game over during the no-ops resets again
    short = _CountingEnv(horizon=1)
    env = NoopStart(short, noop_max=50)
    for i in range(20):
        obs, _ = env.reset(seed=i)
        assert obs[0] == 0
    assert short.resets > 20
    with pytest.raises(ValueError, match="noop_max"):
        NoopStart(_CountingEnv(), noop_max=0)


@needs_ale
def test_vector_env_batch_partial_reset_and_seeding():
    def rollout(seed):
        env = make_atari_ram_env("Pooyan", num_envs=3, max_episode_steps=12, noop_max=10, seed=seed)
        torch.manual_seed(0)  # the random actions
        return env, env.rollout(30, break_when_any_done=False)

    env, data = rollout(5)
    assert env.batch_size == (3,)
    assert data.shape == (3, 30)
    steps = data["next", "step_count"].squeeze(-1)
    assert (steps[:, 11] == 12).all() and (steps[:, 12] == 1).all()  # truncated and reset at the step limit
    assert data["next", "truncated"].squeeze(-1).sum(-1).tolist() == [2, 2, 2]
    first = data["observation"][:, 0]
    assert not torch.equal(first[0], first[1]) or not torch.equal(first[1], first[2])  # games seeded apart
    # the same seed and actions reproduce the rollout, another seed does not
    torch.testing.assert_close(rollout(5)[1], data)
    assert not torch.equal(rollout(6)[1]["observation"], data["observation"])
    check_env_specs(env)
    # a partial reset starts only the masked game again
    td = env.reset()
    for _ in range(5):
        td = env.rand_step(td)
        td = td["next"].clone()
    before = td["observation"].clone()
    td.set("_reset", torch.tensor([[False], [True], [False]]))
    out = env.reset(td)
    assert out["step_count"].squeeze(-1).tolist() == [5, 0, 5]
    torch.testing.assert_close(out["observation"][[0, 2]], before[[0, 2]])
    env.close()
    with pytest.raises(ValueError, match="num_envs"):
        make_atari_ram_env("Pooyan", num_envs=0)
    with pytest.raises(ValueError, match="render"):
        make_atari_ram_env("Pooyan", num_envs=2, render=True)


@needs_ale
def test_vector_env_episodic_life_per_game():
    env = make_atari_ram_env("SpaceInvaders", num_envs=2, episodic_life=True, noop_max=0, max_episode_steps=2000,
                             seed=0)
    torch.manual_seed(0)
    data = env.rollout(600, break_when_any_done=False)
    done = data["next", "terminated"].squeeze(-1)
    steps = data["next", "step_count"].squeeze(-1)
    for i in range(2):
        ends = done[i].nonzero().squeeze(-1)
        assert len(ends) >= 2  # an episode is a life: several per game in 600 steps
        assert (steps[i, ends[:-1] + 1] == 1).all()  # each game starts its next episode on its own
    # a lost life does not reset the emulator: some game is on with fewer lives than it started with
    games = env.base_env._env.envs
    assert any(not g.game_over and 0 < g.unwrapped.ale.lives() < 3 for g in games)
    env.close()


@needs_ale
def test_paper_env_settings_random_frame_skip_sticky_raw_rewards():
    from torchrl_options.envs.atari import PAPER_ENV_SETTINGS

    assert PAPER_ENV_SETTINGS == {"frame_skip": (2, 5), "repeat_action_probability": 0.25, "noop_max": 0,
                                  "episodic_life": False, "clip_rewards": False, "max_episode_steps": 10_000}
    env = make_atari_ram_env("Atlantis", **{**PAPER_ENV_SETTINGS, "max_episode_steps": 300}, seed=0)
    ale = env.base_env._env.unwrapped.ale
    assert ale.getFloat("repeat_action_probability") == 0.25
    env.reset()
    skips, rewards = [], []
    td = env.reset()
    for _ in range(300):
        before = ale.getEpisodeFrameNumber()
        td = env.rand_step(td)
        skips.append(ale.getEpisodeFrameNumber() - before)
        rewards.append(float(td["next", "reward"]))
        td = td["next"] if not td["next", "done"] else env.reset()
    assert set(skips) == {2, 3, 4}  # drawn uniformly in 2-4 at every step
    assert max(rewards) > 1  # raw: Atlantis scores hundreds per hit
    env.close()


@needs_ale
@pytest.mark.parametrize("bad", [0, (3, 3), (0, 2), (2, 5, 7), 2.5, True])
def test_bad_frame_skip_refused(bad):
    with pytest.raises(ValueError, match="frame_skip must be an int >= 1 or a pair"):
        make_atari_ram_env("Pooyan", frame_skip=bad)
