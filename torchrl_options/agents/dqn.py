"""DQN over primitive actions, options, or both: a small building block for the recipes.

Wires an env factory, an :class:`~torchrl_options.transforms.OptionExecutor`, a ``QValueActor`` with an
``EGreedyModule``, a ``Collector``, decision-level transitions (:class:`~torchrl_options.data.SMDPTransitions`,
so that ``DQNLoss`` bootstraps with ``gamma ** k`` after a ``k``-step option), a replay buffer and
``DQNLoss`` with a target network. This is SMDP Q-learning over the augmented action space of Fox et al.,
2017 ("Multi-Level Discovery of Deep Options", section 5): the policy decides only when no option runs,
and its exploration is suspended while an option runs.
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
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import (
    EnvBase,
    ExplorationType,
    ParallelEnv,
    RewardSum,
    SerialEnv,
    set_exploration_type,
    StepCounter,
    TransformedEnv,
)
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate, ValueEstimators

from torchrl_options.checkpoints import load_file, rng_state, save_file, set_rng_state
from torchrl_options.checks import check_bool, check_callable, check_int, check_nested_key
from torchrl_options.agents.training_loop import CollectorTraining, TrainingLog, seed_executors
from torchrl_options.agents.warm_start import widen_action_rows, widen_action_values
from torchrl_options.data.intra_option import intra_option_transitions, option_suffix_transitions
from torchrl_options.data.smdp import SMDPTransitions
from torchrl_options.transforms.decision_counter import DecisionCounter
from torchrl_options.transforms.option_executor import OptionExecutor

logger = logging.getLogger(__name__)

__all__ = ["DQNHyperParameters", "OptionsDQNConfig", "OptionsDQN"]

Mode = Literal["actions", "options", "both"]


@dataclass
class DQNHyperParameters:
    """The DQN settings that :class:`OptionsDQNConfig` shares with the recipes' schemas (the Atari recipe's
    :class:`~torchrl_options.experiments.atari.AtariConfig` derives from this class, its Hydra schema included):
    one declaration and one check of each. Frames are primitive env steps summed over the batched envs.

    Every field is a plain Hydra/OmegaConf type (``str`` for the choices, checked here), so that a subclass can be
    registered in Hydra's ``ConfigStore`` as it is.

    Attributes:
        num_envs: number of envs; more than one are batched in a ``SerialEnv`` (``ParallelEnv`` with
            ``parallel=True``) with the executor outside, evaluating the options once for all envs.
        parallel: batch the envs in a ``ParallelEnv`` instead of a ``SerialEnv``.
        frames_per_batch: collector batch size, a multiple of the number of envs (the collector steps them
            together; another size would make larger batches than asked).
        buffer_size: replay buffer capacity, in decisions.
        batch_size: decisions per gradient step.
        learning_starts: decisions in the buffer before the first gradient step.
        updates_per_batch: gradient steps per collector batch.
        lr: Adam learning rate.
        gamma: discount per primitive step (or per decision with ``discount_per="decision"``).
        discount_per: ``"step"`` (default: the SMDP target ``R + gamma^k max Q``, rewards discounted inside an
            option) or ``"decision"`` (every decision is one time-step: rewards summed, ``R + gamma max Q``);
            see :mod:`torchrl_options.data.smdp`.
        hidden_sizes: hidden layers of the default MLP Q-network.
        eps_init, eps_end, eps_annealing_frames: linear epsilon-greedy schedule, over frames (``0`` frames: as
            ``1``, ``eps_end`` after the first frame).
        hard_update_interval: gradient steps between two copies of the target network (``target_update="hard"``).
        double_dqn: use double DQN targets.
        device: device of the networks and the replay buffer (the envs stay on their own device).

    Examples:
        >>> DQNHyperParameters(gamma=0.9).gamma
        0.9
        >>> DQNHyperParameters(discount_per="option")
        Traceback (most recent call last):
        ...
        ValueError: discount_per must be one of ('step', 'decision'), got 'option'.
    """

    num_envs: int = 1
    parallel: bool = False
    frames_per_batch: int = 64
    buffer_size: int = 100_000
    batch_size: int = 64
    learning_starts: int = 64
    updates_per_batch: int = 4
    lr: float = 1e-3
    gamma: float = 0.99
    discount_per: str = "step"
    hidden_sizes: tuple[int, ...] = (64, 64)
    eps_init: float = 1.0
    eps_end: float = 0.05
    eps_annealing_frames: int = 5_000
    hard_update_interval: int = 100
    double_dqn: bool = False
    device: str = "cpu"

    def __post_init__(self) -> None:
        """Refuses a bad setting at once, naming it and the allowed values (``TypeError`` for a wrong type)."""
        if self.discount_per not in ("step", "decision"):
            raise ValueError(f"discount_per must be one of ('step', 'decision'), got {self.discount_per!r}.")
        for name, minimum in (("num_envs", 1), ("frames_per_batch", 1), ("buffer_size", 1), ("batch_size", 1),
                              ("learning_starts", 0), ("updates_per_batch", 0), ("eps_annealing_frames", 0),
                              ("hard_update_interval", 1)):  # fmt: skip
            check_int(getattr(self, name), name, minimum=minimum)
        check_frames_per_batch(self.frames_per_batch, self.num_envs, "num_envs")
        for name, hi in (("lr", math.inf), ("gamma", 1), ("eps_init", 1), ("eps_end", 1)):
            _check_number(self, name, 0, hi, lo_open=name == "lr", hi_open=name == "lr")
        for name in ("parallel", "double_dqn"):
            check_bool(getattr(self, name), name)
        sizes = self.hidden_sizes
        if isinstance(sizes, (str, bytes)) or not isinstance(sizes, (tuple, list)) or not all(
            isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in sizes
        ):
            raise ValueError(f"hidden_sizes must be a list of ints >= 1, got {sizes!r}.")
        check_device(self.device, "device")


def check_frames_per_batch(frames_per_batch: int, num_envs: int, what: str) -> None:
    """Refuses a collector batch that the envs cannot fill exactly: TorchRL's collector steps all ``num_envs`` envs
    together and rounds ``frames_per_batch`` up to a multiple of them, so a budget would be overrun silently (3 envs
    and 10 frames per batch collect 12)."""
    if frames_per_batch % num_envs:
        low = frames_per_batch // num_envs * num_envs
        hint = f"{low} or {low + num_envs}" if low else f"{num_envs}"
        raise ValueError(
            f"frames_per_batch must be a multiple of the number of envs ({what}={num_envs}): the collector steps the "
            f"envs together and would collect {low + num_envs} frames per batch, not {frames_per_batch}; got "
            f"frames_per_batch={frames_per_batch} (use e.g. {hint})."
        )


def check_device(device: Any, name: str) -> None:
    """Refuses what ``torch.device`` cannot read (``"cpu"``, ``"cuda:0"``, a ``torch.device``)."""
    if isinstance(device, torch.device):
        return
    if not isinstance(device, str):
        raise TypeError(f"{name} must be a device name such as 'cpu' or 'cuda:0', got {device!r} ({type(device).__name__}).")
    try:
        torch.device(device)
    except (RuntimeError, ValueError):
        raise ValueError(f"{name} must be a device name such as 'cpu' or 'cuda:0', got {device!r}.") from None


def _check_number(config: Any, name: str, lo: float, hi: float, *, lo_open: bool, hi_open: bool) -> None:
    value = getattr(config, name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__}).")
    if not (lo < value if lo_open else lo <= value) or not (value < hi if hi_open else value <= hi) or math.isnan(value):
        interval = f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
        raise ValueError(f"{name} must be in {interval}, got {value}.")


@dataclass
class OptionsDQNConfig(DQNHyperParameters):
    """Hyper-parameters of :class:`OptionsDQN`: the fields of :class:`DQNHyperParameters` (``num_envs``, ``lr``,
    ``gamma``, ``batch_size``, ...) and those below.

    Attributes:
        mode: ``"actions"`` (plain DQN), ``"options"`` (the policy chooses among options only) or ``"both"``.
        total_frames: training budget of :meth:`OptionsDQN.train`.
        target_update: ``"hard"`` (copy every ``hard_update_interval`` gradient steps) or ``"soft"``
            (Polyak averaging with ``soft_update_eps``).
        loss_function: ``"l2"``, ``"l1"`` or ``"smooth_l1"``.
        max_grad_norm: gradient clipping (``None`` to disable).
        greedy_options: options act greedily instead of sampling their action.
        intra_option_actions: also learn the primitive actions' values from the steps that options take: each
            such step goes to the replay buffer as a one-step transition of the primitive action executed
            (:func:`~torchrl_options.data.intra_option_transitions`; intra-option learning, Sutton, Precup and
            Singh, 1999), next to the decision-level transitions, with ``"intra_option"`` set to ``True``
            (``False`` on decisions). Needs ``mode="both"`` over an env's own actions (a level-1 executor).
        option_suffixes: also learn the options' values from every step they run: the rest of each option run,
            from each of its steps after the first, goes to the replay buffer as a transition of starting that
            option there (:func:`~torchrl_options.data.option_suffix_transitions`; valid for Markov options),
            marked ``"intra_option"`` as above. Needs options (``mode`` ``"both"`` or ``"options"``) at level 1.
        max_decisions: if set, episodes are limited in decisions rather than primitive steps: a
            :class:`~torchrl_options.transforms.DecisionCounter` after the executor truncates an episode once its
            ``max_decisions``-th decision (a primitive action, or an option run to termination) is over. The
            env's own step limit stays a hard cap on primitive steps: set it well above ``max_decisions``.
            ``None`` (default): no decision limit.
        observation_key: the input of the default Q-network.
        seed: seeds the envs, the collector and the option executors. Network initialisation and exploration draw
            from torch's global generator, as TorchRL's modules do: call ``torch.manual_seed`` before building the
            agent for a reproducible run (the recipes do).
    """

    mode: Mode = "both"
    total_frames: int = 10_000
    target_update: Literal["hard", "soft"] = "hard"
    soft_update_eps: float = 0.995
    loss_function: str = "l2"
    max_grad_norm: float | None = 10.0
    greedy_options: bool = False
    intra_option_actions: bool = False
    option_suffixes: bool = False
    max_decisions: int | None = None
    observation_key: NestedKey = "observation"
    seed: int = 0

    def __post_init__(self) -> None:
        """Refuses a bad setting at once, naming it and the allowed values (``TypeError`` for a wrong type)."""
        super().__post_init__()
        choices = {"mode": ("actions", "options", "both"), "target_update": ("hard", "soft"),
                   "loss_function": ("l2", "l1", "smooth_l1")}  # fmt: skip
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}.")
        check_int(self.total_frames, "total_frames", minimum=0)
        check_int(self.seed, "seed", minimum=0)
        check_int(self.max_decisions, "max_decisions", minimum=1, allow_none=True)
        _check_number(self, "soft_update_eps", 0, 1, lo_open=True, hi_open=True)
        check_max_grad_norm(self.max_grad_norm)
        for name in ("greedy_options", "intra_option_actions", "option_suffixes"):
            check_bool(getattr(self, name), name)
        check_nested_key(self.observation_key, "observation_key")


def check_max_grad_norm(value: Any) -> None:
    """``None`` or a finite number > 0."""
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise TypeError(f"max_grad_norm must be None or a number > 0, got {value!r} ({type(value).__name__}).")
    if value is not None and not 0 < value < math.inf:
        raise ValueError(f"max_grad_norm must be None or > 0 (finite), got {value!r}.")


def _batched_env(env_factory: Callable[[], EnvBase], num_envs: int, parallel: bool) -> EnvBase:
    if num_envs == 1:
        env = env_factory()
        if not isinstance(env, EnvBase):
            raise TypeError(f"env_factory must return a torchrl EnvBase, it returned {type(env).__name__}.")
        return env
    try:
        return (ParallelEnv if parallel else SerialEnv)(num_envs, env_factory)
    except (AttributeError, TypeError) as err:
        raise TypeError(
            f"building {num_envs} envs from env_factory failed ({type(err).__name__}: {err}): env_factory must be a "
            "callable that returns a torchrl EnvBase."
        ) from err


def _check_agent_arguments(
    owner: str, env_factory: Any, config: Any, config_class: type, options: Any, num_options: Any
) -> None:
    """The checks shared by :class:`OptionsDQN` and :class:`~torchrl_options.agents.OptionsPPO` before any env is
    made: the config's type, an env factory (not an env), options exactly when the mode uses them."""
    if not isinstance(config, config_class):
        raise TypeError(f"config must be an {config_class.__name__}, got {type(config).__name__}.")
    if isinstance(env_factory, EnvBase):
        raise TypeError(
            f"{owner}: env_factory must be a callable that makes an env (e.g. `lambda: GridWorldEnv(...)`), got an "
            f"env instance ({type(env_factory).__name__}): the agent makes config.num_envs envs itself and batches "
            "them."
        )
    check_callable(env_factory, "env_factory", what="a callable making an env")
    if config.mode == "actions":
        if options is not None or num_options is not None:
            raise ValueError(
                f"{owner}: mode='actions' learns over primitive actions only and would ignore the options; got "
                f"options={type(options).__name__ if options is not None else None} and num_options={num_options!r}. "
                "Use mode='both' (actions and options) or mode='options', or leave them out."
            )
    elif options is None or num_options is None:
        raise ValueError(f"mode={config.mode!r} needs `options` and `num_options`.")
    check_int(num_options, "num_options", minimum=1, allow_none=True)
    if options is not None and not isinstance(options, TensorDictModuleBase):
        raise TypeError(f"options must be a TensorDictModuleBase, got {type(options).__name__}.")
    k = getattr(options, "num_options", None)
    if isinstance(k, int) and not isinstance(k, bool) and num_options is not None and k != num_options:
        raise ValueError(f"{owner}: num_options={num_options} but the options module has num_options={k}.")


def _check_network(network: Any, name: str) -> None:
    if network is not None and not isinstance(network, nn.Module):
        raise TypeError(f"{name} must be a torch.nn.Module (or None for the default MLP), got {type(network).__name__}.")


def _check_env(owner: str, env: EnvBase, config: Any) -> Any:
    """The training env's action spec, after checking that the agent can drive the env: a discrete ``"action"``,
    the observation it reads, and collector batches the envs fill exactly. Returns the action spec."""
    spec = env.full_action_spec_unbatched.get("action", None)
    if spec is None or not hasattr(spec, "n"):
        found = "no 'action' entry" if spec is None else f"a {type(spec).__name__} 'action'"
        raise ValueError(
            f"{owner} needs an env with a discrete (Categorical) 'action', as DQN and the option executor do; the "
            f"env has {found}."
        )
    key = config.observation_key
    if key not in env.observation_spec.keys(include_nested=True):
        keys = sorted(map(str, env.observation_spec.keys(include_nested=True, leaves_only=True)))
        raise ValueError(
            f"{owner}: config.observation_key={key!r} is not an observation of the env (its observations: {keys})."
        )
    envs = env.batch_size.numel() if len(env.batch_size) else 1
    check_frames_per_batch(config.frames_per_batch, envs, "the env's batch size")
    return spec


_TRAINING_LOG_FIELDS = ("episode_returns", "episode_lengths", "episode_end_frames", "losses", "evaluations")
_OTHER_FORMATS = {
    "torchrl_options/options-v1": "an options file written by save_options (load it with load_options)",
    "torchrl_options/hierarchy-v1": "a hierarchy file written by save_hierarchy (load it with load_hierarchy)",
    "torchrl_options.tensordict/1": "a TensorDict (e.g. trajectories) written by torchrl_options",
}


def _check_state(state: Any, owner: str, required: tuple[str, ...], counters: tuple[str, ...], source: str | None) -> str:
    """Checks an agent checkpoint's layout before anything is restored (a bad one leaves the agent as it was);
    returns the prefix of the error messages (the file, or ``load_state_dict``)."""
    where = f"{source}: " if source else "load_state_dict: "
    if not isinstance(state, dict):
        raise TypeError(f"{where}expected a dict from {owner}.state_dict, got {type(state).__name__}.")
    other = _OTHER_FORMATS.get(state.get("format")) if isinstance(state.get("format"), str) else None
    if other is not None:
        raise ValueError(f"{where}not an {owner} checkpoint: this is {other}.")
    missing = [k for k in required if k not in state]
    if missing:
        raise ValueError(
            f"{where}not an {owner} checkpoint (written by {owner}.save / state_dict), missing {missing}; it holds "
            f"{sorted(map(str, state))}."
        )
    for name in ("loss_module", "optimizer") + (("exploration",) if "exploration" in required else ()):
        if not isinstance(state[name], dict):
            raise ValueError(f"{where}the checkpoint's {name!r} must be a state dict, got {type(state[name]).__name__}.")
    for name in counters:
        value = state.get(name, 0)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{where}the checkpoint's {name!r} must be an int >= 0, got {value!r}.")
    log = state["log"]
    if not isinstance(log, dict) or not set(log) <= set(_TRAINING_LOG_FIELDS) or not all(isinstance(v, list) for v in log.values()):
        raise ValueError(
            f"{where}the checkpoint's 'log' must be a dict of lists with keys among {list(_TRAINING_LOG_FIELDS)}, got "
            f"{log if not isinstance(log, dict) else sorted(map(str, log))!r}."
        )
    if "config" in state and not isinstance(state["config"], dict):
        raise ValueError(f"{where}the checkpoint's 'config' must be a dict, got {type(state['config']).__name__}.")
    rng = state.get("rng")
    if rng is not None and (not isinstance(rng, dict) or not {"torch", "numpy", "python"} <= set(rng)):
        raise ValueError(f"{where}the checkpoint's 'rng' must hold the 'torch', 'numpy' and 'python' random states.")
    if not isinstance(state.get("generators", {}), dict):
        raise ValueError(f"{where}the checkpoint's 'generators' must be a dict of generator states.")
    return where


def _restore_or_roll_back(where: str, parts: list[tuple[str, Any, Any]]) -> None:
    """Loads each ``(name, module or optimizer, state dict)`` in turn; when one does not fit, those already loaded
    are put back as they were and a ``ValueError`` names the part."""
    import copy

    done = []
    for name, target, state in parts:
        backup = copy.deepcopy(target.state_dict())
        try:
            target.load_state_dict(state)
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as err:
            for _, t, b in reversed(done):
                t.load_state_dict(b)
            detail = str(err).splitlines()[0] if str(err) else type(err).__name__
            if name == "loss_module":
                raise ValueError(
                    f"{where}the checkpoint's networks do not fit this agent's (another action space, number of "
                    f"options or hidden sizes?): {detail} ..."
                ) from None
            raise ValueError(f"{where}the checkpoint's {name} state does not fit this agent's: {detail}") from None
        done.append((name, target, backup))


def _with_reward_sum_and_step_count(env: EnvBase) -> EnvBase:
    if "episode_reward" not in env.observation_spec.keys():
        env = env.append_transform(RewardSum())
    if "step_count" not in env.observation_spec.keys():
        env = env.append_transform(StepCounter())
    return env


def _greedy_returns(env: EnvBase, actor: nn.Module, num_episodes: int, max_steps: int, seed: int) -> list[float]:
    """Returns of the first ``num_episodes`` episodes of ``actor``'s deterministic policy on ``env`` (seeded with
    ``seed``, its executors too), run for ``max_steps`` steps; closes ``env``."""
    env.set_seed(seed)
    seed_executors(env, seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        data = env.rollout(max_steps, actor, auto_cast_to_device=True, break_when_any_done=False)
    env.close()
    done = data.get(("next", "done")).squeeze(-1)
    returns = data.get(("next", "episode_reward")).squeeze(-1)
    if data.ndim > 1:  # [*envs, T] -> [T, *envs]: episodes in the order they ended
        done, returns = done.movedim(-1, 0), returns.movedim(-1, 0)
    return returns[done][:num_episodes].tolist()


def _count_executors(env: EnvBase) -> int:
    # (batched envs forward unknown attributes to their workers: only look inside a TransformedEnv)
    if not isinstance(env, TransformedEnv):
        return 0
    return sum(isinstance(m, OptionExecutor) for m in env.transform.modules())


def _generators(env: EnvBase) -> dict[str, torch.Generator]:
    """The private ``torch.Generator`` of the env and of each of its transforms (e.g. the option executor's), by
    position; only those created so far."""
    found = {}
    parts = [("env", env)]
    if isinstance(env, TransformedEnv):
        parts = [("env", env.base_env)] + [(f"transform{i}", t) for i, t in enumerate(env.transform.modules())]
    for name, obj in parts:
        # a public ``generator`` property (the option executor's private stream, ``None`` when it draws from torch's
        # default generator), else a generator attribute; no plain getattr: envs and transforms forward unknown
        # attributes
        if isinstance(getattr(type(obj), "generator", None), property):
            g = obj.generator
            if isinstance(g, torch.Generator):
                found[f"{name}.generator"] = g
            continue
        for attr in ("generator", "_generator", "rng", "_rng"):
            g = vars(obj).get(attr)
            if isinstance(g, torch.Generator):
                found[f"{name}.{attr}"] = g
                break
    return found


class OptionsDQN(CollectorTraining):
    """DQN over actions, options or both, on any env with a ``Categorical`` action.

    Args:
        env_factory (Callable[[], EnvBase]): makes one env with a ``Categorical(A)`` action and a flat
            ``config.observation_key`` observation (or pass ``q_network``). Called ``num_envs`` times.
        config (OptionsDQNConfig): hyper-parameters.

    Keyword Args:
        options (TensorDictModuleBase, optional): writes ``option_logits`` ``[..., K, A]`` and
            ``termination_logits`` ``[..., K]``; required unless ``config.mode == "actions"``.
        num_options (int, optional): ``K``; required with ``options``.
        q_network (nn.Module, optional): maps the observation to one value per augmented action. Defaults
            to an MLP with ``config.hidden_sizes``.
        optimizer (Callable, optional): a factory called as ``optimizer(params, lr=config.lr)``. Defaults to
            ``torch.optim.Adam``. ``functools.partial(torch.optim.Adam, fused=True)`` runs Adam as one fused
            kernel: several times faster per update on the Atari RAM one-hot network (1M parameters) on CPU
            (``benchmarks/bench_dqn_update.py``).

    Attributes:
        env: the (batched, transformed) training env. ``env.full_action_spec_unbatched["action"]`` is the
            augmented action space.
        policy: Q-actor followed by epsilon-greedy exploration; ``actor`` is the greedy Q-actor.
        loss_module, optimizer, replay_buffer, frames (primitive env steps so far), log (:class:`TrainingLog`).

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.envs import GymEnv
        >>> from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
        >>> class Push(torch.nn.Module):  # two options: push left / push right, 4 steps on average
        ...     def forward(self, obs):
        ...         logits = torch.tensor([[5.0, -5.0], [-5.0, 5.0]]).expand(*obs.shape[:-1], 2, 2)
        ...         return logits, torch.full((*obs.shape[:-1], 2), -1.1)
        >>> options = TensorDictModule(Push(), ["observation"], ["option_logits", "termination_logits"])
        >>> config = OptionsDQNConfig(mode="both", num_envs=2, total_frames=256, frames_per_batch=64)
        >>> agent = OptionsDQN(lambda: GymEnv("CartPole-v1", categorical_action_encoding=True), config,
        ...                    options=options, num_options=2)
        >>> log = agent.train()
        >>> agent.frames, len(log.episode_returns) > 0
        (256, True)
        >>> checkpoint = agent.state_dict()  # networks, target, optimizer, epsilon, counters, log
    """

    def __init__(
        self,
        env_factory: Callable[[], EnvBase],
        config: OptionsDQNConfig | None = None,
        *,
        options: TensorDictModuleBase | None = None,
        num_options: int | None = None,
        q_network: nn.Module | None = None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
    ):
        self.config = config = OptionsDQNConfig() if config is None else config
        _check_agent_arguments("OptionsDQN", env_factory, config, OptionsDQNConfig, options, num_options)
        _check_network(q_network, "q_network")
        if optimizer is not None and (isinstance(optimizer, torch.optim.Optimizer) or not callable(optimizer)):
            raise TypeError(
                "optimizer must be a factory called as optimizer(params, lr=config.lr) (e.g. torch.optim.Adam or "
                f"functools.partial(torch.optim.Adam, fused=True)), got {type(optimizer).__name__}."
            )
        self._executor_level = 0
        self.env_factory = env_factory
        self.options = options
        self.num_options = num_options
        self.device = torch.device(config.device)
        self.env = self.make_env()

        spec = _check_env("OptionsDQN", self.env, config)
        if config.intra_option_actions and (config.mode != "both" or self._executor_level != 1):
            raise ValueError(
                "intra_option_actions=True needs mode='both' over an env's own primitive actions (a level-1 "
                f"executor), got mode={config.mode!r} with an executor at level {self._executor_level}."
            )
        if config.option_suffixes and (config.mode == "actions" or self._executor_level != 1):
            raise ValueError(
                "option_suffixes=True needs options (mode 'both' or 'options') run by a level-1 executor, got "
                f"mode={config.mode!r} with an executor at level {self._executor_level}."
            )
        if config.option_suffixes and config.discount_per != "step":
            raise ValueError("option_suffixes=True discounts per primitive step: it needs discount_per='step'.")
        self._num_primitive = int(spec.n) - (num_options or 0) if config.mode == "both" else None
        if q_network is None:
            obs_dim = self.env.observation_spec[config.observation_key].shape[-1]
            q_network = MLP(in_features=obs_dim, out_features=spec.n, num_cells=list(config.hidden_sizes))
        self.actor = QValueActor(q_network, in_keys=[config.observation_key], spec=spec).to(self.device)
        self.exploration = EGreedyModule(
            spec,
            eps_init=config.eps_init,
            eps_end=config.eps_end,
            annealing_num_steps=max(config.eps_annealing_frames, 1),
        ).to(self.device)
        self.policy = TensorDictSequential(self.actor, self.exploration)

        self.loss_module = DQNLoss(
            self.actor,
            loss_function=config.loss_function,
            delay_value=True,
            double_dqn=config.double_dqn,
            action_space=spec,
        )
        # TD(0) over decisions: y = R + gamma^k (1 - terminated) max_a Q'(s', a), k = steps_to_next_obs
        self.loss_module.make_value_estimator(ValueEstimators.TD0, gamma=config.gamma)
        if config.target_update == "hard":
            self.target_updater = HardUpdate(self.loss_module, value_network_update_interval=config.hard_update_interval)
        else:
            self.target_updater = SoftUpdate(self.loss_module, eps=config.soft_update_eps)
        self.optimizer = (optimizer or torch.optim.Adam)(self.loss_module.parameters(), lr=config.lr)
        if not isinstance(self.optimizer, torch.optim.Optimizer):
            raise TypeError(f"optimizer must make a torch.optim.Optimizer, got {type(self.optimizer).__name__}.")
        self.replay_buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(config.buffer_size, device=self.device), batch_size=config.batch_size
        )
        self.smdp = SMDPTransitions(config.gamma, discount_per=config.discount_per)
        self.frames = 0
        self.gradient_steps = 0
        self.log = TrainingLog()

    # ------------------------------------------------------------------ env
    def make_env(self) -> EnvBase:
        """The training env: batched envs, then the executor (outside the batch), a ``DecisionCounter`` (with
        ``config.max_decisions``), ``RewardSum``, ``StepCounter``."""
        config = self.config
        env = _batched_env(self.env_factory, config.num_envs, config.parallel)
        if config.mode != "actions":
            # over an env that already runs options (a lower level of a hierarchy), these options are one level up
            self._executor_level = 1 + _count_executors(env)
            executor = OptionExecutor(
                self.options,
                num_options=self.num_options,
                primitive_actions=config.mode == "both",
                greedy=config.greedy_options,
                level=self._executor_level,
            )
            env = env.append_transform(executor)
            seed_executors(env, config.seed)  # the options' draws have their own stream, apart from exploration's
        if config.max_decisions is not None:
            # counts the decisions of the top executor (the policy's), or every step without an executor
            env = env.append_transform(DecisionCounter(config.max_decisions, level=_count_executors(env) or None))
        return _with_reward_sum_and_step_count(env)

    # ------------------------------------------------------------- training
    # ------------------------------------------------------------- training (the loop: CollectorTraining.train)
    def _collector_policy(self) -> nn.Module:
        return self.policy

    def _start_episodes(self) -> None:
        self.smdp.reset()

    def _learn(self, batch: TensorDictBase) -> None:
        """The batch's decisions (and intra-option steps) into the replay buffer, then the gradient steps."""
        decisions = self.smdp(batch)  # [M]; empty when no decision ended in this batch
        if self._adds_intra_option_steps:
            decisions = self._with_intra_option_steps(decisions, batch)
        if decisions.shape[0]:
            self.replay_buffer.extend(decisions)
        self.exploration.step(batch.numel())
        if len(self.replay_buffer) >= max(self.config.learning_starts, 1):
            for _ in range(self.config.updates_per_batch):
                self._update()

    @property
    def _adds_intra_option_steps(self) -> bool:
        return self.config.intra_option_actions or self.config.option_suffixes

    def _with_intra_option_steps(self, decisions: TensorDictBase, batch: TensorDictBase) -> TensorDictBase:
        """The decisions, then the one-step primitive transitions and the option suffixes that are enabled."""
        parts = [decisions.set("intra_option", torch.zeros(decisions.shape, dtype=torch.bool, device=decisions.device))]
        if self.config.intra_option_actions:
            parts.append(intra_option_transitions(batch, num_actions=self._num_primitive))
        if self.config.option_suffixes:
            parts.append(option_suffix_transitions(batch, self.config.gamma, action_offset=self._num_primitive or 0))
        for part in parts[1:]:
            part.set("intra_option", torch.ones(part.shape, dtype=torch.bool, device=part.device))
            self.smdp.with_duration(part)  # per decision, the decisions carry their length apart from k = 1
        return torch.cat([parts[0]] + [p.to(decisions.device) for p in parts[1:]], 0)

    def _update(self) -> None:
        sample = self.replay_buffer.sample().to(self.device)
        loss = self.loss_module(sample)["loss"]
        self.optimizer.zero_grad()
        loss.backward()
        if self.config.max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), self.config.max_grad_norm)
        self.optimizer.step()
        self.target_updater.step()
        self.gradient_steps += 1
        self.log.losses.append(loss.item())

    def _record_episodes(self, batch: TensorDictBase) -> None:
        returns = self.log.record_episodes(batch, self.frames)
        if returns is None:
            return
        logger.info(
            "frames %d: %d episodes, mean return %.3f, epsilon %.3f",
            self.frames + batch.numel(),
            len(returns),
            returns.float().mean().item(),
            self.exploration.eps.item(),
        )

    # ----------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, num_episodes: int = 10, max_steps: int = 1000) -> list[float]:
        """Returns of the first ``num_episodes`` episodes of the greedy policy (options act as configured).

        Runs one env from ``env_factory`` (batched if the factory makes batched envs) for at most
        ``max_steps`` steps per call; episodes still running then are not counted.
        """
        check_int(num_episodes, "num_episodes", minimum=1)
        check_int(max_steps, "max_steps", minimum=1)
        saved, self.config.num_envs = self.config.num_envs, 1
        try:
            env = self.make_env()
        finally:
            self.config.num_envs = saved
        return _greedy_returns(env, self.actor, num_episodes, max_steps, self.config.seed + 10_000)

    def record_evaluation(self, num_episodes: int = 10, max_steps: int = 1000) -> float:
        """Runs :meth:`evaluate` and appends ``[episodes, frames, mean return, episodes evaluated]`` to
        ``log.evaluations`` (saved with the checkpoints); returns the mean.

        The evaluation draws its random numbers (option actions, no-op starts) from a forked generator, so that
        training goes on exactly as it would have without it, also when called from a :meth:`train` callback; and
        it reseeds its env the same way each time, so that evaluations of different agents (or of one agent at
        different times) play the same games.

        Raises:
            RuntimeError: if no episode finished within ``max_steps`` (raise ``max_steps``).

        Examples:
            >>> from torchrl.envs import GymEnv
            >>> from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
            >>> config = OptionsDQNConfig(mode="actions", total_frames=128, frames_per_batch=64)
            >>> agent = OptionsDQN(lambda: GymEnv("CartPole-v1", categorical_action_encoding=True), config)
            >>> log = agent.train()
            >>> mean = agent.record_evaluation(num_episodes=2, max_steps=500)
            >>> agent.log.evaluations[-1][1:] == [128, mean, 2]
            True
        """
        check_int(num_episodes, "num_episodes", minimum=1)
        check_int(max_steps, "max_steps", minimum=1)
        devices = [self.device] if self.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            returns = self.evaluate(num_episodes=num_episodes, max_steps=max_steps)
        if not returns:
            raise RuntimeError(f"no evaluation episode finished within max_steps={max_steps}; raise max_steps.")
        mean = float(sum(returns) / len(returns))
        self.log.evaluations.append([len(self.log.episode_returns), self.frames, mean, len(returns)])
        return mean

    # ---------------------------------------------------------- checkpoints
    def state_dict(self, include_buffer: bool = False) -> dict[str, Any]:
        """Networks (online and target, in ``loss_module``), optimizer, epsilon, counters, log and every random
        state the training draws from (:func:`~torchrl_options.checkpoints.rng_state`, and the private generators
        of the env and its transforms, such as the option executor's), as plain data: the checkpoint loads with
        ``weights_only=True`` and a run resumed from it draws the same numbers as an uninterrupted one."""
        check_bool(include_buffer, "include_buffer")
        state = {
            "loss_module": self.loss_module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "exploration": self.exploration.state_dict(),
            "frames": self.frames,
            "gradient_steps": self.gradient_steps,
            # HardUpdate counts gradient steps towards its next copy of the target network
            "target_update_counter": int(getattr(self.target_updater, "counter", 0)),
            "log": asdict(self.log),
            "config": asdict(self.config),
            "rng": rng_state(),
            "generators": {name: g.get_state() for name, g in _generators(self.env).items()},
        }
        if include_buffer:
            state["replay_buffer"] = self.replay_buffer.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores :meth:`state_dict` (random states included when the checkpoint has them).

        The checkpoint is checked whole before anything is restored: a bad one leaves the agent as it was.

        Raises:
            ValueError: ``state`` lacks an entry, holds one of the wrong type, or was saved by an agent over another
                action space or network.
        """
        self._load_state(state, None)

    def _load_state(self, state: Any, source: str | None) -> None:
        where = _check_state(
            state, "OptionsDQN", ("loss_module", "optimizer", "exploration", "frames", "gradient_steps", "log"),
            ("frames", "gradient_steps", "target_update_counter"), source,
        )  # fmt: skip
        saved_mode = state.get("config", {}).get("mode", self.config.mode)
        if saved_mode != self.config.mode:
            raise ValueError(f"{where}the checkpoint is of mode={saved_mode!r}, this agent has mode={self.config.mode!r}.")
        _restore_or_roll_back(
            where,
            [("loss_module", self.loss_module, state["loss_module"]), ("optimizer", self.optimizer, state["optimizer"]),
             ("exploration", self.exploration, state["exploration"])],
        )  # fmt: skip
        self.frames = int(state["frames"])
        self.gradient_steps = int(state["gradient_steps"])
        if "target_update_counter" in state and hasattr(self.target_updater, "counter"):
            self.target_updater.counter = int(state["target_update_counter"])
        self.log = TrainingLog(**{k: list(v) for k, v in state["log"].items()})
        if "replay_buffer" in state:
            self.replay_buffer.load_state_dict(state["replay_buffer"])
        if "rng" in state:
            set_rng_state(state["rng"])
            generators = _generators(self.env)
            for name, g_state in state.get("generators", {}).items():
                if name in generators:
                    generators[name].set_state(g_state)
        else:
            logger.warning("the checkpoint has no random state (older format): the resumed run is not bit-for-bit.")

    @torch.no_grad()
    def warm_start_from(self, source: OptionsDQN, *, copy_buffer: bool = True) -> OptionsDQN:
        """Starts this agent (over actions + options) from ``source``, a trained agent over actions only.

        Copies the online and target networks, the output layer widened by one row per option (each new row the
        mean of the primitive rows: :func:`~torchrl_options.agents.warm_start.widen_action_rows`), and the replay
        buffer (primitive decisions stay valid transitions of the augmented action space). The optimizer starts
        afresh (the parameter shapes changed); frames, epsilon and the log are this agent's own. Fox et al. (2017)
        restart the Q-function instead; this keeps what the agent learned before the options were added.

        Args:
            source (OptionsDQN): an agent with ``mode="actions"`` on the same env, with the same Q-network
                architecture but for the output width.

        Keyword Args:
            copy_buffer (bool): also copy ``source``'s replay buffer (default ``True``).

        Returns:
            this agent.

        Raises:
            ValueError: ``source`` is not an actions-only agent, this one has no primitive actions, or their
                action counts do not fit.

        Examples:
            >>> import torch
            >>> from tensordict.nn import TensorDictModule
            >>> from torchrl.envs import GymEnv
            >>> make_env = lambda: GymEnv("CartPole-v1", categorical_action_encoding=True)
            >>> base = OptionsDQN(make_env, OptionsDQNConfig(mode="actions", total_frames=128, frames_per_batch=64))
            >>> _ = base.train()
            >>> class Push(torch.nn.Module):
            ...     def forward(self, obs):
            ...         logits = torch.tensor([[5.0, -5.0], [-5.0, 5.0]]).expand(*obs.shape[:-1], 2, 2)
            ...         return logits, torch.full((*obs.shape[:-1], 2), -1.1)
            >>> options = TensorDictModule(Push(), ["observation"], ["option_logits", "termination_logits"])
            >>> agent = OptionsDQN(make_env, OptionsDQNConfig(mode="both", total_frames=128, frames_per_batch=64),
            ...                    options=options, num_options=2).warm_start_from(base)
            >>> len(agent.replay_buffer) == len(base.replay_buffer)
            True
        """
        if not isinstance(source, OptionsDQN):
            raise TypeError(f"warm_start_from: source must be an OptionsDQN, got {type(source).__name__}.")
        check_bool(copy_buffer, "copy_buffer")
        if source.config.mode != "actions":
            raise ValueError(f"warm_start_from: source must have mode='actions', got {source.config.mode!r}.")
        if self.config.mode != "both":
            raise ValueError(
                f"warm_start_from: this agent must have mode='both' (primitive actions first), got {self.config.mode!r}."
            )
        n_source = int(source.env.full_action_spec_unbatched["action"].n)
        n_self = int(self.env.full_action_spec_unbatched["action"].n)
        if n_self - n_source != (self.num_options or 0):
            raise ValueError(
                f"warm_start_from: the source has {n_source} actions and this agent {n_self} = actions + "
                f"{self.num_options} options; expected {n_source} + {self.num_options}."
            )
        state = widen_action_rows(source.loss_module.state_dict(), self.loss_module.state_dict(), n_source)
        self.loss_module.load_state_dict(state)
        if copy_buffer and len(source.replay_buffer):
            data = source.replay_buffer[: len(source.replay_buffer)].exclude("index")
            if self._adds_intra_option_steps:  # the copied transitions are decisions
                data.set("intra_option", torch.zeros(data.shape, dtype=torch.bool, device=data.device))
            self.replay_buffer.extend(widen_action_values(data.to(self.device), n_self))
        return self

    def save(self, path, include_buffer: bool = False) -> None:
        """Writes :meth:`state_dict` to ``path`` (plain data, atomically)."""
        save_file(self.state_dict(include_buffer=include_buffer), path)

    def load(self, path) -> None:
        """Restores a checkpoint written by :meth:`save`, without running code from the file.

        Raises:
            ValueError: the file is missing, empty, corrupt, needs pickle, or does not fit this agent.
        """
        self._load_state(load_file(path, what="OptionsDQN checkpoint", map_location=self.device), os.fspath(path))
