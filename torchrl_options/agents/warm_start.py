"""Warm-starting a DQN over actions + options from a trained DQN over actions only.

Fox et al., 2017 ("Multi-Level Discovery of Deep Options", section 5) restart the Q-function when they augment
the action space with the discovered options. A user who already has a trained agent may rather keep what it
learned: copy its network (its output layer widened by one row per option), its target network and its replay
buffer, and continue with the options added. The new rows start as the mean of the primitive rows, so that at
the start ``Q(s, option) = mean_a Q(s, a)`` in every state: the options are neither preferred nor ignored before
the agent has tried them.
"""
from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_int, check_nested_key

__all__ = ["widen_action_rows", "widen_action_values"]


def widen_action_rows(
    source: Mapping[str, torch.Tensor], target: Mapping[str, torch.Tensor], num_actions: int
) -> dict[str, torch.Tensor]:
    """Fills the state dict ``target`` from ``source``, whose output layer has ``num_actions`` rows fewer.

    Every tensor of ``target`` is copied from the tensor of the same name in ``source``. A tensor whose first
    dimension is ``num_actions`` in ``source`` and larger in ``target`` (the output layer's weight and bias of a
    network over the augmented action space, primitive actions first) keeps the source rows first and fills the
    new rows with the mean of the source rows, so that each new output starts at the mean of the old outputs.

    Args:
        source (Mapping[str, torch.Tensor]): state dict of the network (or loss module) over actions only.
        target (Mapping[str, torch.Tensor]): state dict of the same architecture over actions + options.
        num_actions (int): number of primitive actions, the output width of ``source``.

    Returns:
        A new state dict with the keys and shapes of ``target``.

    Raises:
        KeyError: a key of ``target`` missing from ``source``.
        ValueError: a tensor whose shapes differ in any other way.

    Examples:
        >>> import torch
        >>> old, new = torch.nn.Linear(3, 2), torch.nn.Linear(3, 4)
        >>> state = widen_action_rows(old.state_dict(), new.state_dict(), num_actions=2)
        >>> _ = new.load_state_dict(state)
        >>> x = torch.randn(5, 3)
        >>> torch.allclose(new(x)[:, :2], old(x)), torch.allclose(new(x)[:, 2:], old(x).mean(-1, keepdim=True).expand(5, 2))
        (True, True)
    """
    for name, value in (("source", source), ("target", target)):
        if not isinstance(value, Mapping):
            raise TypeError(f"widen_action_rows: {name} must be a state dict (a mapping of tensors), got {type(value).__name__}.")
    check_int(num_actions, "num_actions", minimum=1)
    out = {}
    for key, t in target.items():
        if key not in source:
            raise KeyError(f"widen_action_rows: the source state dict has no {key!r} (expected the same architecture).")
        s = source[key]
        if s.shape == t.shape:
            out[key] = s.detach().clone().to(t.dtype)
        elif s.ndim == t.ndim and s.ndim >= 1 and s.shape[0] == num_actions and t.shape[0] > num_actions and s.shape[1:] == t.shape[1:]:
            extra = s.detach().mean(0, keepdim=True).expand(t.shape[0] - num_actions, *s.shape[1:])
            out[key] = torch.cat([s.detach(), extra], 0).to(t.dtype)
        else:
            raise ValueError(
                f"widen_action_rows: {key!r} has shape {tuple(s.shape)} in the source and {tuple(t.shape)} in the "
                f"target; only the output rows may differ, from num_actions={num_actions} to more."
            )
    return out


def widen_action_values(data: TensorDictBase, num_outputs: int, key: NestedKey = "action_value") -> TensorDictBase:
    """Pads the recorded ``key`` ``[..., A]`` of stored transitions to ``[..., num_outputs]`` in place.

    The new entries are the mean of the recorded ones: what a network widened by :func:`widen_action_rows` gives
    for the new outputs. (``DQNLoss`` recomputes action values from the network; this keeps the stored
    transitions consistent with the ones the widened agent adds.) A ``data`` without ``key`` is returned as is.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict(action_value=torch.tensor([[1.0, 3.0]]), batch_size=[1])
        >>> widen_action_values(td, 4)["action_value"]
        tensor([[1., 3., 2., 2.]])
    """
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"widen_action_values: data must be a TensorDict of transitions, got {type(data).__name__}.")
    check_int(num_outputs, "num_outputs", minimum=1)
    key = check_nested_key(key, "key", "widen_action_values")
    value = data.get(key, None)
    if value is None:
        return data
    a = value.shape[-1]
    if a > num_outputs:
        raise ValueError(f"widen_action_values: {key!r} has {a} entries, more than num_outputs={num_outputs}.")
    if a < num_outputs:
        extra = value.mean(-1, keepdim=True).expand(*value.shape[:-1], num_outputs - a)
        data.set(key, torch.cat([value, extra], -1))
    return data
