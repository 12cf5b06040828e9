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
from collections.abc import Sequence
from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Bounded, Categorical, Composite, OneHot
from torchrl.envs import EnvBase, Transform

logger = logging.getLogger(__name__)

__all__ = ["OptionExecutor"]

_NO_OPTION = -1


def _level_key(name: str, level: int) -> str:
    return name if level == 1 else f"{name}_{level}"


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

    ``options`` is any TensorDict module that reads the observation and writes ``option_logits``
    ``[..., K, A]`` and ``termination_logits`` ``[..., K]`` (a DDO options module or a hand-written one).
    It runs under ``torch.no_grad``, once per step: on ``s_{t+1}`` for the termination of the running
    option, and the same outputs give the option's action at the next step (they are recomputed only when
    the observation or the options' parameters changed in between, e.g. after a reset). Besides that
    forward, a step costs a fixed sequence of about 20 small tensor ops, with no host-device
    synchronisation (an out-of-range action still raises a ``ValueError`` naming the expected range).

    Entries (their names follow ``level``, see below), all of the shape of the action:

    - ``"option"`` (state, observation spec): the option running at the start of the step, ``-1`` for
      none. ``data["next", "option"][t] == -1`` exactly when step ``t + 1`` is a decision.
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
    ``"executed_option_2"``, ``"option_decision_2"``), and the level below is watched through its
    ``"option"`` entry (``lower_option_key``), so the records of the two levels never clash. Each key can
    also be set explicitly.

    Randomness (option actions and terminations) comes from a private generator seeded by the env's
    ``set_seed`` (also inside :class:`~torchrl.envs.ParallelEnv` workers). ``TransformedEnv.set_seed``
    does not reach transforms in TorchRL 0.14, so the executor registers itself with the ``set_seed`` of
    the env that contains it; if never seeded it draws its seed from ``torch``'s global generator on first
    use.

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
        done_key (NestedKey, optional): the done entry ending options with episodes. Defaults to ``"done"``.
        option_key (NestedKey, optional): the running-option state entry.
        executed_action_key (NestedKey, optional): the executed-action record.
        executed_option_key (NestedKey, optional): the executed-option record.
        decision_key (NestedKey, optional): the decision record.
        lower_option_key (NestedKey, optional): the running-option entry of the executor below, for
            call-and-return. Defaults to the level ``level - 1`` option key (``None`` at level 1).
        option_logits_key (NestedKey, optional): output of ``options``. Defaults to ``"option_logits"``.
        termination_logits_key (NestedKey, optional): output of ``options``. Defaults to
            ``"termination_logits"``.

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
        >>> env = GymEnv("CartPole-v1", categorical_action_encoding=True).append_transform(
        ...     OptionExecutor(options, num_options=2))
        >>> env.action_spec.n  # 2 primitive actions + 2 options
        4
        >>> check_env_specs(env)
        >>> _ = env.set_seed(0)
        >>> data = env.rollout(10, break_when_any_done=False)
        >>> data["next", "option_decision"].shape, data["next", "executed_action"].dtype
        (torch.Size([10]), torch.int64)
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
        done_key: NestedKey = "done",
        option_key: NestedKey | None = None,
        executed_action_key: NestedKey | None = None,
        executed_option_key: NestedKey | None = None,
        decision_key: NestedKey | None = None,
        lower_option_key: NestedKey | None | str = "auto",
        option_logits_key: NestedKey = "option_logits",
        termination_logits_key: NestedKey = "termination_logits",
    ):
        if not isinstance(num_options, int) or num_options < 1:
            raise ValueError(f"num_options must be a positive int, got {num_options!r}.")
        if not isinstance(level, int) or level < 1:
            raise ValueError(f"level must be a positive int, got {level!r}.")
        out_keys = getattr(options, "out_keys", None)
        if out_keys is not None:
            out_keys = [unravel_key(k) for k in out_keys]
            for key in (option_logits_key, termination_logits_key):
                if unravel_key(key) not in out_keys:
                    raise ValueError(
                        f"The options module must write {key!r} (expected 'option_logits' [..., K, A] and "
                        f"'termination_logits' [..., K]); its out_keys are {out_keys}."
                    )
        self.option_key = unravel_key(option_key or _level_key("option", level))
        self.executed_action_key = unravel_key(executed_action_key or _level_key("executed_action", level))
        self.executed_option_key = unravel_key(executed_option_key or _level_key("executed_option", level))
        self.decision_key = unravel_key(decision_key or _level_key("option_decision", level))
        if lower_option_key == "auto":
            lower_option_key = None if level == 1 else _level_key("option", level - 1)
        self.lower_option_key = None if lower_option_key is None else unravel_key(lower_option_key)
        self.action_key = unravel_key(action_key)
        self.done_key = unravel_key(done_key)
        self.option_logits_key = unravel_key(option_logits_key)
        self.termination_logits_key = unravel_key(termination_logits_key)
        records = [self.option_key, self.executed_action_key, self.executed_option_key, self.decision_key]
        super().__init__(in_keys=[], out_keys=records)
        self.options = options
        self.num_options = num_options
        self.primitive_actions = primitive_actions
        self.greedy = greedy
        self.level = level
        in_keys = getattr(options, "in_keys", None)
        self._options_in_keys = None if in_keys is None else [unravel_key(k) for k in in_keys]
        self._options_params = list(options.parameters()) + list(options.buffers())
        self._generator: torch.Generator | None = None

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
            raise KeyError(
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
        if self.lower_option_key is not None and self.lower_option_key not in observation_spec.keys(True, True):
            raise KeyError(
                f"OptionExecutor(level={self.level}) expected the running-option entry "
                f"{self.lower_option_key!r} of the executor below it in the observation spec; found "
                f"{list(observation_spec.keys(True, True))}. Set lower_option_key (None if there is no "
                "executor below)."
            )
        observation_spec[self.option_key] = Bounded(-1, K - 1, shape=shape, dtype=torch.int64, device=device)
        observation_spec[self.executed_option_key] = Bounded(
            -1, K - 1, shape=shape, dtype=torch.int64, device=device
        )
        observation_spec[self.executed_action_key] = Bounded(
            -1, spec.n - 1, shape=shape, dtype=spec.dtype, device=device
        )
        observation_spec[self.decision_key] = Categorical(2, shape=shape, dtype=torch.bool, device=device)
        return observation_spec

    # ----------------------------------------------------------- randomness
    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        self.__dict__.pop("_base_spec_cache", None)
        self.__dict__.pop("_consts", None)
        self.__dict__.pop("_options_cache", None)
        self._register_seed_hook()
        if self.parent is not None:
            self._base_action_spec()  # a wrong action spec fails here, when the executor is appended

    def _register_seed_hook(self) -> None:
        try:
            env = self.container
        except (AttributeError, ValueError):
            return
        if env is None:
            return
        hook = env.__dict__.get("set_seed")
        if not isinstance(hook, _SeedExecutors):
            env.__dict__["set_seed"] = _SeedExecutors(env)

    def set_seed(self, seed: int) -> None:
        """Seeds the generator of the options' action and termination draws."""
        device = self._base_action_spec().device if self.parent is not None else torch.device("cpu")
        self._generator = torch.Generator(device=device or "cpu")
        self._generator.manual_seed(int(seed) % (2**63))

    def _rng(self) -> torch.Generator:
        if self._generator is None:
            self.set_seed(int(torch.randint(0, 2**62, ())))
        return self._generator

    # -------------------------------------------------------------- options
    def _constants(self, device: torch.device) -> _StepConstants:
        """Sizes, lookup tables and scratch buffers of the per-step code, built once per device."""
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != device:
            spec = self._base_action_spec()
            A, K = spec.n, self.num_options
            n = spec.shape.numel()
            shift = A if self.primitive_actions else 0
            consts = _StepConstants(
                device=device,
                cpu=torch.device(device).type == "cpu",
                A=A,
                K=K,
                n_aug=shift + K,
                shape=spec.shape,
                n=n,
                flat=len(spec.shape) == 1,
                # augmented action -> the option it starts at a decision, -1 for a primitive action
                decode=(torch.arange(shift + K, device=device) - shift).clamp_min(_NO_OPTION),
                arange=torch.arange(n, device=device),
                no_option=torch.tensor(_NO_OPTION, device=device),
                uniform=torch.empty((n, 1), device=device),
                coin=torch.empty(n, device=device),
            )
            self.__dict__["_consts"] = consts
        return consts

    def _params_version(self) -> list[int] | None:
        try:
            return [p._version for p in self._options_params]
        except RuntimeError:  # parameters created in inference mode: no version counter, never cached
            return None

    def _evaluate_options(
        self, tensordict: TensorDictBase, consts: _StepConstants, cache: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``option_logits`` ``[N, K, A]`` and ``termination_logits`` ``[N, K]`` (batch flattened).

        The termination at ``s_{t+1}`` and the action at the next step need the options at the same state:
        the outputs computed in ``_step`` are kept (``cache=True``) and reused by the next ``_inv_call`` when
        it reads the very same input tensors, unmodified since (same objects, same version counters: the
        next observation is passed on by reference by ``step_mdp``; a partial reset or batched env buffers
        writing into them in place bump their versions), and the options' parameters are unchanged. So the
        options run once per step, and no input is copied or compared element-wise (except inference-mode
        tensors, which have no version counter: a copy of them is kept and compared).
        """
        keys = self._options_in_keys
        inputs = None
        if keys is not None:
            inputs = [_get(tensordict, key) for key in keys]
            cached = self.__dict__.get("_options_cache")
            if cached is not None:
                for x, (ref, version, copy) in zip(inputs, cached[0]):
                    if copy is None:  # a tensor with a version counter: the same one, not written since
                        if x is not ref or x._version != version:
                            break
                    elif x is None or x.shape != copy.shape or not torch.equal(x, copy):  # an inference tensor
                        break
                else:
                    params = self._params_version()
                    if params is not None and params == cached[1]:
                        return cached[2], cached[3]
        with torch.no_grad():
            logits, term = self._call_options(tensordict, inputs)
        K, A, n = consts.K, consts.A, consts.n
        if logits is None or term is None:
            raise KeyError(
                f"The options module did not write {self.option_logits_key!r} and "
                f"{self.termination_logits_key!r}."
            )
        if logits.shape[-2:] != (K, A) or logits.shape[:-2].numel() != n:
            raise ValueError(
                f"The options module wrote {self.option_logits_key!r} of shape {tuple(logits.shape)}; "
                f"expected [*batch, K={K}, A={A}] with batch {tuple(consts.shape)}."
            )
        if term.shape[-1] != K or term.shape[:-1].numel() != n:
            raise ValueError(
                f"The options module wrote {self.termination_logits_key!r} of shape {tuple(term.shape)}; "
                f"expected [*batch, K={K}] with batch {tuple(consts.shape)}."
            )
        if logits.dim() != 3:
            logits = logits.reshape(n, K, A)
        if term.dim() != 2:
            term = term.reshape(n, K)
        if cache and inputs is not None:
            entries = _cache_entries(inputs)  # None (no caching) when an input is missing or not a tensor
            if entries is not None:
                self.__dict__["_options_cache"] = (entries, self._params_version(), logits, term)
        return logits, term

    def _call_options(
        self, tensordict: TensorDictBase, inputs: list[torch.Tensor] | None
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        options = self.options
        if (
            inputs is not None
            and type(options) is TensorDictModule
            and options._kwargs is None
            and options.method is None
            and not options.method_kwargs
            and not options._get_kwargs
            and all(x is not None for x in inputs)
        ):
            # hot path: TensorDictModule.forward costs more than a small MLP (dispatch, output wrapping)
            out = options.module(*inputs)
            out = dict(zip(options.out_keys_source, out if isinstance(out, tuple) else (out,)))
            return out.get(self.option_logits_key), out.get(self.termination_logits_key)
        keys = self._options_in_keys
        out = options(tensordict.select(*keys, strict=False) if keys is not None else tensordict.copy())
        return out.get(self.option_logits_key, None), out.get(self.termination_logits_key, None)

    def _lower_ready(self, tensordict: TensorDictBase, shape: torch.Size) -> torch.Tensor | bool:
        """Whether the level below waits for an action (no lower option running)."""
        if self.lower_option_key is None:
            return True
        return _get(tensordict, self.lower_option_key).reshape(shape) < 0

    def _decode(self, action: torch.Tensor, consts: _StepConstants) -> torch.Tensor:
        """The option that ``action`` starts at a decision (``-1`` for a primitive action).

        The table lookup is also the range check: ``gather`` bounds-checks its indices (negative ones
        included) in the same kernel, so valid actions cost no extra op and no host-device sync. On an
        accelerator, where the lookup would only fail with a device-side assert, the range is asserted
        asynchronously first (``torch._assert_async``, with the same message).
        """
        index = action if action.dim() == 1 else action.reshape(-1)
        if index.dtype is not torch.int64:
            index = index.long()
        if not consts.cpu:
            torch._assert_async(((index >= 0) & (index < consts.n_aug)).all(), self._range_message(None))
        try:
            option = consts.decode.gather(0, index)
        except RuntimeError:
            lo, hi = (int(v) for v in torch.aminmax(index))
            if lo < 0 or hi >= consts.n_aug:
                raise ValueError(self._range_message((lo, hi))) from None
            raise
        return option if consts.flat else option.view(consts.shape)

    def _range_message(self, got: tuple[int, int] | None) -> str:
        n_aug = self.num_augmented_actions
        message = (
            f"OptionExecutor: action out of range, expected integers in [0, {n_aug}) "
            f"({self.num_actions * self.primitive_actions} primitive actions + {self.num_options} options)"
        )
        return message + (f", got values in [{got[0]}, {got[1]}]." if got is not None else ".")

    def _check_action_range(self, action: torch.Tensor) -> None:
        """Raises a ``ValueError`` naming the expected range if ``action`` holds an out-of-range index."""
        self._decode(action, self._constants(action.device))

    # ------------------------------------------------------------ env hooks
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # the option is chosen with the action at s_t and acts at s_t. Per-step code: a fixed sequence of
        # small tensor ops (masks, no branch on tensor values), no host-device sync, unvalidated tensordict
        # writes; the options' outputs come from the previous step's _step (see _evaluate_options)
        action = _get(tensordict, self.action_key)
        running = _get(tensordict, self.option_key)
        if running is None:
            raise KeyError(
                f"OptionExecutor: the running-option entry {self.option_key!r} is missing from the input of "
                "env.step. Reset the env first and pass the tensordict returned by reset/step_mdp."
            )
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != action.device:
            consts = self._constants(action.device)
        started = self._decode(action, consts)  # also the range check
        decision = running < 0
        if self.lower_option_key is not None:
            lower_ready = self._lower_ready(tensordict, action.shape)
            decision = decision & lower_ready
        option = torch.where(decision, started, running)  # -1: the policy's primitive action runs

        logits = self._evaluate_options(tensordict, consts)[0]
        # the running option's row for each env; option -1 picks row K-1, whose draw is then not used
        logits = logits[consts.arange, option if consts.flat else option.reshape(-1)]
        if self.greedy:
            option_action = logits.argmax(-1)
        else:
            # inverse-CDF draw with one uniform per env: fewer kernels than torch.multinomial; the clamp keeps
            # rounding (a CDF ending below u) from giving an action >= A. The uniforms fill a buffer that no
            # output references (the same draws as torch.rand)
            generator = self._generator if self._generator is not None else self._rng()
            u = consts.uniform.uniform_(generator=generator)
            if u.dtype is not logits.dtype:  # e.g. float64 options
                u = u.to(logits.dtype)
            option_action = torch.searchsorted(logits.softmax(-1).cumsum(-1), u, right=True)
            option_action = option_action.clamp_max_(consts.A - 1).view(-1)
        if not consts.flat:
            option_action = option_action.view(consts.shape)
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
        _set(tensordict, self.action_key, executed)
        _set(tensordict, self.executed_action_key, executed)
        _set(tensordict, self.executed_option_key, option)
        _set(tensordict, self.decision_key, decision)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        option = _get(tensordict, self.executed_option_key)
        consts = self.__dict__.get("_consts")
        if consts is None or consts.device != option.device:
            consts = self._constants(option.device)
        flat_option = option if consts.flat else option.reshape(-1)
        # the termination of the running option is evaluated at s_{t+1}; these options outputs are kept for
        # the option's action at the next step
        term_logits = self._evaluate_options(next_tensordict, consts, cache=True)[1]
        # option -1 (primitive) picks column K-1: its draw is not used, the option stays -1
        term_logits = term_logits[consts.arange, flat_option]
        # terminate w.p. sigmoid(logit); the uniforms fill a buffer that no output references
        generator = self._generator if self._generator is not None else self._rng()
        terminate = consts.coin.uniform_(generator=generator) < term_logits.sigmoid()
        if self.lower_option_key is not None:
            # call-and-return: no termination check while the level below still runs its option
            terminate = terminate & self._lower_ready(next_tensordict, terminate.shape)
        # the end of an episode ends the option too; option == -1 stays -1
        ends = terminate | _get(next_tensordict, self.done_key).view(-1)
        if not consts.flat:
            ends = ends.view(consts.shape)
        _set(next_tensordict, self.option_key, torch.where(ends, consts.no_option, option))
        _set(next_tensordict, self.executed_action_key, _get(tensordict, self.executed_action_key))
        _set(next_tensordict, self.executed_option_key, option)
        _set(next_tensordict, self.decision_key, _get(tensordict, self.decision_key))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._register_seed_hook()
        spec = self._base_action_spec()
        shape, device = spec.shape, spec.device
        reset = _get(tensordict, _reset_key(self.done_key)) if tensordict is not None else None
        if reset is not None:
            reset = reset.reshape(shape)
        # a new episode starts with a decision; the records are empty (-1 / False) until its first step.
        # Only envs flagged by "_reset" change (TorchRL also merges non-reset envs back after _reset)
        entries = (
            (self.option_key, _NO_OPTION, torch.int64),
            (self.executed_option_key, _NO_OPTION, torch.int64),
            (self.executed_action_key, _NO_OPTION, spec.dtype),
            (self.decision_key, False, torch.bool),
        )
        for key, default, dtype in entries:
            prev = _get(tensordict, key) if tensordict is not None and reset is not None else None
            if prev is None:
                value = torch.full(shape, default, dtype=dtype, device=device)
            else:
                value = torch.where(reset, default, prev.reshape(shape))
            _set(tensordict_reset, key, value)
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "OptionExecutor runs inside an environment step; it has no replay-buffer (forward) mode. "
            "Use torchrl_options.data.SMDPTransitions to turn its step-level data into decisions."
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_options={self.num_options}, primitive_actions={self.primitive_actions}, "
            f"greedy={self.greedy}, level={self.level}, option_key={self.option_key!r})"
        )


class _StepConstants(NamedTuple):
    device: torch.device
    cpu: bool
    A: int  # actions of the env below
    K: int  # options
    n_aug: int  # policy-facing actions
    shape: torch.Size  # action shape (the env's batch)
    n: int  # envs in the batch
    flat: bool  # the action shape is [n]: no reshapes
    decode: torch.Tensor  # [n_aug]: augmented action -> option started (-1: primitive)
    arange: torch.Tensor  # [n]
    no_option: torch.Tensor  # -1, 0-dim
    uniform: torch.Tensor  # [n, 1] buffer of the action draws (never returned)
    coin: torch.Tensor  # [n] buffer of the termination draws (never returned)


def _get(tensordict: TensorDictBase, key: NestedKey) -> torch.Tensor | None:
    """``tensordict.get(key, None)`` for an unravelled key, without the public method's overhead."""
    if type(key) is str:
        return tensordict._get_str(key, None)
    return tensordict._get_tuple(key, None)


def _set(tensordict: TensorDictBase, key: NestedKey, value: torch.Tensor) -> None:
    """``tensordict.set(key, value)`` without validation, for values built with the env's batch shape."""
    if type(tensordict) is TensorDict:
        if type(key) is str:
            tensordict._set_str(key, value, inplace=False, validated=True, ignore_lock=False, non_blocking=False)
        else:
            tensordict._set_tuple(key, value, inplace=False, validated=True, non_blocking=False)
    else:
        tensordict.set(key, value)


def _cache_entries(tensors: list) -> list[tuple] | None:
    """``(tensor, version, None)`` per input, or ``(tensor, None, copy)`` for an inference tensor (it has no
    version counter, so its values are compared); ``None`` if an input is missing or not a tensor."""
    entries = []
    for x in tensors:
        if not isinstance(x, torch.Tensor):
            return None
        try:
            entries.append((x, x._version, None))
        except RuntimeError:  # inference tensors do not track versions
            entries.append((x, None, x.clone()))
    return entries


def _sibling_key(key: NestedKey, name: str) -> NestedKey:
    """``name`` next to ``key``: ``"_reset"`` for ``"done"``, ``(..., "_reset")`` for ``(..., "done")``."""
    return name if isinstance(key, str) else (*key[:-1], name)


def _reset_key(done_key: NestedKey) -> NestedKey:
    return _sibling_key(done_key, "_reset")


class _SeedExecutors:
    """Replaces ``env.set_seed`` on one env instance to also seed the ``OptionExecutor``\\ s it contains.

    Each executor gets a seed derived from the env seed, its level and its position, so levels and sibling
    executors draw independent streams. A module-level class (not a closure) so that envs stay picklable.
    """

    def __init__(self, env: EnvBase):
        self.env = env

    def __call__(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        if seed is not None:
            transform = getattr(self.env, "transform", None)
            executors: Sequence[OptionExecutor] = (
                [m for m in transform.modules() if isinstance(m, OptionExecutor)] if transform is not None else []
            )
            for i, executor in enumerate(executors):
                executor.set_seed(seed * 1_000_003 + 7_919 * executor.level + 104_729 * i)
        return type(self.env).set_seed(self.env, seed, static_seed=static_seed)
