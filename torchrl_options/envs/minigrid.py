"""MiniGrid and BabyAI levels (Farama's ``minigrid`` package) as TorchRL envs with a one-hot egocentric view.

MiniGrid (Chevalier-Boisvert et al., 2023) is a suite of discrete, partially observed, sparse-reward grid tasks;
its BabyAI levels (Chevalier-Boisvert et al., 2019) come with an expert planner, the BabyAI bot, whose subgoals
are a ground truth for segmentation (:mod:`torchrl_options.experiments.minigrid`). Two pieces live here:

- :func:`make_minigrid_env`: ``gymnasium.make(level)`` with the mission string filtered out (gymnasium's
  ``FilterObservation``: a text space has no TorchRL spec, and the levels used here have one mission per level),
  wrapped by TorchRL's :class:`~torchrl.envs.GymWrapper` (what ``GymEnv`` builds from a name), then
  :class:`MiniGridOneHot`.
- :class:`MiniGridOneHot`: a TorchRL transform writing ``"observation"``, a flat float vector: the agent's
  ``image`` view (``view x view`` cells of ``(object type, colour, state)``) one-hot encoded channels-first
  (:data:`NUM_OBJECT_TYPES` + :data:`NUM_COLORS` + :data:`NUM_STATES` = :data:`VIEW_CHANNELS` channels), then
  the agent's ``direction`` one-hot (4). With the default 7 x 7 view that is ``20 * 49 + 4 = 984`` features.
  MiniGrid draws the carried object in the agent's own cell of the view (the bottom middle one), so what the
  agent carries is part of the observation. A network that wants the grid back reshapes the first
  ``VIEW_CHANNELS * view * view`` features to ``[VIEW_CHANNELS, view, view]``
  (:func:`view_from_observation`; :class:`~torchrl_options.modules.GridConvOptions` does).

``minigrid`` is an optional dependency (``pip install 'torchrl-options[minigrid]'``), imported only when an env is
made: importing this module needs the core dependencies alone.
"""
from __future__ import annotations

import importlib.util
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite
from torchrl.envs import GymWrapper, Transform, TransformedEnv

__all__ = [
    "DIRECTIONS",
    "MINIGRID_ACTIONS",
    "MiniGridOneHot",
    "NUM_COLORS",
    "NUM_OBJECT_TYPES",
    "NUM_STATES",
    "VIEW_CHANNELS",
    "make_minigrid_env",
    "make_minigrid_gym",
    "minigrid_available",
    "observation_size",
    "one_hot_view",
    "view_from_observation",
]

#: MiniGrid's object types (``minigrid.core.constants.OBJECT_TO_IDX``: unseen, empty, wall, floor, door, key, ball,
#: box, goal, lava, agent), colours (``COLOR_TO_IDX``: red, green, blue, purple, yellow, grey) and door states
#: (``STATE_TO_IDX``: open, closed, locked); the tests check them against the installed package.
NUM_OBJECT_TYPES = 11
NUM_COLORS = 6
NUM_STATES = 3
VIEW_CHANNELS = NUM_OBJECT_TYPES + NUM_COLORS + NUM_STATES
DIRECTIONS = 4

#: MiniGrid's seven actions, by index.
MINIGRID_ACTIONS = ("left", "right", "forward", "pickup", "drop", "toggle", "done")


def minigrid_available() -> bool:
    """Whether ``minigrid`` (the ``minigrid`` extra) is installed."""
    return importlib.util.find_spec("minigrid") is not None


def _require_minigrid() -> None:
    if not minigrid_available():
        raise ImportError("MiniGrid envs need the minigrid package: pip install 'torchrl-options[minigrid]'.")
    import minigrid  # noqa: F401  (registers the MiniGrid-* and BabyAI-* ids with gymnasium)


def observation_size(view_size: int = 7) -> int:
    """The length of :class:`MiniGridOneHot`'s ``"observation"`` for a ``view_size x view_size`` view.

    Examples:
        >>> observation_size(), observation_size(3)
        (984, 184)
    """
    return VIEW_CHANNELS * view_size * view_size + DIRECTIONS


def one_hot_view(image: torch.Tensor) -> torch.Tensor:
    """MiniGrid's ``image`` ``[..., W, H, 3]`` (object type, colour, state per cell) as a channels-first one-hot
    float tensor ``[..., VIEW_CHANNELS, W, H]``: channels ``0..10`` the object type, ``11..16`` the colour,
    ``17..19`` the state.

    Raises:
        ValueError: when the last dimension is not 3 or a value is outside its range (a corrupt observation).

    Examples:
        >>> import torch
        >>> image = torch.zeros(2, 2, 3, dtype=torch.uint8)
        >>> image[0, 1] = torch.tensor([5, 4, 0])  # a yellow key
        >>> view = one_hot_view(image)
        >>> view.shape, view[:, 0, 1].nonzero().flatten().tolist()
        (torch.Size([20, 2, 2]), [5, 15, 17])
    """
    if image.shape[-1] != 3:
        raise ValueError(f"image must be [..., W, H, 3] (object type, colour, state), got shape {tuple(image.shape)}.")
    x = image.long()
    bounds = (NUM_OBJECT_TYPES, NUM_COLORS, NUM_STATES)
    for i, (name, n) in enumerate(zip(("object type", "colour", "state"), bounds)):
        v = x[..., i]
        if bool(((v < 0) | (v >= n)).any()):
            raise ValueError(f"image holds a {name} index outside 0..{n - 1}: {int(v[(v < 0) | (v >= n)][0])}.")
    parts = [torch.nn.functional.one_hot(x[..., i], n) for i, n in enumerate(bounds)]
    return torch.cat(parts, -1).movedim(-1, -3).to(torch.float32)


def view_from_observation(observation: torch.Tensor, view_size: int = 7) -> tuple[torch.Tensor, torch.Tensor]:
    """Splits :class:`MiniGridOneHot`'s flat ``"observation"`` into the one-hot view ``[..., VIEW_CHANNELS, view,
    view]`` and the one-hot direction ``[..., 4]``.

    Examples:
        >>> import torch
        >>> view, direction = view_from_observation(torch.zeros(5, observation_size()))
        >>> view.shape, direction.shape
        (torch.Size([5, 20, 7, 7]), torch.Size([5, 4]))
    """
    n = VIEW_CHANNELS * view_size * view_size
    if observation.shape[-1] != n + DIRECTIONS:
        raise ValueError(
            f"observation must have {n + DIRECTIONS} features (a {view_size}x{view_size} one-hot view and the direction), "
            f"got {observation.shape[-1]}."
        )
    view = observation[..., :n].unflatten(-1, (VIEW_CHANNELS, view_size, view_size))
    return view, observation[..., n:]


class MiniGridOneHot(Transform):
    """Writes ``"observation"``: the one-hot ``image`` view (channels-first, flattened) and the one-hot
    ``direction``, float32 in {0, 1} (see the module docstring); removes ``image`` and ``direction`` unless
    ``keep_raw``.

    Runs on single and batched envs alike (any leading batch dimensions).

    Keyword Args:
        image_key (NestedKey): MiniGrid's view. Defaults to ``"image"``.
        direction_key (NestedKey): the agent's direction (0-3). Defaults to ``"direction"``.
        out_key (NestedKey): the encoded observation. Defaults to ``"observation"``.
        keep_raw (bool): keep ``image`` and ``direction`` in the data. Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> t = MiniGridOneHot()
        >>> td = TensorDict(image=torch.ones(3, 7, 7, 3, dtype=torch.uint8), direction=torch.tensor([0, 1, 3]),
        ...                 batch_size=[3])
        >>> obs = t._call(td)["observation"]
        >>> obs.shape, obs.sum(-1).tolist()  # three ones per cell, one for the direction
        (torch.Size([3, 984]), [148.0, 148.0, 148.0])
    """

    def __init__(
        self,
        *,
        image_key: NestedKey = "image",
        direction_key: NestedKey = "direction",
        out_key: NestedKey = "observation",
        keep_raw: bool = False,
    ) -> None:
        from torchrl_options.checks import check_bool, check_distinct_keys

        keys = check_distinct_keys(
            {"image_key": image_key, "direction_key": direction_key, "out_key": out_key}, "MiniGridOneHot"
        )
        image_key, direction_key, out_key = keys["image_key"], keys["direction_key"], keys["out_key"]
        check_bool(keep_raw, "keep_raw")
        super().__init__(in_keys=[image_key, direction_key], out_keys=[out_key])
        self.keep_raw = keep_raw

    def _encode(self, image: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        view = one_hot_view(image).flatten(-3)
        d = direction.long().reshape(image.shape[:-3])
        if bool(((d < 0) | (d >= DIRECTIONS)).any()):
            raise ValueError(f"direction must be in 0..3, got {d.reshape(-1).tolist()[:5]}.")
        return torch.cat([view, torch.nn.functional.one_hot(d, DIRECTIONS).to(view.dtype)], -1)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        image_key, direction_key = self.in_keys
        image = next_tensordict.get(image_key, None)
        direction = next_tensordict.get(direction_key, None)
        if image is None or direction is None:
            missing = image_key if image is None else direction_key
            raise KeyError(f"MiniGridOneHot reads {missing!r}, which the env's output lacks.")
        next_tensordict.set(self.out_keys[0], self._encode(image, direction))
        if not self.keep_raw:
            next_tensordict = next_tensordict.exclude(image_key, direction_key, inplace=True)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        image_key, direction_key = self.in_keys
        image = observation_spec[image_key]
        if image.shape[-1] != 3 or image.shape[-2] != image.shape[-3]:
            raise ValueError(f"{image_key!r} must be a square [view, view, 3] MiniGrid image, got {tuple(image.shape)}.")
        view = int(image.shape[-2])
        batch = image.shape[:-3]
        observation_spec[self.out_keys[0]] = Bounded(
            0.0, 1.0, shape=(*batch, observation_size(view)), dtype=torch.float32, device=image.device
        )
        if not self.keep_raw:
            del observation_spec[image_key]
            del observation_spec[direction_key]
        return observation_spec


def make_minigrid_gym(level: str, *, seed: int | None = None, **gym_kwargs: Any):
    """The gymnasium env of a level without its mission string (``FilterObservation`` to ``image`` and
    ``direction``): what :func:`make_minigrid_env` wraps, and what the BabyAI bot plans on.

    Args:
        level (str): a registered MiniGrid or BabyAI id, e.g. ``"BabyAI-UnlockPickup-v0"``.

    Keyword Args:
        seed (int, optional): resets the env once with this seed.
        **gym_kwargs: keyword arguments of ``gymnasium.make`` (``max_steps=...``, ...).
    """
    _require_minigrid()
    import gymnasium as gym
    from gymnasium.wrappers import FilterObservation

    if not isinstance(level, str) or level not in gym.registry:
        known = sorted(k for k in gym.registry if k.startswith(("BabyAI-", "MiniGrid-")))
        raise ValueError(f"level must be a registered MiniGrid/BabyAI id (e.g. {known[:3]}), got {level!r}.")
    env = FilterObservation(gym.make(level, **gym_kwargs), ["image", "direction"])
    if seed is not None:
        env.reset(seed=seed)
    return env


def make_minigrid_env(
    level: str = "BabyAI-UnlockPickup-v0",
    *,
    seed: int | None = None,
    keep_raw: bool = False,
    device: torch.device | str = "cpu",
    gym_env=None,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """A MiniGrid or BabyAI level as a TorchRL env: ``GymWrapper`` of :func:`make_minigrid_gym` with
    :class:`MiniGridOneHot`; a ``Categorical(7)`` action (:data:`MINIGRID_ACTIONS`), a flat float
    ``"observation"`` (984 features with the 7 x 7 view), MiniGrid's sparse reward (``1 - 0.9 * steps /
    max_steps`` on success, 0 otherwise) and its own step limit (``truncated``).

    Args:
        level (str): a registered id, e.g. ``"BabyAI-UnlockPickup-v0"`` or ``"MiniGrid-DoorKey-5x5-v0"``.

    Keyword Args:
        seed (int, optional): seeds the env (``set_seed``).
        keep_raw (bool): keep ``image`` and ``direction`` next to ``"observation"``.
        device: the device of the env's outputs.
        gym_env (optional): a gymnasium env from :func:`make_minigrid_gym` to wrap instead of making one (to keep
            a handle on it, e.g. for the BabyAI bot).
        **gym_kwargs: keyword arguments of ``gymnasium.make`` (``max_steps=...``).

    Examples:
        >>> from torchrl_options.envs.minigrid import make_minigrid_env  # doctest: +SKIP
        >>> env = make_minigrid_env("MiniGrid-DoorKey-5x5-v0", seed=0)  # doctest: +SKIP
        >>> env.rollout(4)["observation"].shape, env.action_spec.n  # doctest: +SKIP
        (torch.Size([4, 984]), 7)
    """
    from torchrl_options.checks import check_bool

    check_bool(keep_raw, "keep_raw")
    if gym_env is None:
        gym_env = make_minigrid_gym(level, **gym_kwargs)
    elif gym_kwargs:
        raise ValueError(f"gym_kwargs {sorted(gym_kwargs)} cannot apply to a given gym_env.")
    env = TransformedEnv(
        GymWrapper(gym_env, categorical_action_encoding=True, device=device), MiniGridOneHot(keep_raw=keep_raw)
    )
    if seed is not None:
        env.set_seed(seed)
    return env

