"""MiniGrid levels as TorchRL envs (torchrl_options.envs.minigrid): the one-hot view transform, specs on single and
batched envs, seeding."""
from functools import partial

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.utils import check_env_specs

from torchrl_options.envs.minigrid import (
    DIRECTIONS,
    MiniGridOneHot,
    minigrid_available,
    NUM_COLORS,
    NUM_OBJECT_TYPES,
    NUM_STATES,
    observation_size,
    one_hot_view,
    VIEW_CHANNELS,
    view_from_observation,
)

needs_minigrid = pytest.mark.skipif(not minigrid_available(), reason="needs minigrid (the minigrid extra)")
LEVEL = "MiniGrid-DoorKey-5x5-v0"


@needs_minigrid
def test_constants_match_the_installed_minigrid():
    from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX

    assert (NUM_OBJECT_TYPES, NUM_COLORS, NUM_STATES) == (len(OBJECT_TO_IDX), len(COLOR_TO_IDX), len(STATE_TO_IDX))
    assert max(OBJECT_TO_IDX.values()) == NUM_OBJECT_TYPES - 1 and max(COLOR_TO_IDX.values()) == NUM_COLORS - 1


def test_one_hot_view_is_one_hot_per_field_and_round_trips():
    g = torch.Generator().manual_seed(0)
    image = torch.stack([torch.randint(0, n, (4, 7, 7), generator=g) for n in (11, 6, 3)], -1).to(torch.uint8)
    view = one_hot_view(image)
    assert view.shape == (4, VIEW_CHANNELS, 7, 7)
    assert torch.equal(view.sum(-3), torch.full((4, 7, 7), 3.0))  # one channel per field is hot
    decoded = torch.stack([view[:, :11].argmax(1), view[:, 11:17].argmax(1), view[:, 17:].argmax(1)], -1)
    assert torch.equal(decoded, image.long())
    with pytest.raises(ValueError, match="object type index outside 0..10: 11"):
        one_hot_view(torch.full((7, 7, 3), 11, dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"\[..., W, H, 3\]"):
        one_hot_view(torch.zeros(7, 7, 2, dtype=torch.uint8))


def test_transform_writes_the_flat_observation_and_splits_back():
    image = torch.zeros(2, 7, 7, 3, dtype=torch.uint8)
    image[1, 3, 6] = torch.tensor([5, 4, 0])  # a yellow key in the agent's own cell: it carries it
    td = TensorDict(image=image, direction=torch.tensor([2, 3]), batch_size=[2])
    out = MiniGridOneHot()._call(td.clone())
    assert set(out.keys()) == {"observation"}  # the raw entries are removed
    obs = out["observation"]
    assert obs.shape == (2, observation_size()) and obs.dtype == torch.float32
    view, direction = view_from_observation(obs)
    assert direction.argmax(-1).tolist() == [2, 3] and direction.sum(-1).tolist() == [1.0, 1.0]
    assert torch.equal(view, one_hot_view(image))
    assert view[1, 5, 3, 6] == 1 and view[0, 5, 3, 6] == 0
    kept = MiniGridOneHot(keep_raw=True)._call(td.clone())
    assert {"image", "direction", "observation"} <= set(kept.keys())
    with pytest.raises(ValueError, match="direction must be in 0..3"):
        MiniGridOneHot()._call(TensorDict(image=image, direction=torch.tensor([0, 4]), batch_size=[2]))
    with pytest.raises(KeyError, match="'direction'"):
        MiniGridOneHot()._call(TensorDict(image=image, batch_size=[2]))
    with pytest.raises(ValueError, match="984 features"):
        view_from_observation(torch.zeros(3, 10))


def test_transform_refuses_bad_keys():
    with pytest.raises(TypeError, match="keep_raw"):
        MiniGridOneHot(keep_raw=1)
    with pytest.raises(ValueError, match="out_key"):
        MiniGridOneHot(out_key="image")


@needs_minigrid
def test_env_specs_single_serial_parallel_and_seeding():
    from torchrl_options.envs.minigrid import make_minigrid_env

    env = make_minigrid_env(LEVEL)
    check_env_specs(env)
    assert env.action_spec.n == 7 and env.observation_spec["observation"].shape == (observation_size(),)
    a = env.reset(seed=3)["observation"]
    b = env.reset(seed=3)["observation"]
    c = env.reset(seed=4)["observation"]
    assert torch.equal(a, b) and a.sum() == 7 * 7 * 3 + 1
    rollout = env.rollout(6, break_when_any_done=False)
    assert rollout["next", "observation"].shape == (6, observation_size())
    assert a.shape == c.shape
    factory = partial(make_minigrid_env, LEVEL)
    serial = SerialEnv(2, factory)
    check_env_specs(serial)
    assert serial.rollout(3)["observation"].shape == (2, 3, observation_size())
    serial.close()
    parallel = ParallelEnv(2, factory)
    try:
        check_env_specs(parallel)
    finally:
        parallel.close()


@needs_minigrid
def test_bad_level_is_refused_by_name():
    from torchrl_options.envs.minigrid import make_minigrid_env

    with pytest.raises(ValueError, match="registered MiniGrid/BabyAI id.*'MiniGrid-Nope-v0'"):
        make_minigrid_env("MiniGrid-Nope-v0")


def test_observation_size():
    assert observation_size(7) == 20 * 49 + DIRECTIONS
