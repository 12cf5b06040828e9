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

import torch
from tensordict import TensorDictBase
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
    It runs under ``torch.no_grad``, on ``s_t`` (the running option's action) and on ``s_{t+1}`` (its
    termination) at every step.

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
        >>> data = env.rollout(10)
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
        self._options_in_keys = getattr(options, "in_keys", None)
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
    def _evaluate_options(
        self, tensordict: TensorDictBase, cache: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``option_logits`` ``[N * K, A]`` and ``termination_logits`` ``[N * K]`` (batch flattened, option-major).

        The termination at ``s_{t+1}`` and the action at the next step need the options at the same state:
        the outputs computed in ``_step`` are kept (``cache=True``) and reused by the next ``_inv_call`` when
        its inputs, and the options' parameters, are unchanged. So the options run once per step.
        """
        keys = self._options_in_keys
        inputs = None if keys is None else tuple(tensordict.get(key, None) for key in keys)
        version = tuple(p._version for p in self._options_params)
        cached = self.__dict__.get("_options_cache")
        if (
            cached is not None
            and inputs is not None
            and cached[0] == version
            and all(x is not None and x.shape == c.shape and torch.equal(x, c) for x, c in zip(inputs, cached[1]))
        ):
            return cached[2], cached[3]
        with torch.no_grad():
            logits, term = self._call_options(tensordict, inputs)
        K, A = self.num_options, self.num_actions
        n = self._base_action_spec().shape.numel()
        if logits is None or term is None:
            raise KeyError(
                f"The options module did not write {self.option_logits_key!r} and "
                f"{self.termination_logits_key!r}."
            )
        if logits.shape[-2:] != (K, A) or logits.shape[:-2].numel() != n:
            raise ValueError(
                f"The options module wrote {self.option_logits_key!r} of shape {tuple(logits.shape)}; "
                f"expected [*batch, K={K}, A={A}] with batch {tuple(self._base_action_spec().shape)}."
            )
        if term.shape[-1] != K or term.shape[:-1].numel() != n:
            raise ValueError(
                f"The options module wrote {self.termination_logits_key!r} of shape {tuple(term.shape)}; "
                f"expected [*batch, K={K}] with batch {tuple(self._base_action_spec().shape)}."
            )
        logits, term = logits.reshape(n * K, A), term.reshape(n * K)
        if cache and inputs is not None and all(x is not None for x in inputs):
            # clone: batched envs write the next observation into the same buffers in place
            self.__dict__["_options_cache"] = (version, tuple(x.clone() for x in inputs), logits, term)
        return logits, term

    def _call_options(
        self, tensordict: TensorDictBase, inputs: tuple[torch.Tensor, ...] | None
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
        return tensordict.get(self.lower_option_key).reshape(shape) < 0

    # ------------------------------------------------------------ env hooks
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # the option is chosen with the action at s_t and acts at s_t
        action = tensordict.get(self.action_key)
        running = tensordict.get(self.option_key, None)
        if running is None:
            raise KeyError(
                f"OptionExecutor: the running-option entry {self.option_key!r} is missing from the input of "
                "env.step. Reset the env first and pass the tensordict returned by reset/step_mdp."
            )
        self._check_action_range(action)
        A = self.num_actions
        decision = running < 0
        if self.lower_option_key is not None:
            lower_ready = self._lower_ready(tensordict, action.shape)
            decision = decision & lower_ready
        # primitive actions become negative "options" -A .. -1, clamped to -1 (none) for the record
        option = torch.where(decision, action - A if self.primitive_actions else action, running)

        logits, _ = self._evaluate_options(tensordict)
        logits = logits[self._row_offsets(logits) + option.clamp_min(0).view(-1)]  # [N, A] of the running option
        if self.greedy:
            option_action = logits.argmax(-1)
        else:
            # inverse-CDF draw with one uniform per env: fewer kernels than torch.multinomial. The last
            # CDF entry is left out so that rounding (CDF ending below u) cannot give an action >= A
            u = torch.rand((logits.shape[0], 1), generator=self._rng(), device=logits.device)
            cdf = logits.softmax(-1).cumsum(-1)[:, :-1].contiguous()
            option_action = torch.searchsorted(cdf, u, right=True).squeeze(-1)
        option_action = option_action.view(action.shape).to(action.dtype)
        if self.lower_option_key is None:
            # a running option always acts; otherwise this is a decision for a primitive action
            executed = torch.where(option >= 0, option_action, action)
        else:
            # call-and-return: this level acts only when the level below waits for an action; otherwise its
            # output is ignored below and any valid action is passed
            acting = (option >= 0) & lower_ready
            passthrough = action.clamp_max(A - 1) if self.primitive_actions else torch.zeros_like(action)
            executed = torch.where(acting, option_action, passthrough)

        # tensordict is the shallow copy given to the env below: the policy's action stays in the data. The
        # records are stashed under this level's keys: a lower executor in the same Compose rewrites the action
        tensordict.set(self.action_key, executed)
        tensordict.set(self.executed_action_key, executed)
        tensordict.set(self.executed_option_key, option.clamp_min(_NO_OPTION))
        tensordict.set(self.decision_key, decision)
        return tensordict

    def _row_offsets(self, table: torch.Tensor) -> torch.Tensor:
        """``[0, K, 2K, ...]``: row ``i`` of a flattened ``[N, K, ...]`` table starts at ``i * K``."""
        offsets = self.__dict__.get("_offsets")
        n = table.shape[0] // self.num_options
        if offsets is None or offsets.shape[0] != n or offsets.device != table.device:
            offsets = torch.arange(n, device=table.device) * self.num_options
            self.__dict__["_offsets"] = offsets
        return offsets

    def _check_action_range(self, action: torch.Tensor) -> None:
        lo, hi = torch.aminmax(action)
        lo, hi, n_aug = int(lo), int(hi), self.num_augmented_actions
        if lo < 0 or hi >= n_aug:
            raise ValueError(
                f"OptionExecutor: action out of range, expected integers in [0, {n_aug}) "
                f"({self.num_actions * self.primitive_actions} primitive actions + {self.num_options} "
                f"options), got values in [{lo}, {hi}]."
            )

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        executed = tensordict.get(self.executed_action_key)
        option = tensordict.get(self.executed_option_key)
        shape = executed.shape
        # the termination of the running option is evaluated at s_{t+1}
        _, term_logits = self._evaluate_options(next_tensordict, cache=True)
        term_logits = term_logits[self._row_offsets(term_logits) + option.clamp_min(0).view(-1)].view(shape)
        terminate = torch.rand(shape, generator=self._rng(), device=term_logits.device) < term_logits.sigmoid()
        if self.lower_option_key is not None:
            # call-and-return: no termination check while the level below still runs its option
            terminate = terminate & self._lower_ready(next_tensordict, shape)
        # the end of an episode ends the option too; option == -1 stays -1
        ends = terminate | next_tensordict.get(self.done_key).view(shape)
        next_tensordict.set(self.option_key, torch.where(ends, _NO_OPTION, option))
        next_tensordict.set(self.executed_action_key, executed)
        next_tensordict.set(self.executed_option_key, option)
        next_tensordict.set(self.decision_key, tensordict.get(self.decision_key))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._register_seed_hook()
        spec = self._base_action_spec()
        shape, device = spec.shape, spec.device
        reset = tensordict.get(_reset_key(self.done_key), None) if tensordict is not None else None
        reset = torch.ones(shape, dtype=torch.bool, device=device) if reset is None else reset.reshape(shape)
        # a new episode starts with a decision; the records are empty (-1 / False) until its first step.
        # Only envs flagged by "_reset" change (TorchRL also merges non-reset envs back after _reset)
        entries = {
            self.option_key: (_NO_OPTION, torch.int64),
            self.executed_option_key: (_NO_OPTION, torch.int64),
            self.executed_action_key: (_NO_OPTION, spec.dtype),
            self.decision_key: (False, torch.bool),
        }
        for key, (default, dtype) in entries.items():
            fresh = torch.full(shape, default, dtype=dtype, device=device)
            prev = tensordict.get(key, None) if tensordict is not None else None
            tensordict_reset.set(key, fresh if prev is None else torch.where(reset, fresh, prev.reshape(shape)))
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


def _reset_key(done_key: NestedKey) -> NestedKey:
    return "_reset" if isinstance(done_key, str) else (*done_key[:-1], "_reset")


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
