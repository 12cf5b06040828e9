"""Episode limits counted in decisions rather than primitive steps.

Fox et al. (2017, "Multi-Level Discovery of Deep Options", appendix B) give +1 "if the agent reaches the goal in
20 time-steps". If an option that runs to its termination counts as one time-step (one decision of the agent, as
in the semi-MDP view of options of Sutton, Precup and Singh, 1999), episodes are limited in *decisions*, not in
primitive env steps. :class:`DecisionCounter` implements that limit on top of an
:class:`~torchrl_options.transforms.OptionExecutor`.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Bounded, Categorical, Composite
from torchrl.envs import EnvBase, Transform

from torchrl_options.checks import check_distinct_keys
from torchrl_options.transforms.keys import (
    FlagToState,
    done_key_arguments,
    followed_done_entries,
    level_key,
    reset_key,
    sibling_key,
)

__all__ = ["DecisionCounter"]


class DecisionCounter(Transform):
    r"""Counts the agent's decisions and truncates an episode once its ``max_decisions``-th decision has finished.

    Appended after an :class:`~torchrl_options.transforms.OptionExecutor`, it counts the steps at which the
    policy's action was used (``("next", "option_decision")``; the first step of every episode is one) and
    writes the count to ``("next", count_key)`` (an observation, like TorchRL's ``StepCounter``'s
    ``"step_count"``, so it is also the state of the next step). The episode is truncated (``truncated`` and
    ``done`` set) at the step after which the ``max_decisions``-th decision is over: right after it for a
    primitive action, or once the option it started has terminated (``("next", "option") == -1``: the next step
    would be a decision). An option run to termination thus counts as one time-step, the semi-MDP view of
    options (Sutton, Precup and Singh, 1999) under which Fox et al. (2017, appendix B) may count the 20
    time-steps of their two-rooms task.

    For an executor at ``level`` ``L > 1`` (a hierarchy) the decisions are those of level ``L``
    (``"option_decision_L"``), and a decision is over only once the options of every level ``1 .. L`` it set
    off have terminated (``"option"``, ..., ``"option_L"`` all ``-1``). With ``level=None`` (no executor) every
    step is a decision: the transform then truncates after exactly ``max_decisions`` steps, like
    ``StepCounter(max_decisions)``.

    An option that never terminates would keep the episode going: keep a cap on primitive steps, e.g. the env's
    own ``max_steps`` (which truncates the episode, and ends the option with it) set well above
    ``max_decisions``.

    **Done entries** (as TorchRL's :class:`~torchrl.envs.transforms.StepCounter`): the count has the shape of the
    first (outermost) done entry followed (``done_key``, by default the ``"done"`` next to each of the env's reset
    keys), and is reset by the ``"_reset"`` next to it. A truncation is written there and carried to the other
    done entries followed (e.g. the ``("agents", "done")`` of a multi-agent env, with their ``"truncated"``). With
    per-agent executors (decisions ``[*B, n_agents]`` for a root count ``[*B, 1]``) a step is a decision when any
    agent decides, and a decision is over once no agent's option runs.

    Args:
        max_decisions (int): decisions per episode, at least 1.

    Keyword Args:
        level (int or None, optional): level of the executor whose decisions are counted (the top one, the
            agent's); sets the default ``decision_key`` and ``option_keys``. ``None``: no executor, every step
            is a decision. Defaults to ``1``.
        decision_key (NestedKey, optional): the executor's decision record. Defaults to ``"option_decision"``
            (``"option_decision_L"`` at level ``L``).
        option_keys (sequence of NestedKey, optional): the running-option entries of the executors; the next
            step is a decision when all are ``-1``. Defaults to ``["option", ..., "option_L"]``.
        count_key (NestedKey, optional): where the count is written. Defaults to ``"decision_count"``.
        done_key (NestedKey or list of NestedKey, optional): the done entries (the first one's shape is the
            count's), named as for :class:`~torchrl_options.transforms.OptionExecutor`: a string is a leaf name
            looked up next to each of the env's reset keys, a list names exactly its entries. Defaults to
            ``"done"``.
        truncated_key (NestedKey, optional): the truncation entry written next to the first done entry. Defaults to
            the ``"truncated"`` entry next to it.

    Raises:
        ValueError: for ``max_decisions < 1``, a bad ``level``, or, once appended, when the env does not provide
            ``decision_key`` or ``option_keys`` (no executor upstream: pass ``level=None``) or ``done_key``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.envs import check_env_specs
        >>> from torchrl_options.envs import GridWorldEnv
        >>> from torchrl_options.transforms import DecisionCounter, OptionExecutor
        >>> class Walk(torch.nn.Module):  # one option: 3 steps to the right
        ...     def forward(self, step_count):
        ...         batch = step_count.shape[:-1]
        ...         logits = torch.tensor([[-1e9, 1e9, -1e9, -1e9]]).expand(*batch, 1, 4)
        ...         return logits, torch.where(step_count % 3 == 0, 1e9, -1e9).expand(*batch, 1)
        >>> options = TensorDictModule(Walk(), ["step_count"], ["option_logits", "termination_logits"])
        >>> env = GridWorldEnv("two-rooms", max_steps=200, noise=0.0, batch_size=[2], seed=0)
        >>> env = env.append_transform(OptionExecutor(options, num_options=1)).append_transform(DecisionCounter(2))
        >>> check_env_specs(env)
        >>> # env 0 always starts the option (action 4), env 1 moves up (action 0): 2 decisions each
        >>> policy = lambda td: td.set("action", torch.tensor([4, 0]))
        >>> data = env.rollout(6, policy, break_when_any_done=False)
        >>> data["next", "decision_count"].squeeze(-1)
        tensor([[1, 1, 1, 2, 2, 2],
                [1, 2, 1, 2, 1, 2]])
        >>> data["next", "truncated"].squeeze(-1)
        tensor([[False, False, False, False, False,  True],
                [False,  True, False,  True, False,  True]])
    """

    invertible = False

    def __init__(
        self,
        max_decisions: int,
        *,
        level: int | None = 1,
        decision_key: NestedKey | None = None,
        option_keys: Sequence[NestedKey] | None = None,
        count_key: NestedKey = "decision_count",
        done_key: NestedKey | Sequence[NestedKey] = "done",
        truncated_key: NestedKey | None = None,
    ):
        if isinstance(max_decisions, bool) or not isinstance(max_decisions, int) or max_decisions < 1:
            raise ValueError(f"max_decisions must be an int >= 1, got {max_decisions!r}.")
        if level is not None and (isinstance(level, bool) or not isinstance(level, int) or level < 1):
            raise ValueError(f"level must be a positive int (the executor's level) or None, got {level!r}.")
        if level is None and (decision_key is not None or option_keys):
            raise ValueError(
                "level=None counts every step as a decision: decision_key and option_keys must then be None, got "
                f"decision_key={decision_key!r}, option_keys={option_keys!r}."
            )
        if level is not None:
            decision_key = decision_key if decision_key is not None else level_key("option_decision", level)
            if option_keys is None:
                option_keys = [level_key("option", lvl) for lvl in range(1, level + 1)]
            option_keys = [unravel_key(k) for k in option_keys]
            if not option_keys:
                raise ValueError("option_keys must name at least one running-option entry (or pass level=None).")
        self.max_decisions = max_decisions
        self.level = level
        self.decision_key = None if decision_key is None else unravel_key(decision_key)
        self.option_keys: list[NestedKey] = list(option_keys or [])
        self.count_key = unravel_key(count_key)
        done_names = done_key_arguments(done_key, "DecisionCounter")
        # the count it writes must not land on an entry it reads (the flags, the decision record, the options)
        named = {"count_key": self.count_key, **done_names}
        if self.decision_key is not None:
            named["decision_key"] = self.decision_key
        named.update({f"option_keys[{i}]": k for i, k in enumerate(self.option_keys)})
        named = check_distinct_keys(named, "DecisionCounter")
        done_keys = [named[name] for name in done_names]
        self.done_key: NestedKey | list[NestedKey] = done_keys if isinstance(done_key, list) else done_keys[0]
        # an explicit truncation entry, or None: the "truncated" next to the first done entry followed
        self._truncated_key = None if truncated_key is None else unravel_key(truncated_key)
        check_distinct_keys({**named, "truncated_key": truncated_key or sibling_key(done_keys[0], "truncated")},
                            "DecisionCounter")  # fmt: skip
        super().__init__(in_keys=[], out_keys=[self.count_key])

    # ------------------------------------------------------------------ specs
    @property
    def truncated_key(self) -> NestedKey:
        """The truncation entry written: ``truncated_key``, or the ``"truncated"`` next to the first done entry."""
        if "_done_plan_cache" not in self.__dict__ and self.parent is None:  # not appended yet: as named
            first = self.done_key[0] if isinstance(self.done_key, list) else self.done_key
            return self._truncated_key or sibling_key(first, "truncated")
        return self._done_plan()[0][1]

    @property
    def done_keys(self) -> list[NestedKey]:
        """The done entries followed in the env (``done_key`` looked up in its done spec); the first is the count's."""
        return [key for key, _, _ in self._done_plan()]

    @property
    def reset_key(self) -> NestedKey:
        """The ``"_reset"`` next to the first done entry: the one that restarts the count."""
        return reset_key(self.done_keys[0])

    def _done_plan(self) -> list[tuple[NestedKey, NestedKey, FlagToState | None]]:
        """``(done key, its truncation entry, map of the count's shape onto it)`` per done entry followed; the first
        one's map is None (it has the count's shape)."""
        plan = self.__dict__.get("_done_plan_cache")
        if plan is None:
            keys, done_spec = followed_done_entries(self, self.done_key, "DecisionCounter")
            shape = done_spec[keys[0]].shape
            plan = [(keys[0], self._truncated_key or sibling_key(keys[0], "truncated"), None)] + [
                (key, sibling_key(key, "truncated"), FlagToState(shape, done_spec[key].shape, key, "DecisionCounter"))
                for key in keys[1:]
            ]
            self.__dict__["_done_plan_cache"] = plan
        return plan

    def _record_maps(self) -> list[FlagToState]:
        """Maps of the decision record and of each running option entry onto the count's shape."""
        maps = self.__dict__.get("_record_maps_cache")
        if maps is None:
            observation_spec = self.parent.full_observation_spec
            shape = self.parent.full_done_spec[self.done_keys[0]].shape
            maps = [FlagToState(observation_spec[key].shape, shape, key, "DecisionCounter")
                    for key in (self.decision_key, *self.option_keys)]  # fmt: skip
            self.__dict__["_record_maps_cache"] = maps
        return maps

    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        self.__dict__.pop("_done_plan_cache", None)
        self.__dict__.pop("_record_maps_cache", None)
        if self.parent is not None:  # a missing executor fails here, when the counter is appended
            self._check_keys(self.parent.full_observation_spec, self.parent.full_done_spec)

    def empty_cache(self) -> None:
        self.__dict__.pop("_done_plan_cache", None)
        self.__dict__.pop("_record_maps_cache", None)
        super().empty_cache()

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state.pop("_done_plan_cache", None)
        state.pop("_record_maps_cache", None)
        return state

    def _check_keys(self, observation_spec: Composite, done_spec: Composite) -> None:
        keys = set(observation_spec.keys(True, True))
        if self.decision_key is not None:
            missing = [k for k in (self.decision_key, *self.option_keys) if k not in keys]
            if missing:
                argument = "decision_key" if self.decision_key in missing else "option_keys"
                raise ValueError(
                    f"DecisionCounter: {argument} entry {missing[0]!r} is not in the env's observation spec: "
                    "append the DecisionCounter after an OptionExecutor (with the executor's level, or its "
                    "decision_key and option_keys), or pass level=None to count every step. Found "
                    f"{sorted(keys, key=str)}."
                )
        self._done_plan()  # raises for a done_key naming no done entry
        if self.decision_key is not None:
            self._record_maps()

    def _count_spec(self, done_spec: Composite, device) -> Bounded:
        shape = done_spec[self.done_keys[0]].shape
        return Bounded(0, torch.iinfo(torch.int64).max, shape=shape, dtype=torch.int64, device=device)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        done_spec = self.parent.full_done_spec
        self._check_keys(observation_spec, done_spec)
        observation_spec[self.count_key] = self._count_spec(done_spec, observation_spec.device)
        return observation_spec

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        # the count is also the state carried from step to step (as StepCounter's step_count)
        if input_spec["full_state_spec"] is None:
            input_spec["full_state_spec"] = Composite(shape=input_spec.shape, device=input_spec.device)
        input_spec["full_state_spec", self.count_key] = self._count_spec(self.parent.full_done_spec, input_spec.device)
        return input_spec

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        output_spec = super().transform_output_spec(output_spec)
        done_spec = output_spec["full_done_spec"]
        for done_key, truncated_key, _ in self._done_plan():
            if truncated_key not in done_spec.keys(True, True):
                done = done_spec[done_key]
                done_spec[truncated_key] = Categorical(2, shape=done.shape, dtype=torch.bool, device=done.device)
        return output_spec

    # ------------------------------------------------------------ env hooks
    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        count = tensordict.get(self.count_key, None)
        if count is None:
            raise KeyError(
                f"DecisionCounter: {self.count_key!r} is missing from the input of env.step. Reset the env first "
                "and pass the tensordict returned by reset/step_mdp."
            )
        plan = self._done_plan()
        done_key, truncated_key, _ = plan[0]
        done = next_tensordict.get(done_key)
        if self.decision_key is None:
            # no executor: every step is a decision, over after the step
            count = count + 1
            over = torch.ones_like(done)
        else:
            decision = next_tensordict.get(self.decision_key, None)
            if decision is None:
                raise ValueError(
                    f"DecisionCounter: decision_key {self.decision_key!r} is missing from the step's output: "
                    "append the DecisionCounter after the OptionExecutor (or pass level=None)."
                )
            to_count, *option_maps = self._record_maps()
            count = count + to_count(decision)
            # the decision made last is over when no option runs any more: the next step is a decision
            running = None
            for key, to_count in zip(self.option_keys, option_maps):
                runs = to_count(next_tensordict.get(key) >= 0)
                running = runs if running is None else running | runs
            over = ~running
        truncated = (count >= self.max_decisions) & over
        previous = next_tensordict.get(truncated_key, None)
        if previous is not None:
            truncated = truncated | previous
        next_tensordict.set(self.count_key, count)
        next_tensordict.set(truncated_key, truncated)
        next_tensordict.set(done_key, done | truncated)
        for key, entry_truncated, to_entry in plan[1:]:  # the truncation carried to the other done entries
            cut = to_entry(truncated)
            previous = next_tensordict.get(entry_truncated, None)
            next_tensordict.set(entry_truncated, cut if previous is None else previous | cut)
            next_tensordict.set(key, next_tensordict.get(key) | cut)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        plan = self._done_plan()
        done = tensordict_reset.get(plan[0][0])
        reset = tensordict.get(reset_key(plan[0][0]), None) if tensordict is not None else None
        prev = tensordict.get(self.count_key, None) if tensordict is not None else None
        if reset is None or prev is None:
            count = torch.zeros(done.shape, dtype=torch.int64, device=done.device)
        else:
            # only the envs flagged by "_reset" start again (TorchRL also merges the others back afterwards)
            count = torch.where(reset.reshape(done.shape), 0, prev.reshape(done.shape))
        tensordict_reset.set(self.count_key, count)
        for done_key, truncated_key, _ in plan:
            if tensordict_reset.get(truncated_key, None) is None:
                tensordict_reset.set(truncated_key, torch.zeros_like(tensordict_reset.get(done_key)))
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "DecisionCounter runs inside an environment step (like StepCounter); it has no replay-buffer mode."
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(max_decisions={self.max_decisions}, level={self.level}, "
            f"count_key={self.count_key!r})"
        )
