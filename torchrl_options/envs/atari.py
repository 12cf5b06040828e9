"""Atari games seen through their 128 bytes of RAM, as in the DDO paper's Atari experiments.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.2 and appendix B:
DQN and DDO on Atlantis, Pooyan, Gopher, Space Invaders and Seaquest with the RAM as observation, one-hot
encoded (128 x 256 inputs), and three dense tanh layers.

Two pieces live here:

- :func:`make_atari_ram_env`: ``GymEnv("ALE/<Game>-v5", obs_type="ram")`` with the usual Atari wrappers, each
  configurable (ALE frame skip and sticky actions, random no-op starts, end of episode at the loss of a life,
  reward clipping, a step limit). The observation is ``"observation"``: float32 ``bytes / 255`` (default) or the
  raw uint8 bytes.
- :class:`RAMOneHotEncoder`: the paper's one-hot encoding as the first layer of a network. A linear layer on the
  32768-dimensional one-hot vector is a sum of 128 embedding rows (one per byte, indexed by its value), so it is
  an ``nn.EmbeddingBag`` and the one-hot vector is never built.

Why the env does not one-hot encode: a 32768-float observation would make every replay-buffer entry 128 KiB.
``bytes / 255`` is exact (``round(x * 255)`` gives the bytes back) and small; each network chooses its input layer:
one-hot (the Q-network's :class:`RAMOneHotEncoder`, the options' :class:`~torchrl_options.modules.OneHotByteOptions`
with ``value_scale=1 / 255``) or the bytes as numbers.

:data:`PAPER_ENV_SETTINGS` are the authors' environment semantics (their gym ``<Game>-ram-v0``).
"""
from __future__ import annotations

import importlib.util
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import (
    Compose,
    EnvBase,
    GymWrapper,
    NoopResetEnv,
    ObservationTransform,
    RewardClipping,
    RewardSum,
    StepCounter,
    TransformedEnv,
)

from torchrl_options.checks import check_bool, check_distinct_keys, check_int, check_number

__all__ = [
    "ATARI_GAMES",
    "PAPER_NUM_OPTIONS",
    "RAMOneHotEncoder",
    "RAMBytesEncoder",
    "make_atari_ram_env",
    "atari_available",
    "EpisodicLife",
    "NoopStart",
    "PAPER_ENV_SETTINGS",
]

#: The paper's five RAM games.
ATARI_GAMES = ("Atlantis", "Pooyan", "Gopher", "SpaceInvaders", "Seaquest")

#: Options per game in the authors' figures.
PAPER_NUM_OPTIONS = {"Atlantis": 4, "Pooyan": 7, "Gopher": 3, "SpaceInvaders": 3, "Seaquest": 5}

RAM_SIZE = 128

#: The authors' environment (their pinned gym's ``<Game>-ram-v0``; ale-py registers the same ALE settings as
#: ``<Game>-v0``): sticky actions with probability 0.25, a frame skip drawn uniformly in 2-4 at every step (ALE's
#: ``frameskip=(2, 5)``), raw rewards, no random no-op starts, a whole game per episode, episodes cut at 10,000 steps
#: (gym's ``TimeLimit`` of the v0 ids). Keyword arguments of :func:`make_atari_ram_env`.
PAPER_ENV_SETTINGS = {
    "frame_skip": (2, 5),
    "repeat_action_probability": 0.25,
    "noop_max": 0,
    "episodic_life": False,
    "clip_rewards": False,
    "max_episode_steps": 10_000,
}


def atari_available() -> bool:
    """Whether ale-py (the ``atari`` extra, which ships the ROMs) is installed."""
    return importlib.util.find_spec("ale_py") is not None


class EpisodicLife(gym.Wrapper):
    """Ends the episode (``terminated``) when a life is lost; the next ``reset`` then continues the same game with
    one no-op step, and only resets the emulator after a real game over (Mnih et al., 2015).

    With it, an *episode* is a life: returns per game are the sum over its lives.
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.lives = 0
        self.game_over = True

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.game_over = terminated or truncated
        lives = self.env.unwrapped.ale.lives()
        if 0 < lives < self.lives:
            terminated = True
        self.lives = lives
        return obs, reward, terminated, truncated, info

    def reset(self, **kwargs):
        if self.game_over:
            obs, info = self.env.reset(**kwargs)
        else:
            obs, _, terminated, truncated, info = self.env.step(0)
            if terminated or truncated:
                obs, info = self.env.reset(**kwargs)
        self.game_over = False
        self.lives = self.env.unwrapped.ale.lives()
        return obs, info


class NoopStart(gym.Wrapper):
    """After each reset, a random number of no-op steps (action 0), uniform in ``[0, noop_max)``, drawn from the env's
    own generator (seeded by ``reset(seed=...)``); the same distribution as TorchRL's ``NoopResetEnv(random=True)``.

    A gymnasium wrapper, so that each env of a gymnasium vector env starts its episodes on its own (TorchRL's
    ``NoopResetEnv`` supports single envs only). If the game ends during the no-ops, it is reset again.

    Examples:
        >>> import gymnasium as gym
        >>> env = NoopStart(gym.make("CartPole-v1"), noop_max=5)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape
        (4,)
    """

    def __init__(self, env: gym.Env, noop_max: int):
        super().__init__(env)
        if noop_max < 1:
            raise ValueError(f"noop_max must be at least 1, got {noop_max}.")
        self.noop_max = int(noop_max)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        for _ in range(int(self.np_random.integers(0, self.noop_max))):
            obs, _, terminated, truncated, info = self.env.step(0)
            if terminated or truncated:
                obs, info = self.env.reset()
        return obs, info


class RAMToFloat(ObservationTransform):
    """uint8 RAM bytes to float32 ``bytes / 255`` in [0, 1] (exact: ``round(x * 255)`` gives the bytes back).

    Examples:
        >>> import torch
        >>> RAMToFloat()._apply_transform(torch.tensor([0, 51, 255], dtype=torch.uint8))
        tensor([0.0000, 0.2000, 1.0000])
    """

    def __init__(self, in_keys=("observation",), out_keys=None):
        in_keys = list(in_keys)
        out_keys = list(out_keys) if out_keys is not None else in_keys
        if len(out_keys) != len(in_keys):
            raise ValueError(f"RAMToFloat: out_keys must have one key per in_key, got {in_keys} and {out_keys}.")
        # two inputs written to one output would overwrite each other (an input may be its own output)
        check_distinct_keys({f"out_keys[{i}]": k for i, k in enumerate(out_keys)}, "RAMToFloat")
        super().__init__(in_keys=in_keys, out_keys=out_keys)

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        return obs.to(torch.float32) / 255.0

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            spec = observation_spec[in_key]
            observation_spec[out_key] = Bounded(0.0, 1.0, shape=spec.shape, dtype=torch.float32, device=spec.device)
        return observation_spec


def _env_id(game: str) -> str:
    if game.startswith("ALE/"):
        return game
    return f"ALE/{game}-v5"


def make_atari_ram_env(
    game: str = "Seaquest",
    *,
    frame_skip: int | tuple[int, int] = 4,
    repeat_action_probability: float = 0.25,
    noop_max: int = 30,
    episodic_life: bool = False,
    clip_rewards: bool = True,
    max_episode_steps: int | None = None,
    ram_encoding: str = "bytes",
    full_action_space: bool = False,
    render: bool = False,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    num_envs: int = 1,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """An Atari game with its RAM as observation, as a TorchRL env.

    ``GymEnv("ALE/<game>-v5", obs_type="ram")`` (through :class:`~torchrl.envs.GymWrapper`) followed by
    ``NoopResetEnv`` (random no-op starts), ``RewardClipping`` (rewards clipped to [-1, 1]), the observation
    encoding, ``StepCounter`` (the step limit) and ``RewardSum`` (``"episode_reward"``, the unclipped return when
    ``clip_rewards=False``; with clipping, the clipped one).

    Args:
        game (str): ``"Seaquest"`` (``ALE/Seaquest-v5``), ``"SpaceInvaders"``, ... or a full ``"ALE/..."`` id.

    Keyword Args:
        frame_skip (int or (int, int)): ALE's own frame skip (``frameskip``; ALE v5 default 4). One env step is this
            many frames; a pair ``(low, high)`` draws it uniformly in ``low .. high - 1`` at every step (``(2, 5)``:
            the authors' gym ``-ram-v0``, see :data:`PAPER_ENV_SETTINGS`).
        repeat_action_probability (float): ALE sticky actions: with this probability the emulator repeats the
            previous action instead of the chosen one (v5 default 0.25). The authors' gym ``-ram-v0`` envs had 0.25
            too (:data:`PAPER_ENV_SETTINGS`); 0 makes the emulator deterministic given the actions, which no-op
            starts then randomise.
        noop_max (int): up to this many random no-op steps after each reset (0 disables).
        episodic_life (bool): end the episode at the loss of a life (see :class:`EpisodicLife`).
        clip_rewards (bool): clip rewards to [-1, 1].
        max_episode_steps (int, optional): truncate episodes after this many env steps.
        ram_encoding (str): ``"bytes"`` (float32 ``bytes / 255``, default) or ``"uint8"`` (the raw bytes).
        full_action_space (bool): all 18 actions instead of the game's minimal set.
        render (bool): make ``render()`` return RGB frames (``render_mode="rgb_array"``), for videos.
        seed (int, optional): seeds the env.
        device: device of the env's outputs.
        num_envs (int): with more than one, a batch of ``num_envs`` games in one gymnasium ``SyncVectorEnv``
            (auto-reset disabled, so TorchRL resets each game on its own when it is done) with batch size
            ``[num_envs]``. The TorchRL transforms then run once per step for the whole batch instead of once per
            game, which is about twice the env steps/s of one game at a time on one core (``SerialEnv`` adds
            little: ``benchmarks/bench_atari_envs.py``). No-op starts and end-of-life are gymnasium wrappers of
            each game (:class:`NoopStart`, :class:`EpisodicLife`); with ``seed``, game ``i`` is seeded
            ``seed + i``.
        **gym_kwargs: more keyword arguments of ``gymnasium.make``.

    Examples:
        >>> from torchrl_options.envs.atari import make_atari_ram_env  # doctest: +SKIP
        >>> env = make_atari_ram_env("Seaquest", max_episode_steps=100, seed=0)  # doctest: +SKIP
        >>> env.rollout(10)["observation"].shape, env.action_spec.n  # doctest: +SKIP
        (torch.Size([10, 128]), 18)
    """
    if not atari_available():
        raise ImportError("Atari envs need ale-py: pip install 'torchrl-options[atari]'.")
    if isinstance(frame_skip, list):
        frame_skip = tuple(frame_skip)
    if isinstance(frame_skip, tuple):
        ok = len(frame_skip) == 2 and all(isinstance(f, int) and not isinstance(f, bool) for f in frame_skip)
        if not ok or not 1 <= frame_skip[0] < frame_skip[1]:
            raise ValueError(f"frame_skip must be an int >= 1 or a pair (low, high) with 1 <= low < high, got {frame_skip!r}.")
    elif isinstance(frame_skip, bool) or not isinstance(frame_skip, int) or frame_skip < 1:
        raise ValueError(f"frame_skip must be an int >= 1 or a pair (low, high) with 1 <= low < high, got {frame_skip!r}.")
    if ram_encoding not in ("bytes", "uint8"):
        raise ValueError(f"ram_encoding must be 'bytes' or 'uint8', got {ram_encoding!r}.")
    if not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive int, got {num_envs!r}.")
    if not isinstance(game, str) or not game:
        raise TypeError(f"game must be a game name such as 'Seaquest' (or an 'ALE/...' id), got {game!r}.")
    check_number(repeat_action_probability, "repeat_action_probability", lo=0.0, hi=1.0)
    check_int(noop_max, "noop_max", minimum=0)
    check_int(max_episode_steps, "max_episode_steps", minimum=1, allow_none=True)
    for name, flag in (("episodic_life", episodic_life), ("clip_rewards", clip_rewards),
                       ("full_action_space", full_action_space), ("render", render)):  # fmt: skip
        check_bool(flag, name)
    if num_envs > 1 and render:
        raise ValueError("render=True needs num_envs=1.")
    import ale_py

    gym.register_envs(ale_py)

    def make_game(vectorized: bool) -> gym.Env:
        try:
            game_env = gym.make(
                _env_id(game),
                obs_type="ram",
                frameskip=frame_skip,
                repeat_action_probability=repeat_action_probability,
                full_action_space=full_action_space,
                render_mode="rgb_array" if render else None,
                **gym_kwargs,
            )
        except gym.error.NameNotFound as err:  # e.g. "Chess": gymnasium suggests the right name
            raise ValueError(f"game {game!r}: no such Atari game ({_env_id(game)}): {err}") from None
        if episodic_life:
            game_env = EpisodicLife(game_env)
        if vectorized and noop_max > 0:
            game_env = NoopStart(game_env, noop_max)
        return game_env

    transforms = []
    if num_envs == 1:
        env = GymWrapper(make_game(False), categorical_action_encoding=True, device=device)
        if noop_max > 0:
            transforms.append(NoopResetEnv(noops=noop_max, random=True))
    else:
        vector_env = gym.vector.SyncVectorEnv(
            [partial(make_game, True) for _ in range(num_envs)], autoreset_mode=gym.vector.AutoresetMode.DISABLED
        )
        env = GymWrapper(vector_env, categorical_action_encoding=True, device=device)
    if clip_rewards:
        transforms.append(RewardClipping(-1.0, 1.0))
    if ram_encoding == "bytes":
        transforms.append(RAMToFloat())
    transforms.append(StepCounter(max_steps=max_episode_steps))
    transforms.append(RewardSum())
    env = TransformedEnv(env, Compose(*transforms))
    if seed is not None:
        env.set_seed(seed)
    return env


def _as_bytes(x: torch.Tensor) -> torch.Tensor:
    if x.dtype == torch.uint8:
        return x.long()
    if x.is_floating_point():
        return (x * 255.0).round().clamp_(0, 255).long()
    return x.long().clamp(0, 255)


class RAMOneHotEncoder(nn.Module):
    """The paper's one-hot RAM encoding (128 bytes x 256 values) followed by a linear layer, without the one-hot.

    ``W @ one_hot(ram) + b`` picks one column of ``W`` per byte: it equals ``sum_i E[i * 256 + ram_i] + b``, an
    ``nn.EmbeddingBag`` with ``mode="sum"``. Accepts raw uint8 bytes or float ``bytes / 255``.

    Args:
        out_features (int): size of the output.

    Keyword Args:
        num_bytes (int): RAM size (128).
        bias (bool): add a bias.

    Examples:
        >>> import torch
        >>> enc = RAMOneHotEncoder(8, num_bytes=4)
        >>> ram = torch.tensor([[0, 255, 3, 7]], dtype=torch.uint8)
        >>> one_hot = torch.nn.functional.one_hot(ram.long(), 256).flatten(-2).float()  # [1, 4 * 256]
        >>> torch.allclose(enc(ram), one_hot @ enc.weight + enc.bias)
        True
        >>> torch.allclose(enc(ram.float() / 255), enc(ram))  # bytes / 255 gives the same result
        True
    """

    def __init__(self, out_features: int, *, num_bytes: int = RAM_SIZE, bias: bool = True):
        super().__init__()
        check_int(out_features, "out_features", minimum=1)
        check_int(num_bytes, "num_bytes", minimum=1)
        check_bool(bias, "bias")
        self.num_bytes = num_bytes
        self.out_features = out_features
        self.embedding = nn.EmbeddingBag(num_bytes * 256, out_features, mode="sum")
        # the scale of nn.Linear's default init on a 128-hot input
        nn.init.uniform_(self.embedding.weight, -1.0 / num_bytes**0.5, 1.0 / num_bytes**0.5)
        self.bias = nn.Parameter(torch.zeros(out_features)) if bias else None
        self.register_buffer("offsets", torch.arange(num_bytes) * 256, persistent=False)

    @property
    def weight(self) -> torch.Tensor:
        """The equivalent linear layer's weight, ``[num_bytes * 256, out_features]``."""
        return self.embedding.weight

    def forward(self, ram: torch.Tensor) -> torch.Tensor:
        batch = ram.shape[:-1]
        idx = _as_bytes(ram).reshape(-1, self.num_bytes) + self.offsets
        out = self.embedding(idx).reshape(*batch, self.out_features)
        return out if self.bias is None else out + self.bias


class RAMBytesEncoder(nn.Module):
    """``bytes / 255`` followed by a linear layer (accepts uint8 bytes or floats already scaled).

    Examples:
        >>> import torch
        >>> enc = RAMBytesEncoder(8, num_bytes=4)
        >>> ram = torch.tensor([[0, 255, 3, 7]], dtype=torch.uint8)
        >>> torch.allclose(enc(ram), enc(ram.float() / 255))
        True
    """

    def __init__(self, out_features: int, *, num_bytes: int = RAM_SIZE):
        super().__init__()
        check_int(out_features, "out_features", minimum=1)
        check_int(num_bytes, "num_bytes", minimum=1)
        self.linear = nn.Linear(num_bytes, out_features)

    def forward(self, ram: torch.Tensor) -> torch.Tensor:
        x = ram.to(torch.float32) / 255.0 if not ram.is_floating_point() else ram
        return self.linear(x)


def ram_q_network(
    num_actions: int,
    *,
    encoding: str = "bytes",
    num_cells: tuple[int, ...] | list[int] = (64, 64, 64),
    activation: type[nn.Module] = nn.Tanh,
    num_bytes: int = RAM_SIZE,
) -> nn.Sequential:
    """A Q-network on RAM: the encoding layer (one-hot or bytes) as first dense layer, then dense tanh layers.

    The paper's policies: three dense tanh layers. ``num_cells`` gives the widths of the hidden layers (the
    first one is the encoder's output).

    Examples:
        >>> import torch
        >>> net = ram_q_network(6, encoding="one_hot", num_cells=[16, 16, 16])
        >>> net(torch.randint(0, 256, (2, 128), dtype=torch.uint8)).shape
        torch.Size([2, 6])
    """
    check_int(num_actions, "num_actions", minimum=1)
    if isinstance(num_cells, (str, bytes)) or not isinstance(num_cells, (tuple, list)):
        raise TypeError(f"num_cells must be a list of layer widths, got {num_cells!r}.")
    cells = list(num_cells)
    if not cells:
        raise ValueError("num_cells needs at least one layer.")
    for i, c in enumerate(cells):
        check_int(c, f"num_cells[{i}]", minimum=1)
    if encoding == "one_hot":
        first: nn.Module = RAMOneHotEncoder(cells[0], num_bytes=num_bytes)
    elif encoding == "bytes":
        first = RAMBytesEncoder(cells[0], num_bytes=num_bytes)
    else:
        raise ValueError(f"encoding must be 'bytes' or 'one_hot', got {encoding!r}.")
    layers: list[nn.Module] = [first, activation()]
    for a, b in zip(cells[:-1], cells[1:]):
        layers += [nn.Linear(a, b), activation()]
    layers.append(nn.Linear(cells[-1], num_actions))
    return nn.Sequential(*layers)


def render_frame(env: EnvBase) -> np.ndarray:
    """The current RGB screen of an env made with ``make_atari_ram_env(..., render=True)`` (or any batched or
    transformed wrapper of it)."""
    if not isinstance(env, EnvBase):
        raise TypeError(f"render_frame expects a TorchRL env (from make_atari_ram_env(..., render=True)), got {type(env).__name__}.")
    base = env
    while hasattr(base, "base_env"):
        base = base.base_env
    if not hasattr(base, "_env") or not hasattr(base._env, "render"):
        raise ValueError(f"render_frame: {type(base).__name__} wraps no gymnasium env to render.")
    return np.asarray(base._env.render())


__all__ += ["EpisodicLife", "RAMToFloat", "ram_q_network", "render_frame"]
