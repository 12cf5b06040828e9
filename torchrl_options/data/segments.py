"""Hindsight segments of an agent's own experience: the stretches of its rollouts that end in a reward.

Options discovered from an agent's own rollouts (the exploration setting of Fox et al., 2017, "Multi-Level
Discovery of Deep Options", section 5.1, and the whole protocol of its Atari experiment) can only be as good as
the behaviour in those rollouts. A weak agent's rollouts mostly wander: in the four-rooms exploration setting the
pre-trained DQN's greedy policy circles 14 cells of 156 for 1000 steps and takes 0.34 apples, where its own
epsilon-greedy policy takes 4 apples in as many steps (``docs/experiments/gridworld.md``). The steps that led to a
reward are the skill the rollouts hold: :func:`rewarded_segments` cuts every rollout after each rewarded step and
keeps the pieces that end in a reward (the unrewarded tail of each rollout is dropped), as trajectories in the
package's layout, ready for :func:`~torchrl_options.discover_options`. Each piece starts a new option (DDO's
``b_0 = 1``), which is where a reward ends one skill and the next begins.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_distinct_keys, check_int, check_number

__all__ = ["rewarded_segments"]


def rewarded_segments(
    rollouts: TensorDictBase,
    *,
    reward_key: NestedKey = ("next", "reward"),
    mask_key: NestedKey = ("collector", "mask"),
    min_reward: float = 0.0,
    min_length: int = 1,
) -> TensorDict:
    """The pieces of ``[B, T]`` rollouts that end in a rewarded step, as a padded ``[N, T']`` batch with a mask.

    A step is rewarded when its reward exceeds ``min_reward``. Each rollout is cut after each rewarded step; a piece
    runs from the step after the previous cut (or the rollout's first step) to the rewarded step, both included.
    Steps after a rollout's last reward, and invalid (masked) steps, are dropped. Pieces shorter than
    ``min_length`` steps are dropped too. Every entry of ``rollouts`` is carried over; the output's
    ``mask_key`` marks each piece's valid steps (left-aligned, padded with the piece's last step).

    Args:
        rollouts (TensorDictBase): ``[B, T]`` step data (``[T]``: one rollout) with ``reward_key`` and, optionally,
            ``mask_key`` (missing: every step valid). Valid steps must come first in each row.

    Keyword Args:
        reward_key (NestedKey): the per-step reward, shape ``[B, T]`` or ``[B, T, 1]``. Defaults to
            ``("next", "reward")``.
        mask_key (NestedKey): the valid-step mask. Defaults to ``("collector", "mask")``.
        min_reward (float): a step is rewarded when its reward is above this. Defaults to 0.
        min_length (int): the shortest piece kept, in steps. Defaults to 1.

    Returns:
        A ``[N, T']`` TensorDict, ``T'`` the longest piece, with ``mask_key`` set and ``"segment_source"`` (long
        ``[N, T']``, constant along a row): the row of ``rollouts`` each piece came from.

    Raises:
        ValueError: no rewarded step in ``rollouts`` (nothing to learn from), a bad key, or a bad setting.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> reward = torch.tensor([[0.0, 1.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]])
        >>> rollouts = TensorDict({"observation": torch.arange(12.0).reshape(2, 6, 1),
        ...                        "next": {"reward": reward.unsqueeze(-1)}}, [2, 6])
        >>> pieces = rewarded_segments(rollouts)
        >>> pieces["collector", "mask"].sum(-1).tolist()  # 0-1 and 2-4 of row 0, all of row 1
        [2, 3, 6]
        >>> pieces["observation"][1, :3, 0].tolist()
        [2.0, 3.0, 4.0]
    """
    if not isinstance(rollouts, TensorDictBase):
        raise TypeError(f"rollouts must be a [B, T] TensorDict, got {type(rollouts).__name__}.")
    keys = check_distinct_keys({"reward_key": reward_key, "mask_key": mask_key}, "rewarded_segments")
    check_number(min_reward, "min_reward")
    check_int(min_length, "min_length", minimum=1)
    if rollouts.ndim == 1:
        rollouts = rollouts.unsqueeze(0)
    if rollouts.ndim != 2 or rollouts.shape[-1] == 0:
        raise ValueError(f"rollouts must be [B, T] with T >= 1 (or one [T] rollout), got batch_size {list(rollouts.shape)}.")
    B, T = rollouts.shape
    reward = rollouts.get(keys["reward_key"], None)
    if reward is None:
        raise ValueError(f"rewarded_segments: rollouts have no {keys['reward_key']!r} entry (reward_key).")
    if reward.shape not in ((B, T), (B, T, 1)):
        raise ValueError(f"rewarded_segments: {keys['reward_key']!r} must have shape [{B}, {T}] or [{B}, {T}, 1], got {list(reward.shape)}.")
    reward = reward.reshape(B, T)
    mask = rollouts.get(keys["mask_key"], None)
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool, device=reward.device)
    elif mask.dtype != torch.bool or mask.reshape(B, -1).shape != (B, T):
        raise ValueError(f"rewarded_segments: the mask {keys['mask_key']!r} must be bool [{B}, {T}], got {mask.dtype} {list(mask.shape)}.")
    mask = mask.reshape(B, T)
    if not torch.isfinite(reward[mask]).all():
        raise ValueError(f"rewarded_segments: {keys['reward_key']!r} holds NaN or infinite rewards at valid steps.")
    rewarded = (reward > min_reward) & mask
    pieces: list[tuple[int, int, int]] = []  # (row, first step, last step)
    for row, ends in enumerate(rewarded.cpu().tolist()):
        start = 0
        for t, hit in enumerate(ends):
            if hit:
                if t - start + 1 >= min_length:
                    pieces.append((row, start, t))
                start = t + 1
    if not pieces:
        raise ValueError(
            f"rewarded_segments: no valid step of the {B} rollouts has a reward above {min_reward} (in {keys['reward_key']!r}), "
            f"or every rewarded piece is shorter than min_length={min_length}: there is no rewarded behaviour to keep."
        )
    longest = max(last - first + 1 for _, first, last in pieces)
    rows = torch.tensor([p[0] for p in pieces])
    first = torch.tensor([p[1] for p in pieces])
    length = torch.tensor([p[2] - p[1] + 1 for p in pieces])
    offset = torch.arange(longest)
    index = first[:, None] + torch.minimum(offset[None, :], (length - 1)[:, None])  # padded with the last step
    out = rollouts[rows[:, None], index]  # [N, T']
    out.set(keys["mask_key"], offset[None, :] < length[:, None])
    out.set("segment_source", rows[:, None].expand(-1, longest).clone())
    return out
