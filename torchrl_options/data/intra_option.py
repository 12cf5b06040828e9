"""One-step transitions of the primitive actions that options took (intra-option learning of primitive actions).

While an option runs, the agent makes no decision, so the decision-level transitions of
:mod:`torchrl_options.data.smdp` teach its Q-function nothing about the primitive actions taken on those steps. Yet
every such step ``(s_t, a_t, r_t, s_{t+1})`` is also a complete run of the one-step option "take ``a_t``", and
Q-learning is off-policy: it is a valid transition of the augmented action space with ``k = 1``,
``y = r_t + gamma (1 - terminated) max_b Q(s_{t+1}, b)``. This is intra-option value learning (Sutton, Precup and
Singh, 1999, "Between MDPs and semi-MDPs", section 7) restricted to the primitive actions, whose one-step options
are consistent with any step that took their action. With it, an agent over actions and options learns the values
of its primitive actions from every env step, as an agent over actions alone does, instead of only from the steps
where it chose a primitive action. Fox et al. (2017) do not use it.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key

__all__ = ["intra_option_transitions"]


def intra_option_transitions(
    data: TensorDictBase,
    *,
    num_actions: int | None = None,
    action_key: NestedKey = "action",
    executed_action_key: NestedKey = ("next", "executed_action"),
    executed_option_key: NestedKey = ("next", "executed_option"),
    reward_key: NestedKey = ("next", "reward"),
    steps_key: NestedKey = "steps_to_next_obs",
) -> TensorDictBase:
    r"""The steps of a batch that an option took, as one-step transitions of the primitive action it executed.

    Selects every step ``t`` that an option was in control of, ``data[executed_option_key][t] >= 0`` (the first
    step of each option run included), and writes the primitive action the env received,
    ``data[executed_action_key][t]``, in place of the policy's action, and ``steps_key = 1``. Steps where the
    policy's own primitive action was executed are left out: they are decisions already. Added to the replay buffer next to the decision-level
    transitions of :class:`~torchrl_options.data.SMDPTransitions`, they let ``DQNLoss`` learn the primitive
    actions' values from every env step (see the module docstring). They apply to an executor whose primitive
    actions are the env's actions (``level=1``, ``primitive_actions=True``).

    Args:
        data (TensorDictBase): step-level data of shape ``[T]`` or ``[*B, T]``, as yielded by a
            :class:`~torchrl.collectors.Collector` over an env with an
            :class:`~torchrl_options.transforms.OptionExecutor`.

    Keyword Args:
        num_actions (int, optional): the number of primitive actions ``A``; when given, every executed action
            must lie in ``[0, A)``.
        action_key (NestedKey): the policy's action, replaced in the output. Defaults to ``"action"``.
        executed_action_key (NestedKey): the executor's record of the action the env received. Defaults to
            ``("next", "executed_action")``.
        executed_option_key (NestedKey): the executor's record of the option in control (``-1`` for none).
            Defaults to ``("next", "executed_option")``.
        reward_key (NestedKey): gives the shape of ``steps_key``. Defaults to ``("next", "reward")``.
        steps_key (NestedKey): where ``k = 1`` is written. Defaults to ``"steps_to_next_obs"``.

    Returns:
        A TensorDict of shape ``[M]`` (``M`` the number of steps taken by options; ordered by env, then time) with
        the entries of ``data`` and ``steps_key``.

    Raises:
        KeyError: ``data`` lacks ``executed_option_key`` or ``executed_action_key``.
        ValueError: no time dimension, or an executed action outside ``[0, num_actions)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.data import intra_option_transitions
        >>> data = TensorDict({
        ...     "observation": torch.arange(5.0),
        ...     "action": torch.tensor([0, 3, 2, 0, 1]),  # A=2: action 0, then option 3 - 2 = 1 for 3 steps, action 1
        ...     "next": {
        ...         "observation": torch.arange(1.0, 6.0),
        ...         "reward": torch.ones(5, 1),
        ...         "executed_action": torch.tensor([0, 1, 1, 0, 1]),  # what the env received
        ...         "executed_option": torch.tensor([-1, 1, 1, 1, -1]),
        ...     },
        ... }, [5])
        >>> out = intra_option_transitions(data, num_actions=2)
        >>> out["observation"], out["action"], out["steps_to_next_obs"].squeeze(-1)
        (tensor([1., 2., 3.]), tensor([1, 1, 0]), tensor([1, 1, 1]))
    """
    if data.ndim == 0:
        raise ValueError("intra_option_transitions expects data with a time dimension (shape [T] or [*B, T]).")
    action_key, executed_action_key = unravel_key(action_key), unravel_key(executed_action_key)
    option_key, reward_key, steps_key = unravel_key(executed_option_key), unravel_key(reward_key), unravel_key(steps_key)
    for key in (option_key, executed_action_key):
        if data.get(key, None) is None:
            raise KeyError(f"intra_option_transitions: data has no {key!r} entry (collect through an OptionExecutor).")
    flat = data.reshape(-1)
    option = flat.get(option_key).reshape(flat.shape[0], -1)
    if option.shape[-1] != 1:
        raise ValueError(f"Expected one {option_key!r} per step, got shape {tuple(data.get(option_key).shape)}.")
    inside = option.reshape(-1) >= 0
    out = flat[inside]
    executed = out.get(executed_action_key)
    if num_actions is not None and executed.numel() and (executed.min() < 0 or executed.max() >= num_actions):
        raise ValueError(
            f"intra_option_transitions: {executed_action_key!r} must lie in [0, {num_actions}) on the steps options "
            f"took, got values in [{int(executed.min())}, {int(executed.max())}]."
        )
    out.set(action_key, executed.to(out.get(action_key).dtype).reshape(out.get(action_key).shape))
    reward = out.get(reward_key)
    out.set(steps_key, torch.ones(reward.shape[0], *([1] * (reward.ndim - 1)), dtype=torch.long, device=reward.device))
    return out
