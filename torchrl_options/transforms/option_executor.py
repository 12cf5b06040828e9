"""Options that run to termination inside a TorchRL environment.

An option (Sutton, Precup and Singh, 1999) is a control policy ``pi_k(a | s)`` plus a termination condition
``beta_k(s)``. Once an option is chosen it keeps control until it terminates, which suspends the agent's own
exploration for that time (Fox et al., 2017, "Multi-Level Discovery of Deep Options", section 1). The
:class:`OptionExecutor` transform runs options *inside* the environment step, so any TorchRL env, batched
env, collector, exploration module and loss works unchanged on the augmented action space
``{0 .. A-1} U {A .. A+K-1}``.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Bounded, Categorical, Composite, OneHot
from torchrl.envs import EnvBase, Transform

from torchrl_options.checks import check_distinct_keys
from torchrl_options.transforms.keys import FlagToState, done_key_arguments, followed_done_entries, level_key, reset_key

logger = logging.getLogger(__name__)

__all__ = ["OptionExecutor"]

_NO_OPTION = -1
# runtime caches kept in the instance __dict__ (as TorchRL's StepCounter does): rebuilt on demand, dropped by
# empty_cache, set_container, clone and pickling
_CACHES = ("_base_spec_cache", "_consts", "_compiled_options", "_done_plan_cache")


class OptionExecutor(Transform):
    r"""Runs options (control policy + termination) inside the environment step.

    Appended to an env whose action spec is ``Categorical(A)``, the policy-facing action becomes
    ``Categorical(A + K)``: an action ``a < A`` is a primitive action and ``A + k`` starts option ``k``.
    With ``primitive_actions=False`` the policy sees ``Categorical(K)`` and every decision starts an option.

    While option ``k`` runs, the action written by the policy (whatever an exploration module drew) is
    ignored and the env receives ``a_t ~ pi_k(. | s_t)`` (``argmax`` with ``greedy=True``). After the step
    the option terminates with probability ``sigmoid(termination_logits[k])`` evaluated at ``s_{t+1}`` (the
    state it lands in); the end of an episode (done, truncated or reset) also ends it. The step after a
    termination, and the first step of every episode, is a *decision*: the policy's action is used.
    Fox et al., 2017, sections 1, 3.4 and 5.

    **Done entries**: as TorchRL's :class:`~torchrl.envs.transforms.StepCounter`, the executor follows every
    done entry of the env (by default the ``"done"`` next to each of its reset keys: the root ``"done"``, and
    nested ones such as ``("agents", "done")`` in a multi-agent env), each with the ``"_reset"`` next to it. Any
    of them ends the option of the envs (or agents) it covers, and a reset starts afresh exactly the entries
    whose ``"_reset"`` is set. A done entry coarser than the action (a root ``"done"`` ``[*B, 1]`` for per-agent
    actions ``[*B, n_agents]``) covers all the agents of its env; a finer one (per-agent dones for a root action)
    ends the option when any of its agents is done.

    ``options`` is any TensorDict module that reads the observation and writes ``option_logits``
    ``[..., K, A]`` and ``termination_logits`` ``[..., K]`` (a DDO options module or a hand-written one).
    It runs under ``torch.no_grad``, once per state, when the state is observed (in the step that lands
    there, or the reset): its termination logits decide whether the running option ends there, and each
    option's action at that state is drawn right away and kept in the ``"option_actions"`` entry, so the
    next step reads it instead of running the options again. State lives in the tensordict, as for
    TorchRL's :class:`~torchrl.envs.transforms.StepCounter`, so the executor works unchanged in batched envs,
    collectors and worker processes.

    Entries (their names follow ``level``, see below); all but ``"option_actions"`` have the shape of the
    action:

    - ``"option"`` (state, observation spec): the option running at the start of the step, ``-1`` for
      none. ``data["next", "option"][t] == -1`` exactly when step ``t + 1`` is a decision.
    - ``"option_actions"`` (state, observation spec, ``[..., K]``): the action each option takes at this
      state if it is in control here (drawn when the state was observed, from the options' parameters of
      that time).
    - ``("next", "executed_action")``: the action the env below received (the primitive action at level 1;
      ``-1`` in a reset tensordict).
    - ``("next", "executed_option")``: the option in control at this step, ``-1`` when the policy's
      primitive action was executed.
    - ``("next", "option_decision")``: ``True`` when the policy's ``data["action"][t]`` was used. On other
      steps ``data["action"][t]`` holds the policy's ignored action.

    Since they are observations, TorchRL also copies these entries to the root of the following step.

    **Hierarchies** (call-and-return): an executor with ``level=2`` appended to an env that already
    has a level-1 executor sees the level-1 augmented space ``A + K1`` as its primitive actions, so its
    options (``option_logits`` ``[..., K2, A + K1]``) choose among primitive actions and level-1 options.
    While a level-1 option invoked by a level-2 option runs, the level-2 option neither acts nor
    terminates: it regains control, and has its termination checked, only once the level-1 option has
    terminated. Level ``L > 1`` entries carry the suffix ``_L`` (``"option_2"``, ``"executed_action_2"``,
    ``"executed_option_2"``, ``"option_decision_2"``, ``"option_actions_2"``), and the level below is
    watched through its ``"option"`` entry (``lower_option_key``), so the records of the two levels never
    clash. Each key can also be set explicitly.

    **Randomness** (option actions and terminations): as TorchRL's transforms do, the executor draws from
    torch's default generator of the env's device, so ``torch.manual_seed`` makes a run reproducible, and
    inside :class:`~torchrl.envs.ParallelEnv` workers and multi-process collectors the worker's
    ``set_seed`` seeds it. :meth:`set_seed` gives the executor a private generator instead (its draws then
    do not depend on, nor shift, those of the policy or of other code). ``env.set_seed`` does not reach
    transforms in TorchRL.

    **Bad input**: an action outside ``[0, A + K)`` and options writing NaN (or logits whose softmax is not
    defined: a ``+inf``, or only ``-inf`` for an option) raise a ``ValueError``. On CPU it is raised by the
    step that received them. On CUDA nothing waits for the device: the step runs with the action clamped
    into range (the option's action drawn as the last action), a device-side flag records the fault, and the
    ``ValueError`` is raised by a later step as soon as the flag has reached the host (usually the next one)
    and at the latest by the next reset.

    Args:
        options (TensorDictModuleBase): writes ``option_logits`` ``[..., K, A]`` and ``termination_logits``
            ``[..., K]`` from the observation.
        num_options (int): ``K``.

    Keyword Args:
        primitive_actions (bool, optional): if ``True`` (default) the policy chooses among ``A`` primitive
            actions and ``K`` options (``Categorical(A + K)``); if ``False``, among options only
            (``Categorical(K)``).
        greedy (bool, optional): options act with the ``argmax`` of their action logits instead of
            sampling. Defaults to ``False``.
        level (int, optional): level of the executor in a hierarchy, 1 for the one closest to the env.
            Sets the default key names and ``lower_option_key``. Defaults to ``1``.
        action_key (NestedKey, optional): the action entry. Defaults to ``"action"``.
        done_key (NestedKey or list of NestedKey, optional): the done entries ending options with episodes. A
            string is a leaf name looked up next to each of the env's reset keys (``"done"``: the root one and
            every nested one, see above); a tuple names one nested entry; a list names exactly the entries it
            holds (``["done"]``: the root one only). Defaults to ``"done"``.
        option_key (NestedKey, optional): the running-option state entry.
        executed_action_key (NestedKey, optional): the executed-action record.
        executed_option_key (NestedKey, optional): the executed-option record.
        decision_key (NestedKey, optional): the decision record.
        option_actions_key (NestedKey, optional): the state entry of the options' actions at the current
            state.
        lower_option_key (NestedKey, optional): the running-option entry of the executor below, for
            call-and-return. Defaults to the level ``level - 1`` option key (``None`` at level 1).
        option_logits_key (NestedKey, optional): output of ``options``. Defaults to ``"option_logits"``.
        termination_logits_key (NestedKey, optional): output of ``options``. Defaults to
            ``"termination_logits"``.
        compile_options (bool or dict, optional): call the options through ``torch.compile(options, **kwargs)``
            (``True``: torch's defaults; a dict: the keyword arguments, e.g. ``{"backend": "eager"}``), compiled on
            the first call in each process. On CPU it pays only over long runs: compiling takes seconds (a
            minute with the default backend), and saves tens of microseconds per env step
            (``benchmarks/bench_option_executor.py --compile``). Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.envs import GymEnv, check_env_specs
        >>> from torchrl_options.transforms import OptionExecutor
        >>> class AlwaysPush(torch.nn.Module):  # K=2 options for CartPole: push left / push right, 4 steps on average
        ...     def forward(self, obs):
        ...         logits = torch.tensor([[10.0, -10.0], [-10.0, 10.0]]).expand(*obs.shape[:-1], 2, 2)
        ...         return logits, torch.full((*obs.shape[:-1], 2), -1.1)
        >>> options = TensorDictModule(AlwaysPush(), ["observation"], ["option_logits", "termination_logits"])
        >>> executor = OptionExecutor(options, num_options=2)
        >>> env = GymEnv("CartPole-v1", categorical_action_encoding=True).append_transform(executor)
        >>> env.action_spec.n  # 2 primitive actions + 2 options
        4
        >>> check_env_specs(env)
        >>> _ = env.set_seed(0)
        >>> executor.set_seed(0)  # or torch.manual_seed(0)
        >>> data = env.rollout(10, break_when_any_done=False)
        >>> data["next", "option_decision"].shape, data["next", "executed_action"].dtype
        (torch.Size([10]), torch.int64)
        >>> data["option_actions"].shape  # each option's action at each state
        torch.Size([10, 2])
    """

    invertible = False

    def __init__(
        self,
        options: TensorDictModuleBase,
        num_options: int,
        *,
        primitive_actions: bool = True,
        greedy: bool = False,
        level: int = 1,
        action_key: NestedKey = "action",
        done_key: NestedKey | Sequence[NestedKey] = "done",
        option_key: NestedKey | None = None,
        executed_action_key: NestedKey | None = None,
        executed_option_key: NestedKey | None = None,
        decision_key: NestedKey | None = None,
        option_actions_key: NestedKey | None = None,
        lower_option_key: NestedKey | None | str = "auto",
        option_logits_key: NestedKey = "option_logits",
        termination_logits_key: NestedKey = "termination_logits",
        compile_options: bool | Mapping[str, Any] = False,
    ):
        if isinstance(num_options, bool) or not isinstance(num_options, int) or num_options < 1:
            raise ValueError(f"OptionExecutor: num_options must be a positive int, got {num_options!r}.")
        if isinstance(level, bool) or not isinstance(level, int) or level < 1:
            raise ValueError(f"OptionExecutor: level must be a positive int, got {level!r}.")
        for name, value in (("primitive_actions", primitive_actions), ("greedy", greedy)):
            if not isinstance(value, bool):
                raise TypeError(f"OptionExecutor: {name} must be a bool, got {value!r}.")
        if not callable(options) or not hasattr(options, "out_keys"):
            raise TypeError(
                "OptionExecutor: options must be a TensorDict module (e.g. a tensordict.nn.TensorDictModule) "
                f"with in_keys and out_keys, got {type(options).__name__}."
            )
        out_keys = [unravel_key(k) for k in options.out_keys]
        for key in (option_logits_key, termination_logits_key):
            if unravel_key(key) not in out_keys:
                raise ValueError(
                    f"OptionExecutor: the options module must write {key!r} (expected 'option_logits' "
                    f"[..., K, A] and 'termination_logits' [..., K]); its out_keys are {out_keys}."
                )
        in_keys = getattr(options, "in_keys", None)
        self.option_key = unravel_key(option_key or level_key("option", level))
        self.executed_action_key = unravel_key(executed_action_key or level_key("executed_action", level))
        self.executed_option_key = unravel_key(executed_option_key or level_key("executed_option", level))
        self.decision_key = unravel_key(decision_key or level_key("option_decision", level))
        self.option_actions_key = unravel_key(option_actions_key or level_key("option_actions", level))
        if lower_option_key == "auto":
            lower_option_key = None if level == 1 else level_key("option", level - 1)
        self.lower_option_key = None if lower_option_key is None else unravel_key(lower_option_key)
        self.action_key = unravel_key(action_key)
        done_names = done_key_arguments(done_key, "OptionExecutor")
        self.option_logits_key = unravel_key(option_logits_key)
        self.termination_logits_key = unravel_key(termination_logits_key)
        records = [
            self.option_key,
            self.option_actions_key,
            self.executed_action_key,
            self.executed_option_key,
            self.decision_key,
        ]
        if len(set(records)) != len(records):
            raise ValueError(f"OptionExecutor: the record keys must differ, got {records}.")
        # a record written over the action, the done flag, the lower level's option or the options' outputs
        named = {"option_key": self.option_key, "option_actions_key": self.option_actions_key,
                 "executed_action_key": self.executed_action_key, "executed_option_key": self.executed_option_key,
                 "decision_key": self.decision_key, "action_key": self.action_key, **done_names,
                 "option_logits_key": self.option_logits_key, "termination_logits_key": self.termination_logits_key}
        if self.lower_option_key is not None:
            named["lower_option_key"] = self.lower_option_key
        named = check_distinct_keys(named, "OptionExecutor")  # fmt: skip
        done_keys = [named[name] for name in done_names]
        self.done_key: NestedKey | list[NestedKey] = done_keys if isinstance(done_key, list) else done_keys[0]
        k = getattr(options, "num_options", None)
        if isinstance(k, int) and not isinstance(k, bool) and k != num_options:
            raise ValueError(f"OptionExecutor: num_options={num_options} but the options module has num_options={k}.")
        super().__init__(in_keys=[], out_keys=records)
        self.options = options
        self.num_options = num_options
        self.primitive_actions = primitive_actions
        self.greedy = greedy
        self.level = level
        self._options_in_keys = None if in_keys is None else [unravel_key(k) for k in in_keys]
        if not isinstance(compile_options, (bool, Mapping)):
            raise TypeError(
                "OptionExecutor: compile_options must be a bool or a dict of torch.compile keyword arguments, got "
                f"{compile_options!r}."
            )
        self.compile_options = compile_options if isinstance(compile_options, bool) else dict(compile_options)
        self._seed: int | None = None

    # ------------------------------------------------------------------ specs
    @property
    def num_actions(self) -> int:
        """``A``: the number of actions of the env below (primitive actions, for this level)."""
        return self._base_action_spec().n

    @property
    def num_augmented_actions(self) -> int:
        """Size of the policy-facing action space: ``A + K``, or ``K`` without primitive actions."""
        return self.num_actions * self.primitive_actions + self.num_options

    def _base_action_spec(self) -> Categorical:
        spec = self.__dict__.get("_base_spec_cache")
        if spec is None:
            if self.parent is None:
                raise RuntimeError("OptionExecutor must be appended to an environment.")
            spec = self._check_action_spec(self.parent.full_action_spec)
            self.__dict__["_base_spec_cache"] = spec
        return spec

    def _check_action_spec(self, full_action_spec: Composite) -> Categorical:
        if self.action_key not in full_action_spec.keys(True, True):
            raise ValueError(
                f"OptionExecutor expected an action entry {self.action_key!r} in the env's action spec, "
                f"found {list(full_action_spec.keys(True, True))}."
            )
        spec = full_action_spec[self.action_key]
        if not isinstance(spec, Categorical) or isinstance(spec, OneHot):
            raise TypeError(
                f"OptionExecutor expected a Categorical(A) action spec at {self.action_key!r}, got "
                f"{type(spec).__name__}. Build the env with categorical actions (e.g. GymEnv(..., "
                "categorical_action_encoding=True))."
            )
        return spec

    def _check_observation_keys(self, observation_spec: Composite) -> None:
        """The options' inputs and the level below's running-option entry must be observations."""
        keys = list(observation_spec.keys(True, True))
        if self.lower_option_key is not None and self.lower_option_key not in keys:
            raise ValueError(
                f"OptionExecutor(level={self.level}) expected the running-option entry "
                f"{self.lower_option_key!r} of the executor below it in the observation spec; found {keys}. "
                "Set lower_option_key (None if there is no executor below)."
            )
        missing = [k for k in self._options_in_keys or () if k not in keys]
        if missing:
            raise ValueError(
                f"OptionExecutor: the options module reads {missing}, which the env does not observe (its "
                f"observation spec has {keys})."
            )

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        input_spec = input_spec.clone()
        spec = self._check_action_spec(input_spec["full_action_spec"])
        n = spec.n * self.primitive_actions + self.num_options
        input_spec["full_action_spec", self.action_key] = Categorical(
            n, shape=spec.shape, device=spec.device, dtype=spec.dtype
        )
        return input_spec

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = self._base_action_spec()
        shape, device = spec.shape, spec.device
        K = self.num_options
        self._check_observation_keys(observation_spec)
        observation_spec[self.option_key] = Bounded(-1, K - 1, shape=shape, dtype=torch.int64, device=device)
        observation_spec[self.option_actions_key] = Bounded(
            0, spec.n - 1, shape=(*shape, K), dtype=spec.dtype, device=device
        )
        observation_spec[self.executed_option_key] = Bounded(
            -1, K - 1, shape=shape, dtype=torch.int64, device=device
        )
        observation_spec[self.executed_action_key] = Bounded(
            -1, spec.n - 1, shape=shape, dtype=spec.dtype, device=device
        )
        observation_spec[self.decision_key] = Categorical(2, shape=shape, dtype=torch.bool, device=device)
        return observation_spec

    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        self._drop_caches()
        self.__dict__.pop("_generators", None)  # a clone attached to another env restarts from the seed
        parent = self.parent
        if parent is not None:  # a wrong action spec or missing inputs fail here, when the executor is appended
            spec = self._base_action_spec()
            self._done_plan()
            self._check_observation_keys(parent.observation_spec)
            a = getattr(self.options, "num_actions", None)
            if isinstance(a, int) and not isinstance(a, bool) and a != spec.n:
                raise ValueError(
                    f"OptionExecutor (level {self.level}): the options choose among num_actions={a} actions, but the "
                    f"env below the executor has {spec.n} ({self.action_key!r}); options of level j choose among the "
                    "actions of the env with the levels below j."
                )

    @property
    def done_keys(self) -> list[NestedKey]:
        """The done entries the executor follows in its env (``done_key`` looked up in the env's done spec)."""
        return [key for key, _, _ in self._done_plan()]

    def _done_plan(self) -> list[tuple[NestedKey, NestedKey, FlagToState]]:
        """``(done key, its reset key, the map of its flags onto the executor's state)`` per followed done entry."""
        plan = self.__dict__.get("_done_plan_cache")
        if plan is None:
            keys, done_spec = followed_done_entries(self, self.done_key, "OptionExecutor")
            state_shape = self._base_action_spec().shape
            plan = [(key, reset_key(key), FlagToState(done_spec[key].shape, state_shape, key, "OptionExecutor"))
                    for key in keys]  # fmt: skip
            self._check_state_nodes(keys)
            self.__dict__["_done_plan_cache"] = plan
        return plan

    def _check_state_nodes(self, done_keys: list[NestedKey]) -> None:
        """The state entries must lie under the node of a followed done entry: TorchRL merges a partial reset node
        by node (``"_reset"`` at ``(*node, "_reset")`` updates the entries under ``node``), so a state entry outside
        every such node would keep its value from before the reset."""
        nodes = [() if isinstance(key, str) else key[:-1] for key in done_keys]
        for name, key in (("option_key", self.option_key), ("option_actions_key", self.option_actions_key),
                          ("executed_action_key", self.executed_action_key),
                          ("executed_option_key", self.executed_option_key), ("decision_key", self.decision_key)):
            path = () if isinstance(key, str) else key[:-1]
            if not any(path[: len(node)] == node for node in nodes):
                raise ValueError(
                    f"OptionExecutor: the state entry {key!r} ({name}) lies outside every node of the done entries "
                    f"it follows ({done_keys}): TorchRL would not reset it with them. Put it next to them, e.g. "
                    f"{name}={(*nodes[0], key if isinstance(key, str) else key[-1])!r}."
                )

    def empty_cache(self) -> None:
        self._drop_caches()
        super().empty_cache()

    def _drop_caches(self) -> None:
        for name in _CACHES:
            self.__dict__.pop(name, None)

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        for name in (*_CACHES, "_generators"):
            state.pop(name, None)
        return state

    # ----------------------------------------------------------- randomness
    def set_seed(self, seed: int | None) -> None:
        """Gives the executor a private generator seeded with ``seed`` (``None``: back to torch's default one).

        Without it the options' action and termination draws come from torch's default generator of the env's
        device, as for TorchRL's transforms (``torch.manual_seed`` seeds it).
        """
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise TypeError(f"OptionExecutor.set_seed: seed must be an int or None, got {seed!r}.")
        self._seed = seed
        self.__dict__.pop("_generators", None)
        self.__dict__.pop("_consts", None)  # they hold the generator of the draws

    @property
    def generator(self) -> torch.Generator | None:
        """The private generator of the draws on the env's device (``None`` when torch's default one is used).

        Its ``get_state`` / ``set_state`` save and restore the executor's random state.
        """
        if self._seed is None:
            return None
        return self._generator(torch.device(self._base_action_spec().device or "cpu"))

    def _generator(self, device: torch.device) -> torch.Generator | None:
        if self._seed is None:
            return None
        generators = self.__dict__.setdefault("_generators", {})
        generator = generators.get(device)
        if generator is None:
            generator = generators[device] = torch.Generator(device=device)
            generator.manual_seed(self._seed % (2**63))
        return generator

    # -------------------------------------------------------------- options
    def _constants(self, device: torch.device) -> _StepConstants:
        """Sizes, lookup table and bad-input flags of the per-step code, built once per device."""
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != device:
            spec = self._base_action_spec()
            A, K = spec.n, self.num_options
            shift = A if self.primitive_actions else 0
            n = spec.shape.numel()
            consts = _StepConstants(
                device=device,
                A=A,
                K=K,
                n_aug=shift + K,
                shape=spec.shape,
                logits_shape=torch.Size((*spec.shape, K, A)),
                term_shape=torch.Size((*spec.shape, K)),
                n=n,
                dtype=spec.dtype,
                # augmented action -> the option it starts at a decision, -1 for a primitive action
                decode=(torch.arange(shift + K, device=device) - shift).clamp_min(_NO_OPTION),
                arange=torch.arange(n, device=device),
                no_option=torch.tensor(_NO_OPTION, device=device),
                # buffers the uniforms are drawn into (torch.rand without an allocation); no output references them
                u_actions=torch.empty((*spec.shape, K, 1), device=device),
                u_terminations=torch.empty(spec.shape, device=device),
                deferred=_DeferredFlags(device) if _defers_checks(device) else None,
                generator=self._generator(device),
            )
            self.__dict__["_consts"] = consts
        return consts

    def _evaluate_options(
        self, tensordict: TensorDictBase, consts: _StepConstants
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each option's action ``[*batch, K]`` drawn at the state of ``tensordict``, and the termination logits
        ``[*batch, K]`` there.

        Per-state code (it runs in every step and reset): a fixed sequence of small tensor ops; the shapes are
        checked in full only when they differ from the expected ones.
        """
        logits, term = self._run_options(tensordict)
        if logits.shape != consts.logits_shape or term.shape != consts.term_shape:
            logits, term = self._reshape_outputs(logits, term, consts)
        if self.greedy:
            actions = logits.argmax(-1)
            probs = logits  # its sums are NaN if a row has a NaN (or both infinities)
        else:
            # inverse-CDF draw, one uniform per env and option (the same draws as torch.rand into a float32
            # buffer, whatever the options' dtype); right=True never picks a zero-probability action, the clamp
            # keeps rounding (a CDF ending below u) from giving A
            probs = logits.softmax(-1).cumsum(-1)  # the CDF: a row is NaN if its softmax is
            u = consts.u_actions.uniform_(generator=consts.generator)
            if u.dtype is not probs.dtype:
                u = u.to(probs.dtype)
            actions = torch.searchsorted(probs, u, right=True).squeeze(-1).clamp_max_(consts.A - 1)
        if consts.deferred is None:
            # one sum per output tells whether anything is NaN; a false alarm (from infinite logits of both signs)
            # is cleared by the exact check
            s = float(probs.sum()) + float(term.sum())
            if s != s:
                self._check_options_outputs(consts, probs, logits, term)
        else:
            self._check_options_outputs(consts, probs, logits, term)
        return (actions if actions.dtype is consts.dtype else actions.to(consts.dtype)), term

    def _reshape_outputs(
        self, logits: torch.Tensor, term: torch.Tensor, consts: _StepConstants
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The options' outputs checked and reshaped to ``[*batch, K, A]`` and ``[*batch, K]``."""
        K, A, shape = consts.K, consts.A, consts.shape
        if logits.shape[-2:] != (K, A) or logits.shape[:-2].numel() != shape.numel():
            raise ValueError(
                f"OptionExecutor: the options module wrote {self.option_logits_key!r} of shape "
                f"{tuple(logits.shape)}; expected [*batch, K={K}, A={A}] with batch {tuple(shape)}."
            )
        if term.shape[-1] != K or term.shape[:-1].numel() != shape.numel():
            raise ValueError(
                f"OptionExecutor: the options module wrote {self.termination_logits_key!r} of shape "
                f"{tuple(term.shape)}; expected [*batch, K={K}] with batch {tuple(shape)}."
            )
        if logits.shape[:-2] != shape:
            logits = logits.reshape(*shape, K, A)
        if term.shape[:-1] != shape:
            term = term.reshape(*shape, K)
        return logits, term

    def _run_options(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """The options' ``(option_logits, termination_logits)`` at the state of ``tensordict``, without gradients.

        The options module is called through its public TensorDict call, on a tensordict holding the entries it
        reads (so its outputs never land in the env's data); compiled first when ``compile_options`` asks for it.
        """
        keys = self._options_in_keys
        if keys is None:
            inputs = tensordict.copy()
        else:
            try:
                inputs = tensordict.select(*keys)
            except KeyError:
                missing = [key for key in keys if tensordict.get(key, None) is None]
                raise ValueError(
                    f"OptionExecutor: the options module reads {missing}, missing from the env's output (it has "
                    f"{list(tensordict.keys(True, True))})."
                ) from None
        options = self.__dict__.get("_compiled_options")
        if options is None:
            options = self._options_call()
        try:
            if torch.is_grad_enabled():
                with torch.no_grad():
                    out = options(inputs)
            else:
                out = options(inputs)
        except (RuntimeError, ValueError) as err:  # e.g. options built for another observation size: say so
            raise self._options_error(tensordict, err) from err
        logits, term = out.get(self.option_logits_key, None), out.get(self.termination_logits_key, None)
        if logits is None or term is None:
            raise ValueError(
                f"OptionExecutor: the options module did not write {self.option_logits_key!r} and "
                f"{self.termination_logits_key!r}; it wrote {list(out.keys(True, True))}."
            )
        return logits, term

    def _options_call(self) -> TensorDictModuleBase:
        """The options module, or its ``torch.compile`` (kept as a runtime cache) with ``compile_options``."""
        if not self.compile_options:
            return self.options
        kwargs = {} if self.compile_options is True else dict(self.compile_options)
        compiled = torch.compile(self.options, **kwargs)
        self.__dict__["_compiled_options"] = compiled
        return compiled

    def _options_error(self, tensordict: TensorDictBase, err: Exception) -> ValueError:
        keys = self._options_in_keys if self._options_in_keys is not None else list(tensordict.keys(True, True))
        shapes = {
            key: tuple(tensordict.get(key).shape) for key in keys if isinstance(tensordict.get(key, None), torch.Tensor)
        }
        return ValueError(
            f"OptionExecutor: the options module failed on the env's observations (shapes {shapes}, batch "
            f"{tuple(tensordict.batch_size)}); were the options built for this env's observation size? "
            f"the module said: {err}"
        )

    # ---------------------------------------------------------------- checks
    def _check_options_outputs(
        self, consts: _StepConstants, probs: torch.Tensor, logits: torch.Tensor, term: torch.Tensor
    ) -> None:
        """Raises (CPU) or flags for a later step (CUDA) a NaN in ``term`` or an unusable row of action logits.

        ``probs`` is the CDF of the action draw (its last column is NaN for a row whose softmax is not defined) or,
        with ``greedy=True``, the logits (a row sums to NaN if it has a NaN, or infinities of both signs).
        """
        total = probs.sum(-1) if self.greedy else probs[..., -1]
        if consts.deferred is None:
            if torch.isnan(total).any() or torch.isnan(term).any():
                raise ValueError(self._nan_message(logits, term))
        else:
            consts.deferred.add(_NAN, torch.isnan(total).any() | torch.isnan(term).any())

    def _raise_deferred(self, consts: _StepConstants, wait: bool = False) -> None:
        """Raises for the faults that earlier CUDA steps flagged, once the flags reached the host."""
        if consts.deferred is None:
            return
        faults = consts.deferred.read(wait)
        if faults[_RANGE]:
            raise ValueError(
                self._range_message(None)
                + f" An earlier step on {consts.device} received such an action (checked without waiting for the "
                "device; that step ran it clamped into range)."
            )
        if faults[_NAN]:
            raise ValueError(
                f"OptionExecutor: the options module wrote NaN (or logits without a valid softmax) in "
                f"{self.option_logits_key!r} or {self.termination_logits_key!r} at an earlier step on "
                f"{consts.device} (checked without waiting for the device)."
            )

    def _nan_message(self, logits: torch.Tensor, term: torch.Tensor) -> str:
        if torch.isnan(term).any():
            where, what = self.termination_logits_key, "NaN"
        elif torch.isnan(logits).any():
            where, what = self.option_logits_key, "NaN"
        else:
            where, what = self.option_logits_key, "a row without a valid softmax (a +inf, or only -inf) for an option"
        return (
            f"OptionExecutor: the options module wrote {what} in {where!r}; the options cannot act or terminate "
            "there. Check the options' parameters and inputs."
        )

    def _decode(self, action: torch.Tensor, consts: _StepConstants) -> torch.Tensor:
        """The option that ``action`` starts at a decision (``-1`` for a primitive action).

        The table lookup is also the range check: on the CPU ``gather`` bounds-checks its indices (negative ones
        included) in the same kernel, so valid actions cost no extra op. On CUDA, where an out-of-range index would
        be a device-side assert, the action is clamped into range and the fault flagged (see the class docstring).
        """
        flat = action.dim() == 1
        index = action if flat else action.reshape(-1)
        if index.dtype is not torch.int64:
            index = index.long()
        if consts.deferred is not None:
            clamped = index.clamp(0, consts.n_aug - 1)
            consts.deferred.add(_RANGE, (clamped != index).any())
            index = clamped
        try:
            option = consts.decode.gather(0, index)
        except RuntimeError:
            lo, hi = (int(v) for v in torch.aminmax(index))
            if lo < 0 or hi >= consts.n_aug:
                raise ValueError(self._range_message((lo, hi))) from None
            raise
        return option if flat else option.view(action.shape)

    def _range_message(self, got: tuple[int, int] | None) -> str:
        n_aug = self.num_augmented_actions
        message = (
            f"OptionExecutor: action out of range, expected integers in [0, {n_aug}) "
            f"({self.num_actions * self.primitive_actions} primitive actions + {self.num_options} options)"
        )
        return message + (f", got values in [{got[0]}, {got[1]}]." if got is not None else ".")

    def _state(self, tensordict: TensorDictBase, key: NestedKey) -> torch.Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise ValueError(
                f"OptionExecutor: the state entry {key!r} is missing from the input of env.step. Reset the env "
                "first and pass the tensordict returned by reset/step_mdp."
            )
        return value

    def _lower_ready(self, tensordict: TensorDictBase, shape: torch.Size) -> torch.Tensor:
        """Whether the level below waits for an action (no lower option running)."""
        return self._state(tensordict, self.lower_option_key).reshape(shape) < 0

    # ------------------------------------------------------------ env hooks
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # the option is chosen with the action at s_t and acts at s_t with the action drawn for it when s_t was
        # observed. Per-step code: a fixed sequence of small tensor ops (masks, no branch on tensor values), no
        # host-device sync on CUDA
        action = tensordict.get(self.action_key, None)
        if action is None:
            raise ValueError(f"OptionExecutor: the input of env.step has no action entry {self.action_key!r}.")
        running = tensordict.get(self.option_key, None)
        option_actions = tensordict.get(self.option_actions_key, None)
        if running is None or option_actions is None:
            self._state(tensordict, self.option_key)  # raises, naming the missing entry
            self._state(tensordict, self.option_actions_key)
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != action.device:
            consts = self._constants(action.device)
        if consts.deferred is not None:
            self._raise_deferred(consts)
        started = self._decode(action, consts)  # also the range check
        decision = running < 0
        if self.lower_option_key is not None:
            lower_ready = self._lower_ready(tensordict, action.shape)
            decision = decision & lower_ready
        option = torch.where(decision, started, running)  # -1: the policy's primitive action runs
        # the running option's action (option -1 reads option K-1's, which is then not used)
        option_action = _pick(option_actions, option, consts)
        if option_action.dtype is not action.dtype:
            option_action = option_action.to(action.dtype)
        if self.lower_option_key is None:
            # a running option always acts; otherwise this is a decision for a primitive action
            executed = torch.where(option >= 0, option_action, action) if self.primitive_actions else option_action
        else:
            # call-and-return: this level acts only when the level below waits for an action; otherwise its
            # output is ignored below and any valid action is passed
            acting = (option >= 0) & lower_ready
            passthrough = action.clamp_max(consts.A - 1) if self.primitive_actions else torch.zeros_like(action)
            executed = torch.where(acting, option_action, passthrough)

        # tensordict is the shallow copy given to the env below: the policy's action stays in the data. The
        # records are stashed under this level's keys: a lower executor in the same Compose rewrites the action
        tensordict.set(self.action_key, executed)
        tensordict.set(self.executed_action_key, executed)
        tensordict.set(self.executed_option_key, option)
        tensordict.set(self.decision_key, decision)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        option = tensordict.get(self.executed_option_key)
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != option.device:
            consts = self._constants(option.device)
        # the options at s_{t+1}: the termination of the running option, and each option's action there
        option_actions, term_logits = self._evaluate_options(next_tensordict, consts)
        # option -1 (primitive) reads column K-1: its draw is not used, the option stays -1
        term_logits = _pick(term_logits, option, consts)
        u = consts.u_terminations.uniform_(generator=consts.generator)  # float32: the same draws for any dtype
        if u.dtype is not term_logits.dtype:
            u = u.to(term_logits.dtype)
        terminate = u < term_logits.sigmoid()
        if self.lower_option_key is not None:
            # call-and-return: no termination check while the level below still runs its option
            terminate = terminate & self._lower_ready(next_tensordict, terminate.shape)
        # the end of an episode (any followed done entry) ends the option too; option == -1 stays -1
        ends = terminate
        for done_key, _, to_state in self._done_plan():
            done = next_tensordict.get(done_key, None)
            if done is None:
                raise ValueError(f"OptionExecutor: the env's output has no done entry {done_key!r} (done_key).")
            ends = ends | to_state(done)
        next_tensordict.set(self.option_key, torch.where(ends, consts.no_option, option))
        next_tensordict.set(self.option_actions_key, option_actions)
        next_tensordict.set(self.executed_action_key, tensordict.get(self.executed_action_key))
        next_tensordict.set(self.executed_option_key, option)
        next_tensordict.set(self.decision_key, tensordict.get(self.decision_key))
        if consts.deferred is not None:
            consts.deferred.publish()
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        spec = self._base_action_spec()
        shape = spec.shape
        device = torch.device(spec.device or "cpu")
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != device:
            consts = self._constants(device)
        self._raise_deferred(consts, wait=True)  # resets already wait for the device (done.any())
        option_actions, _ = self._evaluate_options(tensordict_reset, consts)
        reset = self._reset_mask(tensordict)
        # a new episode starts with a decision; the records are empty (-1 / False) until its first step. Only
        # envs flagged by "_reset" change (TorchRL also keeps the entries of the other envs after _reset)
        entries = (
            (self.option_key, _NO_OPTION, torch.int64),
            (self.executed_option_key, _NO_OPTION, torch.int64),
            (self.executed_action_key, _NO_OPTION, spec.dtype),
            (self.decision_key, False, torch.bool),
        )
        for key, default, dtype in entries:
            prev = tensordict.get(key, None) if reset is not None else None
            if prev is None:
                value = torch.full(shape, default, dtype=dtype, device=device)
            else:
                value = torch.where(reset, default, prev if prev.shape == shape else prev.reshape(shape))
            tensordict_reset.set(key, value)
        prev = tensordict.get(self.option_actions_key, None) if reset is not None else None
        if prev is not None:
            if prev.shape != option_actions.shape:
                prev = prev.reshape(option_actions.shape)
            option_actions = torch.where(reset.unsqueeze(-1), option_actions, prev)
        tensordict_reset.set(self.option_actions_key, option_actions)
        if consts.deferred is not None:
            consts.deferred.publish()
        return tensordict_reset

    def _reset_mask(self, tensordict: TensorDictBase | None) -> torch.Tensor | None:
        """The state entries a reset starts afresh: those flagged by the ``"_reset"`` of any followed done entry,
        mapped onto the state's shape; ``None`` (all of them) when a reset entry is missing (as for TorchRL's
        ``StepCounter``)."""
        if tensordict is None:
            return None
        mask = None
        for _, key, to_state in self._done_plan():
            flag = tensordict.get(key, None)
            if flag is None:
                return None
            flag = to_state(flag)
            mask = flag if mask is None else mask | flag
        return mask

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "OptionExecutor runs inside an environment step; it has no replay-buffer (forward) mode. "
            "Use torchrl_options.data.SMDPTransform (a replay-buffer transform) or SMDPTransitions to turn its "
            "step-level data into decisions."
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_options={self.num_options}, primitive_actions={self.primitive_actions}, "
            f"greedy={self.greedy}, level={self.level}, option_key={self.option_key!r})"
        )


_RANGE, _NAN = 0, 1  # bad-input flags


def _defers_checks(device: torch.device) -> bool:
    """Whether bad-input checks on ``device`` are deferred (CUDA: reading a device value on the host would wait)."""
    return device.type == "cuda"


class _DeferredFlags:
    """Bad-input flags set on the device and read by the host without waiting for the device.

    ``add`` ORs a flag on the device; ``publish`` starts a copy of the flags to (pinned) host memory, non-blocking on
    CUDA, and records an event; ``read`` looks at the last copy once its event has completed (``wait=True`` waits for
    it) and clears the flags it reports. Flags stay set until read, so a fault is never lost between two reads.
    """

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.flags = torch.zeros(2, dtype=torch.bool, device=device)
        self.host = torch.zeros(2, dtype=torch.bool, pin_memory=self.cuda)
        self.event = torch.cuda.Event() if self.cuda else None
        self.published = False

    def add(self, kind: int, invalid: torch.Tensor) -> None:
        self.flags[kind].logical_or_(invalid)

    def publish(self) -> None:
        self.host.copy_(self.flags, non_blocking=self.cuda)
        if self.event is not None:
            self.event.record()
        self.published = True

    def read(self, wait: bool = False) -> list[bool]:
        if not self.published:
            return [False, False]
        if self.event is not None:
            if wait:
                self.event.synchronize()
            elif not self.event.query():
                return [False, False]
        faults = self.host.tolist()
        if any(faults):  # reported once
            self.flags.zero_()
            self.host.zero_()
            self.published = False
        return faults


class _StepConstants(NamedTuple):
    device: torch.device
    A: int  # actions of the env below
    K: int  # options
    n_aug: int  # policy-facing actions
    shape: torch.Size  # action shape (the env's batch)
    logits_shape: torch.Size  # [*shape, K, A]: the expected option logits
    term_shape: torch.Size  # [*shape, K]: the expected termination logits
    n: int  # envs in the batch
    dtype: torch.dtype  # action dtype
    decode: torch.Tensor  # [n_aug]: augmented action -> option started (-1: primitive)
    arange: torch.Tensor  # [n]
    no_option: torch.Tensor  # -1, 0-dim
    u_actions: torch.Tensor  # [*shape, K, 1] float32 buffer of the action draws
    u_terminations: torch.Tensor  # [*shape] float32 buffer of the termination draws
    deferred: _DeferredFlags | None  # CUDA: bad-input flags read without a sync (None: checked at once)
    generator: torch.Generator | None  # None: torch's default generator


def _pick(table: torch.Tensor, option: torch.Tensor, consts: _StepConstants) -> torch.Tensor:
    """``table[..., option]`` per env: ``[*batch, K]`` and ``[*batch]`` -> ``[*batch]``; option ``-1`` reads column
    ``K - 1`` (a value then not used)."""
    if len(consts.shape) == 1:
        return table[consts.arange, option]
    return table.reshape(consts.n, consts.K)[consts.arange, option.reshape(-1)].view(consts.shape)

