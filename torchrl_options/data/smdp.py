"""Decision-level (SMDP) transitions from step-level data collected with an ``OptionExecutor``.

Q-learning over primitive actions and options (Sutton, Precup and Singh, 1999; Fox et al., 2017, section 5)
needs one transition per *decision*: the state ``s_t`` where the policy chose the augmented action ``a_t``,
the discounted reward of the ``k`` steps the choice lasted,

.. math::

    R_t = r_t + \\gamma r_{t+1} + \\dots + \\gamma^{k-1} r_{t+k-1},

the state ``s_{t+k}`` at the next decision (or the last state of the episode), the done flags of that last
step and ``steps_to_next_obs = k``, so that TorchRL's value estimators (and hence ``DQNLoss``) bootstrap with
``gamma ** k``: ``y = R_t + gamma^k (1 - terminated) max_a Q(s_{t+k}, a)``. The rewards are discounted
inside the option (the authors' code summed them undiscounted and bootstrapped with a single ``gamma``).
A truncated episode keeps ``terminated=False`` and is bootstrapped.

``discount_per="decision"`` instead treats every decision as one time-step of a decision-level MDP: the rewards
of a decision are summed undiscounted and ``k = 1``, so the bootstrap uses a single ``gamma`` (the decision's
length in primitive steps is then written apart, under ``duration_key``, ``"decision_steps"`` by default, for
statistics such as how long options ran). That is the
consistent choice only when time itself is counted in decisions (e.g. an episode limit in decisions, with the
:class:`~torchrl_options.transforms.DecisionCounter`); with the default, a primitive step towards a goal followed
by an option is worth as much as the option alone, whatever the decision budget.
"""
from __future__ import annotations

import logging

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.envs import Transform

from torchrl_options.checks import check_bool, check_distinct_keys, check_int, check_number
from torchrl_options.data.intra_option import intra_option_transitions, option_suffix_transitions

logger = logging.getLogger(__name__)

__all__ = ["smdp_transitions", "SMDPTransitions", "SMDPTransform"]


def smdp_transitions(
    data: TensorDictBase,
    gamma: float,
    *,
    decision_key: NestedKey = ("next", "option_decision"),
    reward_key: NestedKey = ("next", "reward"),
    done_key: NestedKey = ("next", "done"),
    steps_key: NestedKey = "steps_to_next_obs",
    discount_per: str = "step",
    duration_key: NestedKey = "decision_steps",
) -> TensorDictBase:
    r"""Turns a batch of step-level data into one transition per decision.

    A decision starts at every step ``t`` with ``data[decision_key][t]`` (the policy's action was used)
    and lasts until the step before the next decision or the end of the episode. Decisions whose end is
    not in the batch (the trailing one of each env, unless its episode ended at the last step) are
    dropped: use :class:`SMDPTransitions` to carry them over to the next collector batch.

    Args:
        data (TensorDictBase): step-level data of shape ``[T]`` or ``[*B, T]`` (time last), as yielded by
            a :class:`~torchrl.collectors.Collector` over an env with an
            :class:`~torchrl_options.transforms.OptionExecutor` (``split_trajs=False``). Without
            ``decision_key`` every step is a decision (``k = 1``).
        gamma (float): the discount factor.

    Keyword Args:
        decision_key (NestedKey): the executor's decision record. Defaults to ``("next", "option_decision")``.
        reward_key (NestedKey): Defaults to ``("next", "reward")``.
        done_key (NestedKey): Defaults to ``("next", "done")``.
        steps_key (NestedKey): where ``k`` is written. Defaults to ``"steps_to_next_obs"``, the key that
            TorchRL's value estimators read.
        discount_per (str): ``"step"`` (default: ``gamma`` per primitive step, the SMDP formulation) or
            ``"decision"`` (rewards of a decision summed, ``k = 1``: ``gamma`` per decision; see the module
            docstring).
        duration_key (NestedKey): with ``discount_per="decision"``, where the decision's length in primitive steps
            is written (``steps_key`` then holds 1). Not written with ``"step"``, where ``steps_key`` is the length.
            Defaults to ``"decision_steps"``.

    Returns:
        A TensorDict of shape ``[M]``, one entry per decision: the root entries of the decision step
        (observation, augmented ``action``, ...), ``"next"`` entries of its last step (next observation,
        ``done``/``terminated``/``truncated``) with ``reward_key`` replaced by the discounted sum, and
        ``steps_key``. Ordered by env, then time.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.data import smdp_transitions
        >>> data = TensorDict({
        ...     "observation": torch.arange(5.0),
        ...     "action": torch.tensor([3, 0, 0, 1, 2]),
        ...     "next": {
        ...         "observation": torch.arange(1.0, 6.0),
        ...         "reward": torch.ones(5, 1),
        ...         "done": torch.tensor([[False], [False], [False], [True], [False]]),
        ...         "terminated": torch.tensor([[False], [False], [False], [True], [False]]),
        ...         "option_decision": torch.tensor([True, False, False, True, True]),
        ...     },
        ... }, [5])
        >>> out = smdp_transitions(data, gamma=0.5)
        >>> out["action"], out["steps_to_next_obs"].squeeze(-1), out["next", "reward"].squeeze(-1)
        (tensor([3, 1]), tensor([3, 1]), tensor([1.7500, 1.0000]))
        >>> out["next", "observation"]  # the 3-step option ends at the next decision, s_3
        tensor([3., 4.])
    """
    keys = _Keys(decision_key, reward_key, done_key, steps_key, duration_key, owner="smdp_transitions")
    per_decision = _per_decision(discount_per)
    _check_step_data(data, keys, "smdp_transitions", per_decision)
    out, _ = _decisions(data, _check_gamma(gamma), None, keys, per_decision)
    return out


class SMDPTransitions:
    r"""Stateful :func:`smdp_transitions` that carries unfinished decisions across collector batches.

    A decision still running at the end of a batch (an option that spans two collector batches) is kept,
    with its partial discounted reward and step count, and completed with the next batch. Call it on every
    batch of one collector, in order; :meth:`reset` forgets the carried decisions (e.g. after the collector
    was reset). The layout of the batches (the envs, their entries, the device) must stay the same between calls
    while decisions are carried over: another layout raises a ``ValueError`` instead of losing them.

    Args:
        gamma (float): the discount factor.

    Keyword Args:
        decision_key, reward_key, done_key, steps_key, duration_key (NestedKey): as in :func:`smdp_transitions`.
        discount_per (str): ``"step"`` (default) or ``"decision"``, as in :func:`smdp_transitions`.

    Examples:
        >>> from torchrl.collectors import Collector
        >>> from torchrl_options.data import SMDPTransitions
        >>> smdp = SMDPTransitions(gamma=0.99)
        >>> for batch in collector:  # doctest: +SKIP
        ...     replay_buffer.extend(smdp(batch))
    """

    def __init__(
        self,
        gamma: float,
        *,
        decision_key: NestedKey = ("next", "option_decision"),
        reward_key: NestedKey = ("next", "reward"),
        done_key: NestedKey = ("next", "done"),
        steps_key: NestedKey = "steps_to_next_obs",
        discount_per: str = "step",
        duration_key: NestedKey = "decision_steps",
    ):
        self.owner = "SMDPTransitions"  # named in the errors (OnPolicyDecisions names itself)
        self.gamma = _check_gamma(gamma)
        self.per_decision = _per_decision(discount_per)
        self.keys = _Keys(decision_key, reward_key, done_key, steps_key, duration_key, owner=self.owner)
        self._carry: _Carry | None = None

    def __call__(self, data: TensorDictBase) -> TensorDictBase:
        """Returns the decisions that end in ``data`` (shape ``[T]`` or ``[*B, T]``, time last), those carried over
        from the previous batch first completed.

        Raises:
            ValueError: the batch's layout (envs, entries, device) differs from the previous batch's while decisions
                are carried over from it (call :meth:`reset` between two streams), or ``data`` already holds an
                entry this writes (``steps_key``, ``duration_key``).
        """
        _check_step_data(data, self.keys, self.owner, self.per_decision)
        carry = self._carry
        if carry is not None:
            _check_same_layout(carry, data, self.owner)
        out, self._carry = _decisions(data, self.gamma, carry, self.keys, self.per_decision)
        self._carry.layout = _layout(data)
        return out

    def reset(self) -> None:
        """Forgets the decisions carried over from the previous batch."""
        self._carry = None

    def with_duration(self, transitions: TensorDictBase) -> TensorDictBase:
        """Gives transitions written beside the decisions (e.g. one-step intra-option transitions) the decisions'
        ``duration_key``, so that both can share a replay buffer: with ``discount_per="decision"`` it copies their
        ``steps_key`` there (in place); per step it leaves them as they are (the decisions have no such key).

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> one_step = TensorDict(steps_to_next_obs=torch.ones(3, 1, dtype=torch.long), batch_size=[3])
            >>> SMDPTransitions(0.9, discount_per="decision").with_duration(one_step)["decision_steps"].squeeze(-1)
            tensor([1, 1, 1])
            >>> "decision_steps" in SMDPTransitions(0.9).with_duration(one_step.exclude("decision_steps")).keys()
            False
        """
        if self.per_decision:
            transitions.set(self.keys.duration, transitions.get(self.keys.steps).clone())
        return transitions

    @property
    def num_pending(self) -> int:
        """Number of envs whose current decision is still running."""
        return 0 if self._carry is None else int(self._carry.valid.sum())


def _check_gamma(gamma: float) -> float:
    check_number(gamma, "gamma", lo=0.0, hi=1.0)
    return float(gamma)


def _per_decision(discount_per: str) -> bool:
    if discount_per not in ("step", "decision"):
        raise ValueError(f"discount_per must be 'step' or 'decision', got {discount_per!r}.")
    return discount_per == "decision"


class _Keys:
    def __init__(self, decision_key, reward_key, done_key, steps_key, duration_key, owner: str = "smdp"):
        # every key argument names its own entry: steps_key=("next", "reward") would write the decisions' lengths
        # over their summed rewards, a duration_key equal to another key its entry
        keys = check_distinct_keys(
            {"duration_key": duration_key, "decision_key": decision_key, "reward_key": reward_key,
             "done_key": done_key, "steps_key": steps_key},
            owner,
        )  # fmt: skip
        self.decision, self.reward, self.done = keys["decision_key"], keys["reward_key"], keys["done_key"]
        self.steps, self.duration = keys["steps_key"], keys["duration_key"]


def _check_step_data(data: TensorDictBase, keys: _Keys, owner: str, per_decision: bool) -> None:
    """Refuses step-level data that already holds an entry the decisions are written to (it would be overwritten)."""
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"{owner} expects a TensorDict of step-level data, got {type(data).__name__}.")
    if data.ndim == 0:
        raise ValueError(f"{owner} expects data with a time dimension (shape [T] or [*B, T]).")
    if data.shape[-1] == 0:
        raise ValueError(f"{owner} expects at least one step, got data of shape {tuple(data.shape)}.")
    for key, name in ((keys.done, "done_key"), (keys.reward, "reward_key")):
        if data.get(key, None) is None:
            raise ValueError(
                f"{owner}: data has no {key!r} entry ({name}); it needs the done flags and rewards of every step, as "
                "a collector yields them."
            )
    for key, name in ((keys.steps, "steps_key"), (keys.duration, "duration_key")):
        if name == "duration_key" and not per_decision:  # written only per decision
            continue
        if data.get(key, None) is not None:
            raise ValueError(
                f"{owner}: the step-level data already holds a {key!r} entry ({name}), which the decisions are "
                f"written to: it would be overwritten. Pass another {name}, or remove the entry."
            )


def _layout(data: TensorDictBase) -> tuple:
    """What must stay the same between two batches of one stream: the envs, the entries and the device."""
    keys = tuple(sorted(map(str, data.keys(include_nested=True, leaves_only=True))))
    return tuple(data.shape[:-1]), keys, data.device


def _check_same_layout(carry: _Carry, data: TensorDictBase, owner: str) -> None:
    """A batch continuing the stream of the previous one: the same envs (leading dims), entries and device."""
    envs, keys, device = carry.layout
    new_envs, new_keys, new_device = _layout(data)
    what = None
    if new_envs != envs:
        what = f"has envs of shape {list(new_envs)} (leading dims), the previous batch {list(envs)}"
    elif new_keys != keys:
        lost, gained = sorted(set(keys) - set(new_keys)), sorted(set(new_keys) - set(keys))
        what = f"has other entries than the previous batch (missing {lost}, new {gained})"
    elif new_device != device:
        what = f"is on device {new_device}, the previous batch on {device}"
    if what is not None:
        raise ValueError(
            f"{owner}: the batch {what}, while {int(carry.valid.sum())} decision(s) of the previous batch are still "
            "running and would be lost. Feed the batches of one collector, in order; call reset() first to start a "
            "new stream (e.g. another collector)."
        )


class _Carry:
    """Per env, the decision still running at the end of a batch, as one macro-step of ``steps`` steps."""

    def __init__(self, td: TensorDictBase, valid: torch.Tensor, steps: torch.Tensor):
        self.td = td  # [N]: root entries of the decision step, "next" of the last step seen, partial reward
        self.valid = valid  # [N] bool
        self.steps = steps  # [N] long
        self.layout: tuple = ()  # of the batch it comes from (see _layout)


def _decisions(
    data: TensorDictBase, gamma: float, carry: _Carry | None, keys: _Keys, per_decision: bool = False
) -> tuple[TensorDictBase, _Carry]:
    T = data.shape[-1]
    data = data.reshape(-1, T)
    N = data.shape[0]
    device = data.device if data.device is not None else data.get(keys.done).device

    def per_step(key: NestedKey, default=None) -> torch.Tensor | None:
        value = data.get(key, None)
        if value is None:
            return default
        if value.numel() != N * T:
            raise ValueError(f"Expected one {key!r} per step (shape {[N, T]} up to singleton dims), got {tuple(value.shape)}.")
        return value.reshape(N, T)

    decision = per_step(keys.decision, torch.ones(N, T, dtype=torch.bool, device=device)).bool()
    done = per_step(keys.done).bool()
    steps = torch.ones(N, T, dtype=torch.long, device=device)
    valid = torch.ones(N, T, dtype=torch.bool, device=device)
    if carry is not None:
        # the running decisions become a first macro-step of carry.steps steps
        data = torch.cat([carry.td.unsqueeze(1), data], 1)
        decision = torch.cat([carry.valid.unsqueeze(1), decision], 1)
        done = torch.cat([torch.zeros_like(carry.valid).unsqueeze(1), done], 1)
        steps = torch.cat([carry.steps.unsqueeze(1), steps], 1)
        valid = torch.cat([carry.valid.unsqueeze(1), valid], 1)
        T = T + 1
    reward = data.get(keys.reward)  # [N, T, *r]
    if not reward.is_floating_point():
        reward = reward.float()
    time = torch.arange(T, device=device).expand(N, T)

    # a segment starts at a decision, after an episode end, or at the first (valid) step of the batch
    after_end = torch.ones_like(done)
    after_end[:, 1:] = done[:, :-1] | ~valid[:, :-1]
    start = valid & (decision | after_end)
    start_time = torch.where(start, time, 0).cummax(1).values
    is_last = valid.clone()
    is_last[:, :-1] &= start[:, 1:]
    # discount exponent of each step inside its segment, counted in primitive steps
    elapsed = steps.cumsum(1) - steps  # steps before t in the row
    if per_decision:  # one time-step per decision: the decision's rewards are summed undiscounted
        discount = torch.ones(N, T, dtype=reward.dtype, device=device)
    else:
        exponent = elapsed - elapsed.gather(1, start_time)
        discount = torch.pow(torch.as_tensor(gamma, dtype=reward.dtype, device=device), exponent.to(reward.dtype))
    segment = (torch.arange(N, device=device).unsqueeze(1) * T + start_time).reshape(-1)
    discount = discount.reshape(N, T, *([1] * (reward.ndim - 2)))
    returns = torch.zeros_like(reward.reshape(N * T, *reward.shape[2:])).index_add_(
        0, segment, (discount * reward).reshape(N * T, *reward.shape[2:])
    )
    length = (elapsed + steps) - elapsed.gather(1, start_time)  # k, valid at the last step of a segment
    # a segment whose start step is not a decision began before the data we have: it is dropped
    known_start = decision.gather(1, start_time) & valid.gather(1, start_time)
    ends_in_batch = torch.ones_like(done)
    ends_in_batch[:, -1] = done[:, -1]
    complete = (is_last & ends_in_batch & known_start).reshape(-1)
    trailing = (is_last & ~ends_in_batch & known_start)[:, -1]

    flat = data.reshape(-1)
    ends = complete.nonzero().squeeze(-1)
    starts = segment[ends]
    k = torch.ones_like(length) if per_decision else length
    out = _assemble(flat, starts, ends, returns, k.reshape(-1), keys)
    if per_decision:  # k is 1 for the bootstrap; the decision's length in steps is kept apart
        _set_like_steps(out, keys.duration, length.reshape(-1)[ends], keys)

    last = torch.arange(N, device=device) * T + T - 1
    carried = _assemble(flat, segment[last], last, returns, length.reshape(-1), keys, steps_entry=False)
    return out, _Carry(carried, trailing, length[:, -1].clone())


def _assemble(
    flat: TensorDictBase,
    starts: torch.Tensor,
    ends: torch.Tensor,
    returns: torch.Tensor,
    length: torch.Tensor,
    keys: _Keys,
    steps_entry: bool = True,
) -> TensorDictBase:
    """Root entries at ``starts``, ``"next"`` entries at ``ends``, the discounted reward and ``k``."""
    out = flat[starts].exclude("next")
    out.set("next", flat.get("next")[ends])
    reward = returns[starts]
    out.set(keys.reward, reward)
    if steps_entry:
        _set_like_steps(out, keys.steps, length[ends], keys)
    return out


def _set_like_steps(out: TensorDictBase, key: NestedKey, value: torch.Tensor, keys: _Keys) -> None:
    """Writes a per-transition count with the reward's trailing singleton dims (as ``steps_to_next_obs``)."""
    ndim = out.get(keys.reward).ndim
    out.set(key, value.view(value.shape[0], *([1] * (ndim - 1))) if ndim > 1 else value)


class SMDPTransform(Transform):
    r"""Decision-level (SMDP) transitions as a replay-buffer transform.

    Appended to a replay buffer (``rb.append_transform(SMDPTransform(gamma))``), it turns each batch of step-level data
    given to ``rb.extend`` (a collector batch, over an env with an
    :class:`~torchrl_options.transforms.OptionExecutor`) into one transition per decision, as
    :func:`smdp_transitions`, and carries the decisions still running at the end of a batch over to the next one, as
    :class:`SMDPTransitions` (the same core). It has the shape of TorchRL's
    :class:`~torchrl.envs.transforms.MultiStepTransform`: an inverse transform, applied when data are written; sampling
    returns the stored transitions unchanged. ``DQNLoss`` reads their ``steps_to_next_obs`` and bootstraps with
    ``gamma ** k``.

    With ``intra_option_actions`` and/or ``option_suffixes`` it also writes the one-step transitions of the primitive
    actions that options took (:func:`~torchrl_options.data.intra_option_transitions`) and the rest of every option run
    from each of its steps (:func:`~torchrl_options.data.option_suffix_transitions`), after the decisions of the batch,
    with a ``marker_key`` entry (``True`` on them, ``False`` on the decisions).

    Call ``rb.extend`` with the batches of one collector, in order; :meth:`reset` forgets the carried decisions (e.g.
    after the collector was reset). A batch in which no transition completes writes nothing. Use one transform per
    collector (its state is the running decision of each env).

    Args:
        gamma (float): the discount factor, in ``[0, 1]``.

    Keyword Args:
        discount_per (str): ``"step"`` (default) or ``"decision"``, as in :func:`smdp_transitions`.
        intra_option_actions (bool): also write the intra-option transitions of primitive actions; needs
            ``num_actions`` (an executor with ``level=1``, ``primitive_actions=True``). Defaults to ``False``.
        option_suffixes (bool): also write the option-suffix transitions (``discount_per="step"`` only). Defaults
            to ``False``.
        num_actions (int, optional): the number of primitive actions ``A`` of the executor (``None`` for an executor
            with ``primitive_actions=False``, whose options are actions ``0 .. K-1``).
        marker_key (NestedKey): marks the intra-option and suffix transitions. Defaults to ``"intra_option"``.
        decision_key, reward_key, done_key, steps_key, duration_key (NestedKey): as in :func:`smdp_transitions`
            (with ``discount_per="decision"`` the intra-option transitions get ``duration_key`` = 1 too).
        action_key, executed_action_key, executed_option_key (NestedKey): as in
            :func:`~torchrl_options.data.intra_option_transitions`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_options.data import SMDPTransform
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)
        >>> rb.append_transform(SMDPTransform(gamma=0.5))  # doctest: +ELLIPSIS
        TensorDictReplayBuffer(...)
        >>> data = TensorDict({  # one env, 5 steps: a primitive action, then option 1 (action 3) for 4 steps
        ...     "observation": torch.arange(5.0),
        ...     "action": torch.tensor([0, 3, 0, 0, 1]),
        ...     "next": {
        ...         "observation": torch.arange(1.0, 6.0),
        ...         "reward": torch.ones(5, 1),
        ...         "done": torch.zeros(5, 1, dtype=torch.bool),
        ...         "option_decision": torch.tensor([True, True, False, False, False]),
        ...     },
        ... }, [5])
        >>> _ = rb.extend(data[:3])  # the primitive decision; the option is still running
        >>> len(rb)
        1
        >>> _ = rb.extend(data[3:])  # the option has not ended yet either
        >>> _ = rb.extend(TensorDict({  # the next decision at s_5 ends it
        ...     "observation": torch.tensor([5.0]), "action": torch.tensor([0]),
        ...     "next": {"observation": torch.tensor([6.0]), "reward": torch.ones(1, 1),
        ...              "done": torch.zeros(1, 1, dtype=torch.bool), "option_decision": torch.tensor([True])},
        ... }, [1]))
        >>> stored = rb[:]
        >>> stored["action"], stored["steps_to_next_obs"].squeeze(-1), stored["next", "reward"].squeeze(-1)
        (tensor([0, 3]), tensor([1, 4]), tensor([1.0000, 1.8750]))
    """

    ENV_ERR = "SMDPTransform is a replay-buffer transform (rb.append_transform); it cannot be used in an env."

    def __init__(
        self,
        gamma: float,
        *,
        discount_per: str = "step",
        intra_option_actions: bool = False,
        option_suffixes: bool = False,
        num_actions: int | None = None,
        marker_key: NestedKey = "intra_option",
        decision_key: NestedKey = ("next", "option_decision"),
        reward_key: NestedKey = ("next", "reward"),
        done_key: NestedKey = ("next", "done"),
        steps_key: NestedKey = "steps_to_next_obs",
        duration_key: NestedKey = "decision_steps",
        action_key: NestedKey = "action",
        executed_action_key: NestedKey = ("next", "executed_action"),
        executed_option_key: NestedKey = ("next", "executed_option"),
    ):
        super().__init__()
        for name, value in (("intra_option_actions", intra_option_actions), ("option_suffixes", option_suffixes)):
            check_bool(value, f"SMDPTransform: {name}")
        check_int(num_actions, "SMDPTransform: num_actions", minimum=1, allow_none=True)
        # the transitions it writes hold every one of these entries: no two key arguments may name the same
        check_distinct_keys(
            {"marker_key": marker_key, "decision_key": decision_key, "reward_key": reward_key, "done_key": done_key,
             "steps_key": steps_key, "duration_key": duration_key, "action_key": action_key,
             "executed_action_key": executed_action_key, "executed_option_key": executed_option_key},
            "SMDPTransform",
        )  # fmt: skip
        if intra_option_actions and num_actions is None:
            raise ValueError(
                "SMDPTransform: intra_option_actions=True needs num_actions (the executor's primitive actions A)."
            )
        if option_suffixes and discount_per != "step":
            raise ValueError(
                "SMDPTransform: option_suffixes=True discounts per primitive step: it needs discount_per='step'."
            )
        self.smdp = SMDPTransitions(
            gamma,
            decision_key=decision_key,
            reward_key=reward_key,
            done_key=done_key,
            steps_key=steps_key,
            duration_key=duration_key,
            discount_per=discount_per,
        )
        self.intra_option_actions = intra_option_actions
        self.option_suffixes = option_suffixes
        self.num_actions = num_actions
        self.marker_key = unravel_key(marker_key)
        self.action_key = unravel_key(action_key)
        self.executed_action_key = unravel_key(executed_action_key)
        self.executed_option_key = unravel_key(executed_option_key)

    @property
    def gamma(self) -> float:
        """The discount factor."""
        return self.smdp.gamma

    @property
    def num_pending(self) -> int:
        """Number of envs whose current decision is still running (carried over to the next batch)."""
        return self.smdp.num_pending

    def reset(self) -> None:
        """Forgets the decisions carried over from the previous batch."""
        self.smdp.reset()

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase | None:
        if self.parent is not None:
            raise ValueError(self.ENV_ERR)
        out = self.smdp(tensordict)
        if self.intra_option_actions or self.option_suffixes:
            keys = self.smdp.keys
            parts = [out]
            if self.intra_option_actions:
                parts.append(
                    intra_option_transitions(
                        tensordict,
                        num_actions=self.num_actions,
                        action_key=self.action_key,
                        executed_action_key=self.executed_action_key,
                        executed_option_key=self.executed_option_key,
                        reward_key=keys.reward,
                        steps_key=keys.steps,
                    )
                )
            if self.option_suffixes:
                parts.append(
                    option_suffix_transitions(
                        tensordict,
                        self.gamma,
                        action_offset=self.num_actions or 0,
                        action_key=self.action_key,
                        executed_option_key=self.executed_option_key,
                        decision_key=keys.decision,
                        reward_key=keys.reward,
                        done_key=keys.done,
                        steps_key=keys.steps,
                    )
                )
            for part in parts[1:]:
                self.smdp.with_duration(part)
            for i, part in enumerate(parts):
                part.set(self.marker_key, torch.full(part.shape, i > 0, dtype=torch.bool, device=part.device))
            out = torch.cat(parts, 0)
        # an empty write is skipped, as TorchRL's MultiStepTransform does (an empty extend fails on a new storage)
        return out if out.shape[0] else None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Sampling: the stored transitions, unchanged."""
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise ValueError(self.ENV_ERR)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        raise ValueError(self.ENV_ERR)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(gamma={self.gamma}, "
            f"discount_per={'decision' if self.smdp.per_decision else 'step'!r}, "
            f"intra_option_actions={self.intra_option_actions}, option_suffixes={self.option_suffixes}, "
            f"num_actions={self.num_actions})"
        )
