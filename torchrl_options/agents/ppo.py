"""PPO over primitive actions, options, or both: policy gradients at the level of decisions.

Wires an env factory, an :class:`~torchrl_options.transforms.OptionExecutor` (on top of the executors an env may
already have: a hierarchy), a categorical ``ProbabilisticActor`` over the augmented action space ``A + K`` (``K``
with ``mode="options"``), a ``ValueOperator``, a ``Collector``, the decision-level batches of
:class:`~torchrl_options.data.OnPolicyDecisions`, TorchRL's :class:`~torchrl.objectives.value.GAE` (which
discounts a decision of ``k`` steps by ``gamma ** k``) and TorchRL's :class:`~torchrl.objectives.ClipPPOLoss`,
guarded against step-level data by :func:`~torchrl_options.objectives.guard_decision_level`. It is the PPO
counterpart of :class:`~torchrl_options.agents.OptionsDQN` (same env wiring, log, checkpoints and ``train``
callback), so the GridWorld recipes run either.

In a user's own TorchRL PPO script the same composition is three additions (see ``docs/ppo.md``): the
executor appended to the env, ``decisions = OnPolicyDecisions(gamma)(batch)`` before the advantage module, and
``guard_decision_level(loss_module)``.
"""
from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs import EnvBase, ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from torchrl_options.agents.dqn import (
    _batched_env,
    _check_agent_arguments,
    _check_env,
    _check_network,
    _check_state,
    _count_executors,
    _generators,
    _greedy_returns,
    _restore_or_roll_back,
    _with_reward_sum_and_step_count,
    check_device,
    check_frames_per_batch,
    check_max_grad_norm,
)
from torchrl_options.agents.training_loop import CollectorTraining, TrainingLog, seed_executors
from torchrl_options.checkpoints import load_file, rng_state, save_file, set_rng_state
from torchrl_options.checks import check_bool, check_int, check_nested_key
from torchrl_options.data.on_policy import OnPolicyDecisions
from torchrl_options.objectives.decision_guard import guard_decision_level
from torchrl_options.transforms.option_executor import OptionExecutor

logger = logging.getLogger(__name__)

__all__ = ["OptionsPPOConfig", "OptionsPPO"]

Mode = Literal["actions", "options", "both"]


@dataclass
class OptionsPPOConfig:
    """Hyper-parameters of :class:`OptionsPPO`. Frames are primitive env steps summed over the batched envs.

    Attributes:
        mode: ``"actions"`` (plain PPO), ``"options"`` (the policy chooses among options only: the executor's
            ``primitive_actions=False``) or ``"both"`` (``Categorical(A + K)``).
        num_envs: number of envs; more than one are batched in a ``SerialEnv`` (``ParallelEnv`` with
            ``parallel=True``) with the executor outside.
        total_frames: training budget of :meth:`OptionsPPO.train`.
        frames_per_batch: collector batch size (one PPO update per batch), a multiple of the number of envs (the
            collector steps them together; another size would make larger batches than asked).
        num_epochs: passes over each batch's decisions.
        minibatch_size: decisions per gradient step (``None``: the whole batch).
        lr: Adam learning rate.
        gamma: discount per primitive step (a decision of ``k`` steps is discounted by ``gamma ** k``).
        lmbda: GAE's lambda, per decision.
        clip_epsilon, entropy_coeff, critic_coeff, loss_critic_type, normalize_advantage: ``ClipPPOLoss``'s.
        hidden_sizes: hidden layers of the default policy and value MLPs.
        max_grad_norm: gradient clipping (``None`` to disable).
        greedy_options: options act greedily instead of sampling their action.
        observation_key: the input of the default networks.
        seed: seeds the envs, the collector and the option executors. Network initialisation and the policy's
            sampling draw from torch's global generator, as TorchRL's modules do: call ``torch.manual_seed`` before
            building the agent for a reproducible run (the recipes do).
        device: device of the networks (the envs stay on their own device).
    """

    mode: Mode = "both"
    num_envs: int = 1
    parallel: bool = False
    total_frames: int = 10_000
    frames_per_batch: int = 256
    num_epochs: int = 4
    minibatch_size: int | None = 64
    lr: float = 3e-4
    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5
    loss_critic_type: str = "smooth_l1"
    normalize_advantage: bool = True
    hidden_sizes: tuple[int, ...] = (64, 64)
    max_grad_norm: float | None = 0.5
    greedy_options: bool = False
    observation_key: NestedKey = "observation"
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        """Refuses a bad setting at once, naming it and the allowed values (``TypeError`` for a wrong type)."""
        choices = {"mode": ("actions", "options", "both"), "loss_critic_type": ("l1", "l2", "smooth_l1")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}.")
        for name, minimum in (("num_envs", 1), ("total_frames", 0), ("frames_per_batch", 1), ("num_epochs", 1), ("seed", 0)):
            check_int(getattr(self, name), name, minimum=minimum)
        check_frames_per_batch(self.frames_per_batch, self.num_envs, "num_envs")
        check_int(self.minibatch_size, "minibatch_size", minimum=1, allow_none=True)
        for name, lo, hi, lo_open in (("lr", 0, math.inf, True), ("gamma", 0, 1, False), ("lmbda", 0, 1, False),
                                      ("clip_epsilon", 0, math.inf, True), ("entropy_coeff", 0, math.inf, False),
                                      ("critic_coeff", 0, math.inf, False)):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__}).")
            if math.isnan(value) or not (lo < value if lo_open else lo <= value) or not value <= hi or value == math.inf:
                raise ValueError(f"{name} must be in {'(' if lo_open else '['}{lo}, {hi}], got {value}.")
        for name in ("parallel", "normalize_advantage", "greedy_options"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be a bool, got {getattr(self, name)!r}.")
        check_max_grad_norm(self.max_grad_norm)
        check_nested_key(self.observation_key, "observation_key")
        check_device(self.device, "device")
        sizes = self.hidden_sizes
        if isinstance(sizes, (str, bytes)) or not isinstance(sizes, (tuple, list)) or not all(
            isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in sizes
        ):
            raise ValueError(f"hidden_sizes must be a list of ints >= 1, got {sizes!r}.")


class OptionsPPO(CollectorTraining):
    """PPO over actions, options or both, on any env with a ``Categorical`` action (see the module docstring).

    Each collector batch becomes one entry per decision (:class:`~torchrl_options.data.OnPolicyDecisions`; a
    decision still running at the end of a batch is completed with the next one), TorchRL's GAE computes the SMDP
    advantages over them (``gamma ** k`` per decision), and ``config.num_epochs`` passes of ``ClipPPOLoss`` over
    minibatches of decisions update the policy and the value network.

    Args:
        env_factory (Callable[[], EnvBase]): makes one env with a ``Categorical(A)`` action and a flat
            ``config.observation_key`` observation (or pass the networks). It may already run lower levels of
            options (executors of a hierarchy): the agent's executor then goes one level up.
        config (OptionsPPOConfig): hyper-parameters.

    Keyword Args:
        options (TensorDictModuleBase, optional): writes ``option_logits`` ``[..., K, A]`` and
            ``termination_logits`` ``[..., K]``; required unless ``config.mode == "actions"``.
        num_options (int, optional): ``K``; required with ``options``.
        policy_network (nn.Module, optional): maps the observation to one logit per augmented action. Defaults
            to an MLP with ``config.hidden_sizes``.
        value_network (nn.Module, optional): maps the observation to one value. Defaults to an MLP.

    Attributes:
        env, actor (the ``ProbabilisticActor``; ``policy`` is the same), critic, loss_module (``ClipPPOLoss``),
        decisions (:class:`~torchrl_options.data.OnPolicyDecisions`), optimizer, frames, log
        (:class:`~torchrl_options.agents.TrainingLog`).

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.envs import GymEnv
        >>> from torchrl_options.agents import OptionsPPO, OptionsPPOConfig
        >>> class Push(torch.nn.Module):  # two options: push left / push right, 4 steps on average
        ...     def forward(self, obs):
        ...         logits = torch.tensor([[5.0, -5.0], [-5.0, 5.0]]).expand(*obs.shape[:-1], 2, 2)
        ...         return logits, torch.full((*obs.shape[:-1], 2), -1.1)
        >>> options = TensorDictModule(Push(), ["observation"], ["option_logits", "termination_logits"])
        >>> config = OptionsPPOConfig(mode="both", num_envs=2, total_frames=256, frames_per_batch=128)
        >>> agent = OptionsPPO(lambda: GymEnv("CartPole-v1", categorical_action_encoding=True), config,
        ...                    options=options, num_options=2)
        >>> log = agent.train()
        >>> agent.frames, len(log.losses) > 0
        (256, True)
    """

    def __init__(
        self,
        env_factory: Callable[[], EnvBase],
        config: OptionsPPOConfig | None = None,
        *,
        options: TensorDictModuleBase | None = None,
        num_options: int | None = None,
        policy_network: nn.Module | None = None,
        value_network: nn.Module | None = None,
    ):
        self.config = config = OptionsPPOConfig() if config is None else config
        _check_agent_arguments("OptionsPPO", env_factory, config, OptionsPPOConfig, options, num_options)
        _check_network(policy_network, "policy_network")
        _check_network(value_network, "value_network")
        self.env_factory = env_factory
        self.options = options
        self.num_options = num_options
        self.device = torch.device(config.device)
        self._executor_level = 0
        self.env = self.make_env()

        spec = _check_env("OptionsPPO", self.env, config)
        obs_dim = self.env.observation_spec[config.observation_key].shape[-1]
        if policy_network is None:
            policy_network = MLP(in_features=obs_dim, out_features=spec.n, num_cells=list(config.hidden_sizes), activation_class=nn.Tanh)
        if value_network is None:
            value_network = MLP(in_features=obs_dim, out_features=1, num_cells=list(config.hidden_sizes), activation_class=nn.Tanh)
        self.actor = ProbabilisticActor(
            TensorDictModule(policy_network, in_keys=[config.observation_key], out_keys=["logits"]),
            in_keys=["logits"],
            spec=spec,
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,
            default_interaction_type=ExplorationType.RANDOM,
        ).to(self.device)
        self.policy = self.actor
        self.critic = ValueOperator(value_network, in_keys=[config.observation_key]).to(self.device)
        self.loss_module = ClipPPOLoss(
            self.actor,
            self.critic,
            clip_epsilon=config.clip_epsilon,
            entropy_bonus=config.entropy_coeff > 0,
            entropy_coeff=config.entropy_coeff,
            critic_coeff=config.critic_coeff,
            loss_critic_type=config.loss_critic_type,
            normalize_advantage=config.normalize_advantage,
        )
        guard_decision_level(self.loss_module)
        # GAE over decisions: TorchRL's estimator discounts each by gamma ** steps_to_next_obs
        self.loss_module.make_value_estimator(ValueEstimators.GAE, gamma=config.gamma, lmbda=config.lmbda)
        self.optimizer = torch.optim.Adam(self.loss_module.parameters(), lr=config.lr)
        self.decisions = OnPolicyDecisions(config.gamma, decision_key=self.decision_key)
        self.frames = 0
        self.updates = 0
        self.log = TrainingLog()

    @property
    def decision_key(self) -> NestedKey | None:
        """The decision record of the agent's executor (the top level); ``None`` without executor."""
        level = self._executor_level
        if level == 0:
            return None
        return ("next", "option_decision" if level == 1 else f"option_decision_{level}")

    # ------------------------------------------------------------------ env
    def make_env(self) -> EnvBase:
        """The training env: batched envs, then the executor (outside the batch, one level above those the env
        already has), ``RewardSum``, ``StepCounter``."""
        config = self.config
        env = _batched_env(self.env_factory, config.num_envs, config.parallel)
        if config.mode != "actions":
            self._executor_level = 1 + _count_executors(env)
            env = env.append_transform(
                OptionExecutor(
                    self.options,
                    num_options=self.num_options,
                    primitive_actions=config.mode == "both",
                    greedy=config.greedy_options,
                    level=self._executor_level,
                )
            )
            seed_executors(env, config.seed)
        return _with_reward_sum_and_step_count(env)

    # ------------------------------------------------------------- training (the loop: CollectorTraining.train)
    def _collector_policy(self) -> nn.Module:
        return self.actor

    def _start_episodes(self) -> None:
        self.decisions.reset()

    def _learn(self, batch: TensorDictBase) -> None:
        """One PPO update on the batch's decisions (none when no decision ended in it)."""
        decisions = self.decisions(batch)
        if decisions.shape[0]:
            self.update(decisions)

    def update(self, decisions: TensorDictBase) -> None:
        """One PPO update on a decision-level batch (from :attr:`decisions`): GAE over the decisions, then
        ``num_epochs`` passes of ``ClipPPOLoss`` over shuffled minibatches."""
        if not isinstance(decisions, TensorDictBase) or decisions.ndim != 1:
            raise TypeError(
                "update expects a decision-level TensorDict of shape [M] (from agent.decisions(batch)), got "
                f"{type(decisions).__name__}{f' of shape {list(decisions.shape)}' if isinstance(decisions, TensorDictBase) else ''}."
            )
        config = self.config
        decisions = decisions.to(self.device)
        with torch.no_grad():
            self.loss_module.value_estimator(decisions)
        n = decisions.shape[0]
        size = min(config.minibatch_size or n, n)
        for _ in range(config.num_epochs):
            order = torch.randperm(n, device=self.device)
            for start in range(0, n, size):
                out = self.loss_module(decisions[order[start : start + size]])
                loss = out["loss_objective"] + out["loss_critic"]
                if "loss_entropy" in out.keys():
                    loss = loss + out["loss_entropy"]
                self.optimizer.zero_grad()
                loss.backward()
                if config.max_grad_norm is not None:
                    torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), config.max_grad_norm)
                self.optimizer.step()
                self.updates += 1
                self.log.losses.append(loss.item())

    def _record_episodes(self, batch: TensorDictBase) -> None:
        returns = self.log.record_episodes(batch, self.frames)
        if returns is None:
            return
        logger.info("frames %d: %d episodes, mean return %.3f", self.frames + batch.numel(), len(returns), returns.float().mean().item())

    # ----------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, num_episodes: int = 10, max_steps: int = 1000) -> list[float]:
        """Returns of the first ``num_episodes`` episodes of the greedy policy (the mode of its distribution;
        options act as configured), on one env from ``env_factory`` run for at most ``max_steps`` steps."""
        check_int(num_episodes, "num_episodes", minimum=1)
        check_int(max_steps, "max_steps", minimum=1)
        saved, self.config.num_envs = self.config.num_envs, 1
        try:
            env = self.make_env()
        finally:
            self.config.num_envs = saved
        return _greedy_returns(env, self.actor, num_episodes, max_steps, self.config.seed + 10_000)

    # ---------------------------------------------------------- checkpoints
    def state_dict(self, include_buffer: bool = False) -> dict[str, Any]:
        """Networks, optimizer, counters, log and every random state the training draws from, as plain data (loads
        with ``weights_only=True``). ``include_buffer`` is accepted for the recipes' sake: PPO keeps no buffer."""
        check_bool(include_buffer, "include_buffer")
        return {
            "loss_module": self.loss_module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "frames": self.frames,
            "updates": self.updates,
            "log": asdict(self.log),
            "config": asdict(self.config),
            "rng": rng_state(),
            "generators": {name: g.get_state() for name, g in _generators(self.env).items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores :meth:`state_dict`. The checkpoint is checked whole before anything is restored: a bad one
        leaves the agent as it was.

        Raises:
            ValueError: ``state`` is not an OptionsPPO checkpoint, holds an entry of the wrong type, or was saved by
                an agent over another action space or network.
        """
        self._load_state(state, None)

    def _load_state(self, state: Any, source: str | None) -> None:
        where = _check_state(
            state, "OptionsPPO", ("loss_module", "optimizer", "frames", "updates", "log"), ("frames", "updates"), source
        )
        saved_mode = state.get("config", {}).get("mode", self.config.mode)
        if saved_mode != self.config.mode:
            raise ValueError(f"{where}the checkpoint is of mode={saved_mode!r}, this agent has mode={self.config.mode!r}.")
        _restore_or_roll_back(
            where,
            [("loss_module", self.loss_module, state["loss_module"]), ("optimizer", self.optimizer, state["optimizer"])],
        )
        self.frames = int(state["frames"])
        self.updates = int(state["updates"])
        self.log = TrainingLog(**{k: list(v) for k, v in state["log"].items()})
        if "rng" in state:
            set_rng_state(state["rng"])
            generators = _generators(self.env)
            for name, g_state in state.get("generators", {}).items():
                if name in generators:
                    generators[name].set_state(g_state)

    def save(self, path) -> None:
        """Writes :meth:`state_dict` to ``path`` (plain data, atomically)."""
        save_file(self.state_dict(), path)

    def load(self, path) -> None:
        """Restores a checkpoint written by :meth:`save`, without running code from the file."""
        self._load_state(load_file(path, what="OptionsPPO checkpoint", map_location=self.device), os.fspath(path))
