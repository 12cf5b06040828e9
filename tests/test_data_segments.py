"""rewarded_segments: the pieces of an agent's rollouts that end in a reward."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_options.data import rewarded_segments


def _rollouts(reward, mask=None):
    reward = torch.as_tensor(reward, dtype=torch.float32)
    B, T = reward.shape
    td = TensorDict({"observation": torch.arange(B * T, dtype=torch.float32).reshape(B, T, 1),
                     "action": torch.arange(B * T).reshape(B, T) % 4,
                     "next": {"reward": reward.unsqueeze(-1)}}, [B, T])
    if mask is not None:
        td.set(("collector", "mask"), torch.as_tensor(mask))
    return td


def test_pieces_end_at_each_reward_and_drop_the_tails():
    data = _rollouts([[0, 1, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0, 2]])
    pieces = rewarded_segments(data)
    mask = pieces["collector", "mask"]
    assert mask.sum(-1).tolist() == [2, 3, 7]
    assert pieces["segment_source"][:, 0].tolist() == [0, 0, 1]
    # every piece's valid steps are the rollout's, in order, and its last valid step is rewarded
    obs = pieces["observation"].squeeze(-1)
    assert obs[0, :2].tolist() == [0.0, 1.0] and obs[1, :3].tolist() == [2.0, 3.0, 4.0]
    assert obs[2, :7].tolist() == list(map(float, range(7, 14)))
    last = mask.sum(-1) - 1
    assert bool((pieces["next", "reward"].squeeze(-1)[torch.arange(3), last] > 0).all())
    # rewards inside a piece (before its end) are never above the threshold: each piece holds one reward
    inside = pieces["next", "reward"].squeeze(-1) * mask
    assert bool(((inside > 0).sum(-1) == 1).all())
    # padding repeats the last valid step
    assert bool((obs[0, 2:] == obs[0, 1]).all())


def test_mask_threshold_and_min_length():
    # row 0's reward at t=5 is masked out: not a piece; min_length drops the 1-step piece
    data = _rollouts([[1, 0, 0, 1, 0, 1], [0.5, 0, 0, 0, 0, 0]],
                     mask=[[True] * 5 + [False], [True] * 6])
    assert rewarded_segments(data)["collector", "mask"].sum(-1).tolist() == [1, 3, 1]
    assert rewarded_segments(data, min_length=2)["collector", "mask"].sum(-1).tolist() == [3]
    assert rewarded_segments(data, min_reward=0.5)["collector", "mask"].sum(-1).tolist() == [1, 3]


def test_one_rollout_and_nested_keys():
    data = _rollouts([[0, 0, 1, 0]])[0]
    data.set(("stats", "r"), data.get(("next", "reward")))
    pieces = rewarded_segments(data, reward_key=("stats", "r"))
    assert pieces.shape == torch.Size([1, 3])


@pytest.mark.parametrize(
    "kwargs, data, error, match",
    [
        ({}, _rollouts([[0, 0, 0]]), ValueError, "no valid step"),
        ({"min_length": 5}, _rollouts([[0, 1, 0]]), ValueError, "min_length=5"),
        ({"reward_key": "missing"}, _rollouts([[0, 1]]), ValueError, "no 'missing' entry"),
        ({"reward_key": 3}, _rollouts([[0, 1]]), TypeError, "reward_key must be a NestedKey"),
        ({"reward_key": "m", "mask_key": "m"}, _rollouts([[0, 1]]), ValueError, "both 'm'"),
        ({"min_length": 0}, _rollouts([[0, 1]]), ValueError, "min_length"),
        ({"min_reward": float("nan")}, _rollouts([[0, 1]]), ValueError, "min_reward"),
        ({}, _rollouts([[0, float("nan")]]), ValueError, "NaN"),
        ({}, _rollouts([[0, 1]], mask=[[1, 1]]), ValueError, "must be bool"),
        ({}, "not a tensordict", TypeError, "rollouts must be"),
    ],
)
def test_bad_input_is_refused_at_the_door(kwargs, data, error, match):
    with pytest.raises(error, match=match):
        rewarded_segments(data, **kwargs)
