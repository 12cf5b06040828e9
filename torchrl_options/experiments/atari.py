"""The Atari RAM experiment of the DDO paper (figure 3) as a resumable per-cell pipeline, and its summary.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.2: DQN with primitive
actions for N episodes; 100 greedy trajectories of that DQN; DDO with K options per game; then DQN over actions
and options from a reset Q-function, against the baseline that continues the first DQN with actions only.

A cell is ``(game, condition, seed)``. The conditions: ``"A"``, the baseline (phase 1's DQN continued with actions
only); ``"H1"``, the paper's (actions + options, Q-function reset); and others that the paper does not run:
``"A0"``, a control (actions only, Q-function reset: what the reset alone costs); ``"H1w"``, options added
to phase 1's DQN without a reset (:meth:`~torchrl_options.agents.OptionsDQN.warm_start_from`); ``"H1g"``, as
``H1`` but each option acts with the argmax of its control policy instead of sampling from it. (DDO fits
stochastic policies to a deterministic demonstrator, the greedy phase-1 DQN; a short fit leaves them far from
deterministic, so a sampled option also explores, where the paper's argument is that options carry the
demonstrator's behaviour uninterrupted by exploration.) And ``"H1i"``, as ``H1`` but the Q-function also learns
its primitive actions' values from the steps that options take (``OptionsDQNConfig.intra_option_actions``): under
``H1`` the steps inside options, often half of all steps, teach the primitive actions nothing, where ``A0`` learns
from every step. ``"H1s"``: as ``H1``, but the options' values are also learned from every step they run, the rest
of each run being a sample of starting the option there (``OptionsDQNConfig.option_suffixes``). The letters
combine, in the order ``w``, ``g``, ``i``, ``s``: ``"H1wi"`` is the warm start with intra-option transitions,
``"H1is"`` learns both kinds of values from every step (all in :data:`CONDITIONS`). The paper's comparison is ``H1``
against ``A``.
The conditions of a seed share phases 1 and 2, cached in ``<out>/<game>/seed<s>/`` (a file lock makes later cells
wait for, then reuse, the first one's phase-1 checkpoint and options). Every phase checkpoints at its end and
every ``checkpoint_every`` episodes, and resumes from there.

What a cell returns (one row per episode in ``results.csv``): the phase-1 episodes followed by the phase-3
episodes, so both conditions have ``phase1_episodes + phase3_episodes`` episodes and share the first part.
``frames`` is the cumulative number of env steps (agent steps; ``frame_skip`` emulator frames each) at the end of
each episode, counted from the start of phase 1; for the options conditions (``H1...``) it includes the frames of
the greedy demonstrations of phase 2, which the baseline does not spend.
"""
from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import logging
import os
import time
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields
from functools import partial
from typing import Any, ClassVar

import numpy as np
import torch
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.utils import step_mdp

from torchrl_options.checkpoints import load_file, save_file
from torchrl_options.experiments.intervals import interval_verdict, mean_interval, paired_difference_interval
from torchrl_options.experiments.results import ResultsLog, smooth
from torchrl_options.experiments.sweep import Cell, CellResult

__all__ = [
    "AtariConfig",
    "run_atari_cell",
    "atari_cells",
    "atari_comparison",
    "atari_summary_markdown",
    "write_option_frames",
    "option_usage",
    "option_usage_markdown",
    "greedy_evaluation_markdown",
    "atari_summary_pairs",
    "atari_scores",
    "atari_aggregates",
]

logger = logging.getLogger(__name__)

#: what may follow ``"H1"`` in a condition's name, in this order: ``w`` options added to phase 1's DQN (no reset),
#: ``g`` options act greedily, ``i`` intra-option transitions for the primitive actions, ``s`` option suffixes
OPTION_FLAGS = ("w", "g", "i", "s")
CONDITIONS = ("A", "A0", "H1") + tuple(
    "H1" + "".join(letters)
    for n in range(1, len(OPTION_FLAGS) + 1)
    for letters in itertools.combinations(OPTION_FLAGS, n)
)


@dataclass(frozen=True)
class _OptionFlags:
    warm: bool
    greedy: bool
    intra: bool
    suffixes: bool


def _option_flags(condition: str) -> _OptionFlags | None:
    """The flags of an options condition (``"H1"`` then any of :data:`OPTION_FLAGS`, in order); ``None`` for ``A``
    and ``A0``."""
    if not condition.startswith("H1"):
        return None
    rest = condition[2:]
    return _OptionFlags(warm="w" in rest, greedy="g" in rest, intra="i" in rest, suffixes="s" in rest)


def _describe(condition: str) -> str:
    flags = _option_flags(condition)
    if flags is None:
        baselines = {"A": "the phase-1 DQN continued with actions only", "A0": "DQN over actions only from a reset Q-function"}
        return baselines[condition]
    text = "DQN over actions + DDO options" + (
        ", started from phase 1's DQN (output layer widened, replay kept)" if flags.warm else " from a reset Q-function"
    )
    if flags.greedy:
        text += ", each option acting with the argmax of its control policy"
    if flags.intra:
        text += ", the primitive actions' values also learned from the steps options take"
    if flags.suffixes:
        text += ", the options' values also learned from every step they run (option suffixes)"
    return text


@dataclass
class AtariConfig:
    """Settings of one Atari RAM cell (mirrors ``recipes/config/atari_ram.yaml``).

    Env: ``frame_skip``, ``repeat_action_probability``, ``noop_max``, ``episodic_life``, ``clip_rewards``,
    ``max_episode_steps`` (see :func:`~torchrl_options.envs.atari.make_atari_ram_env`); ``ram_encoding`` is the
    Q-network's input layer: ``"one_hot"`` (the paper's 128 x 256) or ``"bytes"``. The options networks read
    ``bytes / 255``.

    Phases: ``phase1_episodes`` (DQN, actions), ``num_demonstrations`` greedy trajectories of at most
    ``demo_max_steps`` steps, DDO with ``num_options`` (``None``: the paper's count for the game) for
    ``ddo_iterations`` iterations of ``ddo_m_steps`` optimizer steps each (1: the paper's Expectation-Gradient;
    more: a generalised EM that fits the demonstrations much more closely for the same E-steps, see
    :func:`~torchrl_options.discover_options`), then ``phase3_episodes`` for each condition.

    DQN (paper: epsilon 0.05, gamma 0.85, three dense tanh layers): ``hidden_sizes``, ``gamma``, ``eps_init``,
    ``eps_end``, ``eps_annealing_frames``, ``lr``, ``batch_size``, ``buffer_size``, ``learning_starts``,
    ``frames_per_batch``, ``updates_per_batch``, ``hard_update_interval``, ``double_dqn``, ``num_envs`` games
    batched in a ``SerialEnv`` (``ParallelEnv`` with ``parallel``; one gymnasium ``SyncVectorEnv`` with
    ``vector_env``, the fastest on few cores: see :func:`~torchrl_options.envs.atari.make_atari_ram_env`; the
    greedy demonstrations stay one game at a time), ``device``, ``fused_adam`` (Adam as one fused kernel: the
    same algorithm, several times faster per update on the one-hot network; ``benchmarks/bench_dqn_update.py``).

    Greedy evaluation (off by default; the paper plots the mean return of rollouts of the learned policy): each
    time a cell's episode count passes a multiple of ``eval_every``, ``eval_episodes`` episodes of the greedy
    policy (options run as in training) on freshly seeded games, the same games for every condition and every
    time (:meth:`~torchrl_options.agents.OptionsDQN.record_evaluation`); the cell's json file keeps them and
    ``summary.md`` compares the conditions on them.

    With batched games, episodes end several at a time and a phase stops at the first collector batch that
    completes its count: phase 1 may then have run up to ``num_envs - 1`` episodes more than
    ``phase1_episodes``. They are part of ``A``'s continuation (the same agent), so ``A``'s first phase-3 episodes
    may come from phase 1's last batch; the other conditions start new agents.
    """

    # env
    frame_skip: int = 4
    repeat_action_probability: float = 0.0
    noop_max: int = 30
    episodic_life: bool = False
    clip_rewards: bool = True
    max_episode_steps: int | None = None
    ram_encoding: str = "one_hot"
    # phases
    phase1_episodes: int = 1000
    phase3_episodes: int = 4000
    num_demonstrations: int = 100
    demo_max_steps: int = 2000
    num_options: int | None = None
    options_num_cells: tuple[int, ...] = (64, 64, 64)
    ddo_iterations: int = 500
    ddo_batch_size: int | None = 20
    ddo_lr: float = 1e-3
    ddo_m_steps: int = 1
    # DQN
    hidden_sizes: tuple[int, ...] = (64, 64, 64)
    gamma: float = 0.85
    eps_init: float = 0.05
    eps_end: float = 0.05
    eps_annealing_frames: int = 1
    lr: float = 1e-4
    batch_size: int = 64
    buffer_size: int = 100_000
    learning_starts: int = 1000
    frames_per_batch: int = 64
    updates_per_batch: int = 4
    hard_update_interval: int = 1000
    double_dqn: bool = False
    num_envs: int = 1
    parallel: bool = False
    vector_env: bool = False
    device: str = "cpu"
    fused_adam: bool = False
    # greedy evaluation (the paper's measure): every eval_every episodes of a cell (0: off)
    eval_every: int = 0
    eval_episodes: int = 8
    # outputs
    checkpoint_every: int = 100
    checkpoint_buffer: bool = True
    option_frames: bool = True
    option_frames_max_steps: int = 400
    torch_threads: int | None = None

    #: (minimum, allowed None) of every int setting, and [low, high] of every number: checked when the settings
    #: are read, before any work starts
    _INTS: ClassVar[dict[str, tuple[int, bool]]] = {
        "frame_skip": (1, False), "noop_max": (0, False), "max_episode_steps": (1, True), "phase1_episodes": (1, False),
        "phase3_episodes": (1, False), "num_demonstrations": (1, False), "demo_max_steps": (1, False),
        "num_options": (1, True), "ddo_iterations": (0, False), "ddo_batch_size": (1, True), "batch_size": (1, False),
        "buffer_size": (1, False), "learning_starts": (0, False), "frames_per_batch": (1, False),
        "updates_per_batch": (0, False), "hard_update_interval": (1, False), "num_envs": (1, False),
        "eval_every": (0, False), "eval_episodes": (1, False), "checkpoint_every": (0, False),
        "option_frames_max_steps": (1, False), "torch_threads": (1, True), "eps_annealing_frames": (0, False),
    }  # fmt: skip
    _NUMBERS: ClassVar[dict[str, tuple[float, float]]] = {
        "repeat_action_probability": (0.0, 1.0), "gamma": (0.0, 1.0), "eps_init": (0.0, 1.0), "eps_end": (0.0, 1.0),
    }  # fmt: skip

    def __post_init__(self) -> None:
        from torchrl_options.discovery._validation import check_int
        from torchrl_options.discovery.discover import _check_m_steps

        _check_m_steps(self.ddo_m_steps, name="ddo_m_steps")  # refused when the settings are read, not after phase 1
        for name, (minimum, allow_none) in self._INTS.items():
            check_int(getattr(self, name), name, minimum=minimum, allow_none=allow_none)
        for name, (lo, hi) in self._NUMBERS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
                raise ValueError(f"{name} must be a number in [{lo}, {hi}], got {value!r}.")
        for name in ("lr", "ddo_lr"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
                raise ValueError(f"{name} must be a number > 0, got {value!r}.")
        if self.ram_encoding not in ("one_hot", "bytes"):
            raise ValueError(f"ram_encoding must be 'one_hot' or 'bytes', got {self.ram_encoding!r}.")
        for name in ("hidden_sizes", "options_num_cells"):
            sizes = getattr(self, name)
            if not isinstance(sizes, (tuple, list)) or not sizes or not all(
                isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in sizes
            ):
                raise ValueError(f"{name} must be a non-empty list of ints >= 1, got {sizes!r}.")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AtariConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown Atari settings: {sorted(unknown)}")
        d = dict(d)
        for key in ("options_num_cells", "hidden_sizes"):
            if key in d and d[key] is not None:
                d[key] = tuple(d[key])
        return cls(**d)

    #: fields that change how a cell runs (device, threads, pictures, greedy evaluation, which leaves training's
    #: random numbers untouched, fused Adam, the same algorithm), not the episodes it records. ``checkpoint_every``
    #: is not one of them: training restarts its episodes at each checkpoint (what makes resuming exact)
    RUN_ONLY_FIELDS: ClassVar[tuple[str, ...]] = (
        "device", "parallel", "torch_threads", "fused_adam", "checkpoint_buffer", "eval_every",
        "eval_episodes", "option_frames", "option_frames_max_steps",
    )  # fmt: skip

    def cell_settings(self) -> dict[str, Any]:
        """The settings that define what a cell computes: every field but :attr:`RUN_ONLY_FIELDS`. The recipe records
        them in its ``out_dir`` and refuses to resume it with others
        (:func:`~torchrl_options.experiments.run_settings.check_run_settings`).

        Examples:
            >>> settings = AtariConfig(device="cuda").cell_settings()
            >>> settings["phase1_episodes"], "device" in settings
            (1000, False)
        """
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.RUN_ONLY_FIELDS}

    def env_kwargs(self) -> dict[str, Any]:
        return dict(
            frame_skip=self.frame_skip,
            repeat_action_probability=self.repeat_action_probability,
            noop_max=self.noop_max,
            episodic_life=self.episodic_life,
            clip_rewards=self.clip_rewards,
            max_episode_steps=self.max_episode_steps,
        )

    def options_for(self, game: str) -> int:
        from torchrl_options.envs.atari import PAPER_NUM_OPTIONS

        if self.num_options is not None:
            return int(self.num_options)
        return PAPER_NUM_OPTIONS.get(game, 4)


def atari_cells(games: Sequence[str], seeds: Sequence[int] | int, conditions: Sequence[str] = ("A", "H1")) -> list[Cell]:
    """The cells of a sweep, conditions outermost: the first cells of a pool then run the phases 1 and 2 of
    different seeds in parallel, and the other condition's cells find them cached (rather than wait on a lock).

    Examples:
        >>> [c.name for c in atari_cells(["Pooyan"], 2)]
        ['Pooyan-A-seed0', 'Pooyan-A-seed1', 'Pooyan-H1-seed0', 'Pooyan-H1-seed1']

    Raises:
        ValueError: a condition not in :data:`CONDITIONS` (``A``, ``A0``, or ``H1`` followed by any of ``w``, ``g``,
            ``i``, ``s`` in that order), or none.
    """
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad or not conditions:
        raise ValueError(f"conditions must be a non-empty list of {CONDITIONS}, got {list(conditions)}.")
    seeds = range(seeds) if isinstance(seeds, int) else seeds
    return [Cell(g, c, int(s)) for c in conditions for g in games for s in seeds]


# ---------------------------------------------------------------------------------------------- pipeline


def _env_factory(game: str, config: AtariConfig, seed: int, render: bool = False, batched: bool = False):
    """One game; with ``batched`` and ``config.vector_env``, the ``config.num_envs`` games of one vector env."""
    from torchrl_options.envs.atari import make_atari_ram_env

    num_envs = config.num_envs if batched and config.vector_env else 1
    return partial(
        make_atari_ram_env, game, **config.env_kwargs(), render=render, ram_encoding="bytes", num_envs=num_envs
    )


def _num_actions(game: str, config: AtariConfig) -> int:
    env = _env_factory(game, config, 0)()
    n = env.action_spec.n
    env.close()
    return int(n)


def _make_agent(game: str, config: AtariConfig, seed: int, mode: str, options=None, num_options=None,
                greedy_options: bool = False, intra_option_actions: bool = False, option_suffixes: bool = False):
    from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
    from torchrl_options.envs.atari import ram_q_network

    num_actions = _num_actions(game, config)
    out = num_actions + (num_options if mode == "both" else 0)
    torch.manual_seed(seed)
    q_net = ram_q_network(out, encoding=config.ram_encoding, num_cells=config.hidden_sizes)
    dqn_config = OptionsDQNConfig(
        mode=mode,
        num_envs=1 if config.vector_env else config.num_envs,  # a vector env is batched already
        parallel=config.parallel,
        total_frames=10**12,
        frames_per_batch=config.frames_per_batch,
        buffer_size=config.buffer_size,
        batch_size=config.batch_size,
        learning_starts=config.learning_starts,
        updates_per_batch=config.updates_per_batch,
        lr=config.lr,
        gamma=config.gamma,
        hidden_sizes=tuple(config.hidden_sizes),
        eps_init=config.eps_init,
        eps_end=config.eps_end,
        eps_annealing_frames=max(int(config.eps_annealing_frames), 1),
        hard_update_interval=config.hard_update_interval,
        double_dqn=config.double_dqn,
        greedy_options=greedy_options,
        intra_option_actions=intra_option_actions,
        option_suffixes=option_suffixes,
        seed=seed,
        device=config.device,
    )
    return OptionsDQN(
        _env_factory(game, config, seed, batched=True), dqn_config, options=options, num_options=num_options,
        q_network=q_net, optimizer=partial(torch.optim.Adam, fused=True) if config.fused_adam else None,
    )


def _close(agent) -> None:
    try:
        if not agent.env.is_closed:
            agent.env.close()
    except Exception as err:  # closing is best effort
        logger.debug("closing the env failed: %s", err)


def _atomic_save(obj: Any, path: str) -> None:
    save_file(obj, path)


def _evaluate_if_due(agent, config: AtariConfig, offset: int) -> None:
    """Greedy evaluation when the cell's episode count (``offset`` + the agent's) has passed a new multiple of
    ``eval_every`` since the agent's last evaluation."""
    if not config.eval_every:
        return
    done = offset + len(agent.log.episode_returns)
    last = offset + int(agent.log.evaluations[-1][0]) if agent.log.evaluations else offset
    if done // config.eval_every > last // config.eval_every:
        batch = config.num_envs if config.vector_env else 1  # evaluate() plays one env from the factory
        episodes_per_game = -(-config.eval_episodes // batch)
        agent.record_evaluation(config.eval_episodes, episodes_per_game * (config.max_episode_steps or 27_000))


def _train_episodes(agent, num_episodes: int, partial_path: str, config: AtariConfig, offset: int = 0) -> None:
    """Trains ``agent`` until its log holds ``num_episodes`` episodes, checkpointing every ``checkpoint_every``
    and evaluating (see :func:`_evaluate_if_due`; ``offset``: the cell's episodes before this agent's).

    Training runs in chunks of ``checkpoint_every`` episodes, each a fresh :meth:`OptionsDQN.train` (new
    episodes, envs seeded from the frame count) ending with a checkpoint that holds every random state (and the
    replay buffer with ``checkpoint_buffer``): a run resumed from the checkpoint is the uninterrupted run, bit for
    bit."""
    while len(agent.log.episode_returns) < num_episodes:
        start = len(agent.log.episode_returns)
        target = min(start + config.checkpoint_every, num_episodes) if config.checkpoint_every else num_episodes

        def callback(agent, batch, target=target):
            _evaluate_if_due(agent, config, offset)
            return len(agent.log.episode_returns) >= target

        agent.train(total_frames=10**12, callback=callback)
        if config.checkpoint_every and len(agent.log.episode_returns) < num_episodes:
            _atomic_save(agent.state_dict(include_buffer=config.checkpoint_buffer), partial_path)


def _load_if(agent, path: str) -> bool:
    if os.path.exists(path):
        agent.load_state_dict(load_file(path, what="Atari DQN checkpoint", map_location=agent.device))
        logger.info("resumed from %s (%d episodes)", path, len(agent.log.episode_returns))
        return True
    return False


@contextlib.contextmanager
def _file_lock(path: str):
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _greedy_rollouts(agent, game: str, config: AtariConfig, seed: int, n: int, max_steps: int, render=False):
    """``n`` greedy trajectories of the agent's Q-network, one env at a time (and their RGB frames if asked)."""
    from torchrl_options.envs.atari import render_frame

    env = _env_factory(game, config, seed, render=render)()
    env.set_seed(seed + 777)
    actor = agent.actor
    trajectories, frames = [], []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(n):
            if not render:
                td = env.rollout(max_steps, actor, auto_cast_to_device=True)
                trajectories.append(td.cpu())
                continue
            td = env.reset()
            steps, screens = [], []
            for _ in range(max_steps):
                screens.append(render_frame(env))
                td = actor(td.to(agent.device)).cpu()
                td = env.step(td)
                steps.append(td.clone())
                td = step_mdp(td)
                if steps[-1]["next", "done"].any():
                    break
            trajectories.append(torch.stack(steps))
            frames.append(screens)
    env.close()
    return (trajectories, frames) if render else trajectories


def _phase1(game: str, config: AtariConfig, seed: int, seed_dir: str):
    path = os.path.join(seed_dir, "phase1.pt")
    agent = _make_agent(game, config, seed, "actions")
    if not _load_if(agent, path):
        partial_path = os.path.join(seed_dir, "phase1.partial.pt")
        _load_if(agent, partial_path)
        t0 = time.time()
        _train_episodes(agent, config.phase1_episodes, partial_path, config)
        _atomic_save(agent.state_dict(include_buffer=config.checkpoint_buffer), path)
        logger.info("%s seed %d: phase 1 done in %.0fs", game, seed, time.time() - t0)
        if os.path.exists(partial_path):
            os.remove(partial_path)
    return agent, path


def _phase2(game: str, config: AtariConfig, seed: int, seed_dir: str, agent):
    from torchrl_options.discovery import discover_options, load_options, save_options

    path = os.path.join(seed_dir, "options.pt")
    if os.path.exists(path):
        options, _, metadata = load_options(path, with_meta_control=True)
        return options, metadata
    t0 = time.time()
    demos = _greedy_rollouts(agent, game, config, seed, config.num_demonstrations, config.demo_max_steps)
    demo_frames = int(sum(t.numel() for t in demos))
    k = config.options_for(game)
    result = discover_options(
        [t.select("observation", "action", ("next", "observation"), ("next", "done"), ("next", "terminated")) for t in demos],
        num_options=k,
        num_actions=_num_actions(game, config),
        num_cells=list(config.options_num_cells),
        activation="tanh",
        num_iterations=config.ddo_iterations,
        batch_size=config.ddo_batch_size,
        lr=config.ddo_lr,
        m_steps=config.ddo_m_steps,
        restarts=1,  # the paper's protocol: one start, every iteration run
        tol=None,
        device=config.device,
        seed=seed,
        progress=False,
        return_info=True,
    )
    metadata = {
        "game": game,
        "num_options": k,
        "demo_frames": demo_frames,
        "demo_returns": [float(t["next", "reward"].sum()) for t in demos],
        "log_likelihood_per_step": result.final_log_likelihood_per_step,
        "option_duration": result.history[-1].get("option_duration", float("nan")) if result.history else float("nan"),
        "seconds": time.time() - t0,
    }
    options = result.options.cpu()
    save_options(options, path, metadata=metadata)
    logger.info("%s seed %d: DDO done, %s", game, seed, metadata)
    return options, metadata


def option_usage(agent, num_actions: int, start: int = 0) -> dict[str, float]:
    """How much an agent over actions + options used its options, from the decisions in its replay buffer.

    Reads the decisions stored from position ``start`` on (to skip decisions copied in by a warm start), up to
    the buffer's capacity, leaving out the one-step transitions of steps inside options (``"intra_option"``, with
    ``OptionsDQNConfig.intra_option_actions``). A decision is an option when its action index is ``num_actions`` or
    more.

    Returns:
        ``option_decision_share`` (fraction of decisions that started an option), ``option_step_share``
        (fraction of env steps spent inside options) and ``mean_option_steps`` (mean steps per option run;
        NaN when no option ran).

    Examples:
        >>> import torch
        >>> from types import SimpleNamespace
        >>> from tensordict import TensorDict
        >>> buf = TensorDict(action=torch.tensor([0, 3, 1, 4]), steps_to_next_obs=torch.tensor([[1], [5], [1], [3]]),
        ...                  batch_size=[4])
        >>> option_usage(SimpleNamespace(replay_buffer=buf), num_actions=3)
        {'option_decision_share': 0.5, 'option_step_share': 0.8, 'mean_option_steps': 4.0}
    """
    n = len(agent.replay_buffer)
    if n <= start:
        return {"option_decision_share": float("nan"), "option_step_share": float("nan"), "mean_option_steps": float("nan")}
    data = agent.replay_buffer[start:n]
    if "intra_option" in data.keys():
        data = data[~data.get("intra_option").reshape(-1)]
    is_option = data.get("action").reshape(-1) >= num_actions
    steps = data.get("steps_to_next_obs").reshape(-1).float()
    option_steps = steps[is_option]
    return {
        "option_decision_share": float(is_option.float().mean()),
        "option_step_share": float(option_steps.sum() / steps.sum()),
        "mean_option_steps": float(option_steps.mean()) if option_steps.numel() else float("nan"),
    }


def run_atari_cell(cell: Cell, *, config: AtariConfig | dict, out_dir: str) -> CellResult:
    """Runs one ``(game, condition, seed)`` cell of the Atari RAM experiment, resuming from its checkpoints.

    Args:
        cell (Cell): ``setting`` is the game (``"Seaquest"``), ``condition`` one of :data:`CONDITIONS`: ``"A"``,
            ``"A0"``, ``"H1"``, and ``"H1"`` followed by any of ``w``, ``g``, ``i``, ``s`` (see the module docstring).

    Keyword Args:
        config (AtariConfig or dict): the settings.
        out_dir (str): the experiment's output directory (checkpoints go to ``<out_dir>/<game>/seed<s>/``).

    Returns:
        The phase-1 then phase-3 episode returns, and cumulative frames (see the module docstring).
    """
    if isinstance(config, dict):
        config = AtariConfig.from_dict(config)
    if cell.condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {cell.condition!r}.")
    if config.torch_threads:
        torch.set_num_threads(config.torch_threads)
    game, seed = cell.setting, cell.seed
    seed_dir = os.path.join(out_dir, game, f"seed{seed}")
    os.makedirs(seed_dir, exist_ok=True)
    t0 = time.time()
    with _file_lock(os.path.join(seed_dir, ".lock")):
        agent, _ = _phase1(game, config, seed, seed_dir)
        options, metadata = _phase2(game, config, seed, seed_dir, agent)
    n1 = config.phase1_episodes
    p1_returns = list(agent.log.episode_returns[:n1])
    p1_frames = list(agent.log.episode_end_frames[:n1])
    p1_total = p1_frames[-1] if p1_frames else 0
    total = n1 + config.phase3_episodes
    partial_path = os.path.join(seed_dir, f"{cell.condition}.partial.pt")
    phase1_agent = agent
    if cell.condition == "A":
        # the baseline continues phase 1's DQN (networks, optimizer, epsilon, replay buffer) with actions only
        _load_if(agent, partial_path)
        _train_episodes(agent, total, partial_path, config)
        returns = list(agent.log.episode_returns[:total])
        frames = list(agent.log.episode_end_frames[:total])
        phase3 = {}
    elif cell.condition == "A0":
        # control: actions only from a reset Q-function, as H1 but without the options
        agent = _make_agent(game, config, seed + 1000, "actions")
        _load_if(agent, partial_path)
        _train_episodes(agent, config.phase3_episodes, partial_path, config, offset=n1)
        returns = p1_returns + list(agent.log.episode_returns[: config.phase3_episodes])
        frames = p1_frames + [p1_total + f for f in agent.log.episode_end_frames[: config.phase3_episodes]]
        phase3 = {}
    else:
        k = metadata["num_options"]
        flags = _option_flags(cell.condition)
        agent = _make_agent(game, config, seed + 1000, "both", options=options, num_options=k,
                            greedy_options=flags.greedy, intra_option_actions=flags.intra,
                            option_suffixes=flags.suffixes)
        copied = 0
        if flags.warm:
            # phase 1's networks (output layer widened) and replay buffer; a partial checkpoint then restores
            # the state reached since (its buffer too with checkpoint_buffer; otherwise the copied one stands in)
            agent.warm_start_from(phase1_agent)
            copied = len(agent.replay_buffer)
        _load_if(agent, partial_path)
        _train_episodes(agent, config.phase3_episodes, partial_path, config, offset=n1)
        offset = p1_total + int(metadata["demo_frames"])
        returns = p1_returns + list(agent.log.episode_returns[: config.phase3_episodes])
        frames = p1_frames + [offset + f for f in agent.log.episode_end_frames[: config.phase3_episodes]]
        num_actions = int(agent.env.full_action_spec_unbatched["action"].n) - k  # augmented space: A + K
        phase3 = {"num_options": k, **option_usage(agent, num_actions, start=copied)}
        if config.option_frames and seed == 0 and cell.condition == "H1":
            try:
                write_option_frames(phase1_agent, options, game, config, seed,
                                    os.path.join(out_dir, "option_frames", game))
            except Exception as err:  # frames are an illustration: never lose a finished cell to them
                logger.warning("option frames for %s failed: %s", game, err)
    for a in {id(agent): agent, id(phase1_agent): phase1_agent}.values():
        _close(a)  # a ParallelEnv's workers would keep the process alive
    if os.path.exists(partial_path):
        os.remove(partial_path)
    info = {"seconds": time.time() - t0, "phase1_frames": p1_total, "demo_frames": metadata.get("demo_frames"), **phase3}
    if config.eval_every:
        info["evaluations"] = _cell_evaluations(cell.condition, phase1_agent, agent, n1, config.eval_every)
    with open(os.path.join(seed_dir, f"{cell.condition}.json"), "w") as f:
        json.dump(info, f)
    return CellResult(returns=[float(r) for r in returns], frames=[int(f) for f in frames], info=info)


def _cell_evaluations(condition: str, phase1_agent, agent, n1: int, every: int) -> list[list[float]]:
    """The cell's greedy evaluations as ``[point, episodes, mean return]``: ``point`` is the multiple of ``every``
    that triggered it (comparable across conditions), ``episodes`` the cell's episode count then."""
    if condition == "A":  # one agent through both phases
        rows = [(e[0], e[2]) for e in agent.log.evaluations]
    else:
        rows = [(e[0], e[2]) for e in phase1_agent.log.evaluations if e[0] // every <= n1 // every]
        rows += [(n1 + e[0], e[2]) for e in agent.log.evaluations]
    return [[int(ep) // every * every, int(ep), float(mean)] for ep, mean in rows]


def agent_for_frames(game: str, config: AtariConfig, seed: int, seed_dir: str):
    """The phase-1 agent (whose greedy trajectories the options were discovered from)."""
    agent = _make_agent(game, config, seed, "actions")
    _load_if(agent, os.path.join(seed_dir, "phase1.pt"))
    return agent


def write_option_frames(agent, options, game: str, config: AtariConfig, seed: int, out_dir: str, *,
                        strip_frames: int = 6, fps: float = 15.0) -> list[str]:
    """Figure 4: for each option, a strip of frames and a short video of where it is the most likely one.

    Rolls out one greedy trajectory of the phase-1 agent with RGB rendering, labels every step with the
    posterior argmax option (forward-backward under the discovered options, uniform meta-control), and writes
    for each option its longest segment as ``option<h>.png`` (``strip_frames`` frames side by side) and
    ``option<h>.avi`` (OpenCV), plus ``labels.json`` with the per-step labels.
    """
    import cv2

    from torchrl_options.envs.render import write_video
    from torchrl_options.inference import forward_backward, most_likely_options
    from torchrl_options.objectives import DDOLoss

    os.makedirs(out_dir, exist_ok=True)
    trajs, screens = _greedy_rollouts(agent, game, config, seed, 1, config.option_frames_max_steps, render=True)
    traj, screens = trajs[0], screens[0]
    with torch.no_grad():
        p = DDOLoss(options).log_probabilities(traj.unsqueeze(0))
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
    labels = most_likely_options(fb.u)[0].tolist()
    written = []
    k = int(p["log_pi"].shape[-1])
    for h in range(k):
        best, start = (0, 0), None
        for t, lab in enumerate(labels + [-1]):
            if lab == h and start is None:
                start = t
            elif lab != h and start is not None:
                if t - start > best[1] - best[0]:
                    best = (start, t)
                start = None
        a, b = best
        if b <= a:
            continue
        segment = screens[a:b]
        picks = np.linspace(0, len(segment) - 1, num=min(strip_frames, len(segment))).round().astype(int)
        strip = np.concatenate([segment[i] for i in picks], axis=1)
        png = os.path.join(out_dir, f"option{h}.png")
        cv2.imwrite(png, cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
        write_video(segment, os.path.join(out_dir, f"option{h}.avi"), fps=fps)
        written += [png, os.path.join(out_dir, f"option{h}.avi")]
    with open(os.path.join(out_dir, "labels.json"), "w") as f:
        json.dump({"game": game, "labels": labels, "usage": [labels.count(h) for h in range(k)]}, f)
    return written


# ---------------------------------------------------------------------------------------------- summary
@dataclass
class AtariComparison:
    """A condition (``H1`` by default) against a baseline (``A`` by default) in one game, over seeds that finished
    both. (Fields are named for the paper's pair: ``options_*`` is ``condition``, ``baseline_*`` is ``baseline``.)

    ``*_episodes``: mean return over the phase-3 episodes (the paper's "learns faster": area under the curve);
    ``final_*``: mean over the last ``final_window`` episodes, both at equal episodes. ``*_frames``: mean return
    of the episodes ending within the first ``F`` frames after phase 1, ``F`` the smaller of the two conditions'
    phase-3 frame budgets in that seed (the demonstration frames count against conditions with options). Each is
    ``(mean, low, high)`` over seeds; ``diff_*`` is the paired difference ``condition - baseline``.
    """

    game: str
    num_seeds: int
    phase3_episodes: int
    baseline_episodes: tuple[float, float, float]
    options_episodes: tuple[float, float, float]
    diff_episodes: tuple[float, float, float]
    baseline_final: tuple[float, float, float]
    options_final: tuple[float, float, float]
    diff_final: tuple[float, float, float]
    baseline_frames: tuple[float, float, float]
    options_frames: tuple[float, float, float]
    diff_frames: tuple[float, float, float]
    equal_frames: float
    extra: dict = field(default_factory=dict)
    condition: str = "H1"
    baseline: str = "A"


def _ci_text(x: tuple[float, float, float]) -> str:
    """``(mean, low, high)`` as ``"mean [low, high]"``."""
    return f"{x[0]:.2f} [{x[1]:.2f}, {x[2]:.2f}]"


def _cell_infos(out_dir: str, pattern: str = "*") -> list[tuple[str, int, str, dict]]:
    """``(game, seed, condition, info)`` of the finished cells' json files
    ``<out_dir>/<game>/seed<s>/<pattern>.json``."""
    import glob

    infos = []
    for path in sorted(glob.glob(os.path.join(out_dir, "*", "seed*", f"{pattern}.json"))):
        parts = path.split(os.sep)
        with open(path) as f:
            infos.append((parts[-3], int(parts[-2][len("seed"):]), os.path.splitext(parts[-1])[0], json.load(f)))
    return infos


def _verdict_counts(diffs: Sequence[tuple[float, float, float]]) -> str:
    """``"ahead in a, behind in b, no evidence either way in c"`` for the paired differences ``diffs``."""
    verdicts = [interval_verdict(d) for d in diffs]
    return ", ".join(f"{v} in {verdicts.count(v)}" for v in ("ahead", "behind", "no evidence either way"))


def _seed_counts(counts: Sequence[int]) -> str:
    """``"3 seeds"`` or ``"2-8 seeds"``."""
    lo, hi = min(counts), max(counts)
    return f"{lo} seed{'s' if hi > 1 else ''}" if lo == hi else f"{lo}-{hi} seeds"


def atari_comparison(log: ResultsLog | Sequence[dict], *, phase1_episodes: int, final_window: int = 100,
                     confidence: float = 0.95, condition: str = "H1", baseline: str = "A") -> list[AtariComparison]:
    """Per game, ``condition`` against ``baseline`` at equal episodes and at equal frames: means over seeds with
    Student-t intervals (:func:`~torchrl_options.experiments.intervals.mean_interval`), and the differences paired by
    seed (:func:`~torchrl_options.experiments.intervals.paired_difference_interval`). The default is the paper's
    pair: options (``H1``) against actions only, continued (``A``).

    Examples:
        >>> rows = []
        >>> for seed in range(3):
        ...     for cond, gain in (("A", 0.0), ("H1", 1.0)):
        ...         for ep in range(6):  # 2 phase-1 episodes, 4 phase-3 episodes of 10 frames
        ...             r = 0.0 if ep < 2 else gain + seed
        ...             rows.append(dict(setting="Pong", condition=cond, seed=seed, episode=ep, frames=10 * (ep + 1),
        ...                              **{"return": r}))
        >>> [c] = atari_comparison(rows, phase1_episodes=2, final_window=2)
        >>> c.diff_episodes[0], c.diff_frames[0], c.num_seeds
        (1.0, 1.0, 3)
    """
    rows = log.rows() if isinstance(log, ResultsLog) else list(log)
    data: dict[str, dict[str, dict[int, list[tuple[float, int | None]]]]] = defaultdict(lambda: defaultdict(dict))
    for r in sorted(rows, key=lambda r: (r["setting"], r["condition"], r["seed"], r["episode"])):
        data[r["setting"]][r["condition"]].setdefault(r["seed"], []).append((r["return"], r.get("frames")))
    out = []
    for game, conds in data.items():
        if baseline not in conds or condition not in conds:
            continue
        seeds = sorted(set(conds[baseline]) & set(conds[condition]))
        if not seeds:
            continue
        per = defaultdict(list)
        budgets = []
        for s in seeds:
            a, h = conds[baseline][s][phase1_episodes:], conds[condition][s][phase1_episodes:]
            n = min(len(a), len(h))
            if n == 0:
                continue
            ra, rh = np.array([x[0] for x in a[:n]]), np.array([x[0] for x in h[:n]])
            w = min(final_window, n)
            per["A_ep"].append(ra.mean())
            per["H_ep"].append(rh.mean())
            per["A_fin"].append(ra[-w:].mean())
            per["H_fin"].append(rh[-w:].mean())
            start_a = conds[baseline][s][phase1_episodes - 1][1] if phase1_episodes else 0
            start_h = start_a or 0
            fa = np.array([x[1] for x in a[:n]], dtype=float) - (start_a or 0)
            fh = np.array([x[1] for x in h[:n]], dtype=float) - start_h
            budget = min(fa[-1], fh[-1])
            budgets.append(budget)
            # returns of the episodes finished within the common frame budget (at least the first one)
            per["A_fr"].append(ra[: max(int((fa <= budget).sum()), 1)].mean())
            per["H_fr"].append(rh[: max(int((fh <= budget).sum()), 1)].mean())
        if not per["A_ep"]:
            continue

        def ci(x):
            return mean_interval(x, confidence=confidence)

        d = lambda k1, k2: paired_difference_interval(per[k1], per[k2], confidence)  # noqa: E731
        out.append(
            AtariComparison(
                game=game,
                num_seeds=len(per["A_ep"]),
                phase3_episodes=min(len(conds[baseline][s]) for s in seeds) - phase1_episodes,
                baseline_episodes=ci(per["A_ep"]),
                options_episodes=ci(per["H_ep"]),
                diff_episodes=d("H_ep", "A_ep"),
                baseline_final=ci(per["A_fin"]),
                options_final=ci(per["H_fin"]),
                diff_final=d("H_fin", "A_fin"),
                baseline_frames=ci(per["A_fr"]),
                options_frames=ci(per["H_fr"]),
                diff_frames=d("H_fr", "A_fr"),
                equal_frames=float(np.mean(budgets)),
                condition=condition,
                baseline=baseline,
            )
        )
    return out


def atari_summary_markdown(comparisons: Sequence[AtariComparison], *, final_window: int = 100,
                           header: str | None = None) -> str:
    """The per-game table of :func:`atari_comparison` in Markdown, with a verdict per comparison and a count.

    ``comparisons`` should share one ``(condition, baseline)`` pair (one call per pair); the table names them. A
    verdict is "ahead" / "behind" when the 95% Student-t interval of the paired per-seed difference lies above /
    below 0, "no evidence either way" when it contains 0; the count line says how many seeds the verdicts rest on.
    """

    f = _ci_text
    c_name = comparisons[0].condition if comparisons else "H1"
    b_name = comparisons[0].baseline if comparisons else "A"
    lines = [header + "\n"] if header else []
    lines += [
        "Returns of phase 3 (after the shared phase 1), mean over seeds with 95% Student-t intervals over seeds. "
        f"`{c_name}`: {_describe(c_name)}; `{b_name}`: {_describe(b_name)}. Verdict of `{c_name}` against "
        f"`{b_name}`: \"ahead\" / \"behind\" when the 95% Student-t interval of the per-seed paired difference "
        f"{c_name} - {b_name} lies above / below 0, \"no evidence either way\" when it contains 0.\n",
        f"| game | seeds | phase-3 episodes | {b_name}, mean over episodes | {c_name}, mean over episodes | "
        f"{c_name} - {b_name} | verdict (equal episodes) | {b_name}, last {final_window} | {c_name}, last "
        f"{final_window} | {c_name} - {b_name} | equal frames (phase 3) | {b_name} at equal frames | {c_name} at "
        f"equal frames | {c_name} - {b_name} | verdict (equal frames) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ahead = 0
    for c in comparisons:
        ahead += c.diff_episodes[0] > 0
        lines.append(
            f"| {c.game} | {c.num_seeds} | {c.phase3_episodes} | {f(c.baseline_episodes)} | {f(c.options_episodes)} | "
            f"{f(c.diff_episodes)} | {interval_verdict(c.diff_episodes)} | {f(c.baseline_final)} | "
            f"{f(c.options_final)} | {f(c.diff_final)} | {c.equal_frames:.0f} | {f(c.baseline_frames)} | "
            f"{f(c.options_frames)} | {f(c.diff_frames)} | {interval_verdict(c.diff_frames)} |"
        )
    lines.append("")
    if comparisons:
        seeds = _seed_counts([c.num_seeds for c in comparisons])
        lines.append(
            f"`{c_name}` against `{b_name}` over {len(comparisons)} games, on {seeds} per game (Student-t intervals of "
            f"the paired per-seed differences): at equal episodes "
            f"{_verdict_counts([c.diff_episodes for c in comparisons])}; "
            f"at equal frames {_verdict_counts([c.diff_frames for c in comparisons])}. Mean difference above 0 at "
            f"equal episodes in {ahead} of {len(comparisons)} games."
        )
    return "\n".join(lines) + "\n"


def atari_summary_pairs(conditions: Iterable[str]) -> list[tuple[str, str]]:
    """The ``(condition, baseline)`` pairs to report for a sweep over ``conditions``, among those that ran.

    The paper's comparison (``H1`` vs ``A``) first; then every other options condition against ``A``; ``A0`` against
    ``A`` (what the reset costs); every options condition with a reset (no ``w``) against ``A0``; every options
    condition against ``H1``; and every condition ending in ``i`` or ``s`` after another letter against the same
    without that last letter.

    Examples:
        >>> atari_summary_pairs(["A", "H1", "A0"])
        [('H1', 'A'), ('A0', 'A'), ('H1', 'A0')]
        >>> atari_summary_pairs(["A", "H1", "H1w", "H1wi"])
        [('H1', 'A'), ('H1w', 'A'), ('H1wi', 'A'), ('H1w', 'H1'), ('H1wi', 'H1'), ('H1wi', 'H1w')]
    """
    have = [c for c in CONDITIONS if c in set(conditions)]
    options = [c for c in have if _option_flags(c) is not None]
    pairs = [("H1", "A")] + [(c, "A") for c in options if c != "H1"] + [("A0", "A")]
    pairs += [(c, "A0") for c in options if not _option_flags(c).warm]
    pairs += [(c, "H1") for c in options if c != "H1"]
    pairs += [(c, c[:-1]) for c in options if c[-1] in "is" and len(c) > 3]
    return [(c, b) for c, b in pairs if c in have and b in have]


def atari_scores(
    log: ResultsLog | Sequence[dict], *, phase1_episodes: int, conditions: Sequence[str] | None = None
) -> tuple[list[str], dict[str, np.ndarray]]:
    """Per condition, a score matrix ``[num_seeds, num_games]`` for :mod:`~torchrl_options.experiments.aggregates`:
    each run's mean training return over its phase-3 episodes (after ``phase1_episodes``).

    The games are those every condition ran (conditions that did not run at all are left out); a condition's seeds,
    those it finished in every one of these games. A condition with no such seed is left out.

    Returns:
        ``(games, {condition: scores})``.

    Examples:
        >>> rows = [dict(setting=g, condition=c, seed=s, episode=e, **{"return": float(e >= 2) * (s + (c == "H1"))})
        ...         for g in ("Pong", "Seaquest") for c in ("A", "H1") for s in range(3) for e in range(4)]
        >>> games, scores = atari_scores(rows, phase1_episodes=2)
        >>> games, scores["H1"].shape, scores["H1"][:, 0].tolist()
        (['Pong', 'Seaquest'], (3, 2), [1.0, 2.0, 3.0])
    """
    rows = log.rows() if isinstance(log, ResultsLog) else list(log)
    returns: dict[tuple[str, str, int], list[tuple[int, float]]] = defaultdict(list)
    for r in rows:
        returns[(r["setting"], r["condition"], r["seed"])].append((r["episode"], r["return"]))
    score = {}
    for key, eps in returns.items():
        phase3 = [ret for _, ret in sorted(eps)][phase1_episodes:]
        if phase3:
            score[key] = float(np.mean(phase3))
    ran = list(dict.fromkeys(c for _, c, _ in score))
    names = ran if conditions is None else [c for c in conditions if c in ran]
    games = sorted(set.intersection(*({g for g, c, _ in score if c == name} for name in names)) if names else set())
    out = {}
    for name in names:
        seeds = sorted(set.intersection(*({s for g2, c, s in score if g2 == g and c == name} for g in games))
                       if games else set())
        if seeds:
            out[name] = np.array([[score[(g, name, s)] for g in games] for s in seeds])
        else:
            logger.warning("aggregates: condition %r has no seed finished in every game of %s; left out", name, games)
    return games, out


def atari_aggregates(
    log: ResultsLog | Sequence[dict],
    *,
    phase1_episodes: int,
    pairs: Sequence[tuple[str, str]],
    confidence: float = 0.95,
    num_resamples: int = 2000,
    seed: int = 0,
):
    """The aggregates over games of Agarwal et al. (2021) for the conditions of ``pairs``: interquartile mean,
    probability of improvement per ``(condition, baseline)`` pair and performance profiles, with stratified
    bootstrap intervals (:func:`~torchrl_options.experiments.aggregates.aggregate_scores`), of each run's mean
    phase-3 training return (:func:`atari_scores`), min-max normalised per game. ``None`` when no game has them.

    Examples:
        >>> rows = [dict(setting=g, condition=c, seed=s, episode=e, **{"return": float(e >= 2) * (s + 3 * (c == "H1"))})
        ...         for g in ("Pong", "Seaquest") for c in ("A", "H1") for s in range(3) for e in range(4)]
        >>> agg = atari_aggregates(rows, phase1_episodes=2, pairs=[("H1", "A")], num_resamples=200)
        >>> agg.tasks, agg.verdict(("H1", "A")), agg.improvement[("H1", "A")][0]
        (['Pong', 'Seaquest'], 'ahead', 1.0)
    """
    from torchrl_options.experiments.aggregates import aggregate_scores

    names = list(dict.fromkeys(c for pair in pairs for c in pair))
    games, scores = atari_scores(log, phase1_episodes=phase1_episodes, conditions=names)
    pairs = [(c, b) for c, b in pairs if c in scores and b in scores]
    if not games or not pairs:
        return None
    return aggregate_scores(scores, pairs, tasks=games, confidence=confidence, num_resamples=num_resamples,
                            seed=seed)


def greedy_evaluation_markdown(out_dir: str, pairs: Sequence[tuple[str, str]], *, phase1_episodes: int) -> str:
    """Markdown tables comparing conditions on their greedy evaluations (``AtariConfig.eval_every``), read from
    the finished cells' json files under ``out_dir``: per game and pair ``(condition, baseline)``, the mean over
    the phase-3 evaluation points (after ``phase1_episodes``) of each seed, and the paired difference over the seeds
    that ran both, with 95% Student-t intervals over seeds and a verdict ("ahead", "behind", "no evidence either
    way"). Empty when no cell was evaluated.

    Examples:
        >>> import json, os, tempfile
        >>> out = tempfile.mkdtemp()
        >>> for cond, value in (("A", 1.0), ("H1", 3.0)):
        ...     os.makedirs(os.path.join(out, "Pooyan", "seed0"), exist_ok=True)
        ...     evals = [[10, 10, 0.0], [20, 21, value], [30, 30, value]]
        ...     with open(os.path.join(out, "Pooyan", "seed0", f"{cond}.json"), "w") as f:
        ...         json.dump({"evaluations": evals}, f)
        >>> print(greedy_evaluation_markdown(out, [("H1", "A")], phase1_episodes=10).splitlines()[-3])
        | Pooyan | 1 | 2 | 1.00 [-inf, inf] | 3.00 [-inf, inf] | 2.00 [-inf, inf] | no evidence either way |
    """
    evals: dict[tuple[str, str], dict[int, float]] = defaultdict(dict)  # (game, condition) -> seed -> mean
    points: dict[tuple[str, str], int] = {}
    for game, seed, condition, info in _cell_infos(out_dir):
        phase3 = [e[2] for e in info.get("evaluations", []) if e[0] > phase1_episodes]
        if phase3:
            evals[(game, condition)][seed] = float(np.mean(phase3))
            points[(game, condition)] = len(phase3)
    text = ""
    for condition, baseline in pairs:
        games = sorted({g for g, c in evals if c == condition} & {g for g, c in evals if c == baseline})
        if not games:
            continue
        text += (
            f"\n## Greedy evaluation: {condition} vs {baseline}\n\nMean return of the greedy policy (options run as in "
            f"training) on the same freshly seeded games, averaged over the evaluations of phase 3, then over seeds "
            f"(95% Student-t intervals over seeds; verdict from the paired per-seed difference).\n\n"
            f"| game | seeds | evaluations | {baseline} | {condition} | {condition} - {baseline} | verdict |\n"
            "|---|---|---|---|---|---|---|\n"
        )
        ahead, diffs, counts = 0, [], []
        for game in games:
            a, b = evals[(game, condition)], evals[(game, baseline)]
            seeds = sorted(set(a) & set(b))
            if not seeds:
                continue
            ci_b = mean_interval([b[s] for s in seeds])
            ci_a = mean_interval([a[s] for s in seeds])
            diff = paired_difference_interval([a[s] for s in seeds], [b[s] for s in seeds])
            ahead += diff[0] > 0
            diffs.append(diff)
            counts.append(len(seeds))
            text += (f"| {game} | {len(seeds)} | {points[(game, condition)]} | {_ci_text(ci_b)} | {_ci_text(ci_a)} | "
                     f"{_ci_text(diff)} | {interval_verdict(diff)} |\n")
        text += (f"\n`{condition}` against `{baseline}` in greedy evaluation over {len(diffs)} games, on "
                 f"{_seed_counts(counts)} per game (Student-t intervals of the paired per-seed differences): "
                 f"{_verdict_counts(diffs)}. Mean difference above 0 in {ahead} of {len(diffs)} games.\n")
    return text


def option_usage_markdown(out_dir: str) -> str:
    """A Markdown table of the option usage recorded by the finished options cells (``H1...``) under ``out_dir``
    (mean over seeds of :func:`option_usage`); empty when there is none.

    Examples:
        >>> import json, os, tempfile
        >>> out = tempfile.mkdtemp()
        >>> os.makedirs(os.path.join(out, "Pooyan", "seed0"))
        >>> info = {"option_decision_share": 0.5, "option_step_share": 0.8, "mean_option_steps": 4.0}
        >>> with open(os.path.join(out, "Pooyan", "seed0", "H1.json"), "w") as f:
        ...     json.dump(info, f)
        >>> print(option_usage_markdown(out).splitlines()[-1])
        | Pooyan | H1 | 1 | 0.50 | 0.80 | 4.0 |
    """
    usage: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for game, _, condition, info in _cell_infos(out_dir, "H1*"):
        if "option_decision_share" in info:
            usage[(game, condition)].append(info)
    if not usage:
        return ""
    keys = ("option_decision_share", "option_step_share", "mean_option_steps")
    lines = [
        "| game | condition | seeds | decisions that start an option | env steps inside options | steps per option |",
        "|---|---|---|---|---|---|",
    ]
    for (game, condition), infos in sorted(usage.items()):
        means = [float(np.nanmean([i[k] for i in infos])) if any(np.isfinite(i[k]) for i in infos) else float("nan")
                 for k in keys]
        lines.append(f"| {game} | {condition} | {len(infos)} | {means[0]:.2f} | {means[1]:.2f} | {means[2]:.1f} |")
    return "\n".join(lines) + "\n"
