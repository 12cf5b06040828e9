"""One-step transitions of the primitive actions that options took (intra-option learning of primitive actions).

While an option runs, the agent makes no decision, so the decision-level transitions of
:mod:`torchrl_options.data.smdp` teach its Q-function nothing about the primitive actions taken on those steps. Yet
every such step ``(s_t, a_t, r_t, s_{t+1})`` is also a complete run of the one-step option "take ``a_t``", and
Q-learning is off-policy: it is a valid transition of the augmented action space with ``k = 1``,
``y = r_t + gamma (1 - terminated) max_b Q(s_{t+1}, b)``. This is intra-option value learning (Sutton, Precup and
Singh, 1999, "Between MDPs and semi-MDPs", section 7) restricted to the primitive actions, whose one-step options
are consistent with any step that took their action. With it, an agent over actions and options learns the values
of its primitive actions from every env step, as an agent over actions alone does, instead of only from the steps
where it chose a primitive action.

The options themselves get the same from :func:`option_suffix_transitions`: an option whose control policy and
termination depend on the current state only (a Markov option, as DDO's are) behaves from any state it passes
through exactly as if it had been started there, so the rest of each run, from every step after its first, is a
sample of "start this option here". Fox et al. (2017) use neither.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_distinct_keys, check_int, check_number

__all__ = ["intra_option_transitions", "option_suffix_transitions"]


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
    policy's own primitive action was executed are left out: they are decisions already. Added to the replay
    buffer next to the decision-level transitions of :class:`~torchrl_options.data.SMDPTransitions`, they let
    ``DQNLoss`` learn the primitive actions' values from every env step (see the module docstring). They apply to
    an executor whose primitive actions are the env's actions (``level=1``, ``primitive_actions=True``).

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
        ValueError: ``data`` lacks ``executed_option_key`` or ``executed_action_key``, has no time dimension, or an
            executed action lies outside ``[0, num_actions)``.

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
    _check_data(data, "intra_option_transitions")
    check_int(num_actions, "intra_option_transitions: num_actions", minimum=1, allow_none=True)
    keys = check_distinct_keys(
        {"action_key": action_key, "executed_action_key": executed_action_key,
         "executed_option_key": executed_option_key, "reward_key": reward_key, "steps_key": steps_key},
        "intra_option_transitions",
    )  # fmt: skip
    action_key, executed_action_key = keys["action_key"], keys["executed_action_key"]
    option_key, reward_key, steps_key = keys["executed_option_key"], keys["reward_key"], keys["steps_key"]
    if data.get(reward_key, None) is None:
        raise ValueError(f"intra_option_transitions: data has no {reward_key!r} entry (reward_key).")
    for key in (option_key, executed_action_key):
        if data.get(key, None) is None:
            raise ValueError(
                f"intra_option_transitions: data has no {key!r} entry (collect through an OptionExecutor)."
            )
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


def option_suffix_transitions(
    data: TensorDictBase,
    gamma: float,
    *,
    action_offset: int,
    action_key: NestedKey = "action",
    executed_option_key: NestedKey = ("next", "executed_option"),
    decision_key: NestedKey = ("next", "option_decision"),
    reward_key: NestedKey = ("next", "reward"),
    done_key: NestedKey = ("next", "done"),
    steps_key: NestedKey = "steps_to_next_obs",
) -> TensorDictBase:
    r"""The rest of every option run, from each of its steps after the first, as a decision-level transition.

    For a run of option ``o`` over steps ``t0 .. t1`` (decided at ``t0``; :class:`~torchrl_options.data.SMDPTransitions`
    gives its transition from ``t0``), each step ``t0 < t <= t1`` yields the transition of starting ``o`` at
    ``s_t``: action ``action_offset + o``, reward :math:`\sum_{j=t}^{t_1} \gamma^{j-t} r_j`, ``"next"`` entries of
    step ``t1`` and ``steps_key = t1 - t + 1``. This is valid for Markov options (the module docstring) and gives
    their values one transition per step they run instead of one per run.

    Only runs that end within ``data`` (at a step followed by a decision, or at an episode end) are used: a run
    still going at the last step of an env's row gives no suffix from its steps in this batch (a run that began
    before the batch does: a suffix needs only its own steps).

    Args:
        data (TensorDictBase): step-level data of shape ``[T]`` or ``[*B, T]`` (time last), as yielded by a
            :class:`~torchrl.collectors.Collector` over an env with an
            :class:`~torchrl_options.transforms.OptionExecutor`.
        gamma (float): the discount per primitive step.

    Keyword Args:
        action_offset (int): the augmented action of option ``o`` is ``action_offset + o``: the number of primitive
            actions (``primitive_actions=True``), or ``0``.
        action_key, executed_option_key, decision_key, reward_key, done_key, steps_key (NestedKey): the entries
            (the executor's records and TorchRL's defaults).

    Returns:
        A TensorDict of shape ``[M]`` with the entries of ``data``: root entries of the suffix's first step with
        ``action_key`` set to the option's augmented action, ``"next"`` entries of the run's last step with the
        discounted reward sum, and ``steps_key``. Ordered by env, then time.

    Raises:
        ValueError: ``data`` lacks ``executed_option_key``, ``decision_key``, ``reward_key`` or ``done_key``, has no
            time dimension, or ``gamma`` lies outside ``[0, 1]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.data import option_suffix_transitions
        >>> data = TensorDict({
        ...     "observation": torch.arange(5.0),
        ...     "action": torch.tensor([0, 3, 2, 0, 1]),  # A=2: action 0, then option 1 for 3 steps, action 1
        ...     "next": {
        ...         "observation": torch.arange(1.0, 6.0),
        ...         "reward": torch.ones(5, 1),
        ...         "done": torch.zeros(5, 1, dtype=torch.bool),
        ...         "executed_option": torch.tensor([-1, 1, 1, 1, -1]),
        ...         "option_decision": torch.tensor([True, True, False, False, True]),
        ...     },
        ... }, [5])
        >>> out = option_suffix_transitions(data, 0.5, action_offset=2)
        >>> out["observation"], out["action"], out["steps_to_next_obs"].squeeze(-1), out["next", "reward"].squeeze(-1)
        (tensor([2., 3.]), tensor([3, 3]), tensor([2, 1]), tensor([1.5000, 1.0000]))
        >>> out["next", "observation"]  # both end where the run ends, at s_4
        tensor([4., 4.])
    """
    _check_data(data, "option_suffix_transitions")
    check_number(gamma, "gamma", lo=0.0, hi=1.0)
    check_int(action_offset, "option_suffix_transitions: action_offset", minimum=0)
    keys = check_distinct_keys(
        {"action_key": action_key, "executed_option_key": executed_option_key, "decision_key": decision_key,
         "reward_key": reward_key, "done_key": done_key, "steps_key": steps_key},
        "option_suffix_transitions",
    )  # fmt: skip
    action_key, option_key, decision_key = keys["action_key"], keys["executed_option_key"], keys["decision_key"]
    reward_key, done_key, steps_key = keys["reward_key"], keys["done_key"], keys["steps_key"]
    for key in (option_key, decision_key, reward_key, done_key):
        if data.get(key, None) is None:
            raise ValueError(
                f"option_suffix_transitions: data has no {key!r} entry (collect through an OptionExecutor)."
            )
    T = data.shape[-1]
    rows = data.reshape(-1, T)
    N = rows.shape[0]

    def per_step(key: NestedKey) -> torch.Tensor:
        value = rows.get(key)
        if value.numel() != N * T:
            raise ValueError(
                f"Expected one {key!r} per step (shape {[N, T]} up to singleton dims), got {tuple(value.shape)}."
            )
        return value.reshape(N, T)

    option = per_step(option_key)
    decision = per_step(decision_key).bool()
    done = per_step(done_key).bool()
    reward = rows.get(reward_key)  # [N, T, *r]
    # the run goes on after step t: not the last step, no episode end, and no decision at t + 1
    goes_on = torch.zeros_like(done)
    goes_on[:, :-1] = ~done[:, :-1] & ~decision[:, 1:]
    # backwards over time: the discounted reward to the end of the run and the run's steps left (t included)
    ret = torch.zeros_like(reward[:, 0])
    length = torch.zeros(N, dtype=torch.long, device=done.device)
    returns, lengths = [], []
    for t in range(T - 1, -1, -1):
        cont = goes_on[:, t]
        ret = reward[:, t] + gamma * torch.where(cont.view(N, *([1] * (ret.ndim - 1))), ret, torch.zeros_like(ret))
        length = 1 + torch.where(cont, length, 0)
        returns.append(ret)
        lengths.append(length)
    ret = torch.stack(returns[::-1], 1)  # [N, T, *r]
    length = torch.stack(lengths[::-1], 1)
    last = torch.arange(T, device=done.device) + length - 1  # the run's last step
    # the run ends in the batch unless its last step is the row's last and the episode goes on there
    known = (last < T - 1) | done.gather(1, last)
    # a step after the first of its run (no decision), whose run ends in the batch
    use = (option >= 0) & ~decision & known
    flat = rows.reshape(-1)
    index = use.reshape(-1).nonzero().squeeze(-1)
    ends = (torch.arange(N, device=done.device).unsqueeze(1) * T + last).reshape(-1)[index]
    out = flat[index].exclude("next")
    out.set("next", flat.get("next")[ends])
    r = ret.reshape(N * T, *ret.shape[2:])[index]
    out.set(reward_key, r)
    action = out.get(action_key)
    out.set(action_key, (action_offset + option.reshape(-1)[index]).to(action.dtype).reshape(action.shape))
    k = length.reshape(-1)[index]
    out.set(steps_key, k.view(k.shape[0], *([1] * (r.ndim - 1))) if r.ndim > 1 else k)
    return out


def _check_data(data: TensorDictBase, owner: str) -> None:
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"{owner} expects a TensorDict of step-level data, got {type(data).__name__}.")
    if data.ndim == 0:
        raise ValueError(f"{owner} expects data with a time dimension (shape [T] or [*B, T]).")
