"""The per-cell pipeline of the GridWorld recipes: trajectories, option discovery, DQN, returns per episode.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options" (2017): section 5.1 (four rooms,
supervised and exploration settings) and appendix B (two rooms, three rooms). A cell is a (setting, condition,
seed) triple (:class:`~torchrl_options.experiments.Cell`); :func:`run_gridworld_cell` turns one into its
per-episode returns:

- ``source: supervisor`` settings: demonstrations of the value-iteration supervisor, then DDO (one set of
  options per seed and discovery settings, cached), then DQN over the condition's action space.
- ``source: greedy`` settings (the exploration setting): DQN with actions only for ``pretrain_episodes``
  (once per seed, cached and shared by the conditions), trajectories of its greedy policy, DDO, then a *reset*
  DQN over the augmented action space. The baseline (``mode: actions``) is not reset: it continues the
  pre-trained agent, as in the paper.

Everything slow is checkpointed under ``<out_dir>/cells``: discovered options (:func:`save_options`), the
pre-trained agent and its greedy trajectories, and every DQN every ``checkpoint_every`` episodes (networks,
target, optimizer, epsilon, replay buffer and the returns so far), so a killed recipe resumes mid-cell.

The configuration is a plain dict: the recipes' settings checked by
:func:`~torchrl_options.experiments.gridworld_config.gridworld_settings` (their schema); see
``recipes/config/four_rooms.yaml`` for every key and the reasons behind the defaults.
"""
from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.utils import step_mdp

from torchrl_options.agents.dqn import OptionsDQN, OptionsDQNConfig
from torchrl_options.checks import check_number
from torchrl_options.checkpoints import (
    atomic_replace,
    load_file,
    save_file,
    scoped_seed,
    tensordict_from_plain,
    tensordict_to_plain,
)
from torchrl_options.discovery import discover_options, load_options, PAPER_SETTINGS, save_options
from torchrl_options.envs import GridWorldEnv, generate_demonstrations
from torchrl_options.experiments.gridworld_config import AGENT_SECTIONS, apply_protocol
from torchrl_options.experiments.gridworld_config import discovery_iterations as _discovery_iterations
from torchrl_options.experiments.gridworld_config import discovery_kwargs as _discovery_kwargs
from torchrl_options.experiments.gridworld_config import env_kwargs as _env_kwargs
from torchrl_options.experiments.recipe_config import plain_settings
from torchrl_options.experiments.sweep import Cell, CellResult
from torchrl_options.hierarchy import discover_hierarchy, load_hierarchy, OptionHierarchy, save_hierarchy

__all__ = [
    "make_env",
    "greedy_trajectories",
    "discover_cached",
    "train_episodes",
    "run_gridworld_cell",
    "cell_dir",
    "reach_table",
    "apply_protocol",
    "write_option_pictures",
    "write_summary",
]

logger = logging.getLogger(__name__)
#: what a resumed run skips and where it resumes: kept on the console when the recipes quiet the rest
resume_logger = logging.getLogger("torchrl_options.resume")


def make_env(env_cfg: Mapping[str, Any], num_envs: int, seed: int) -> GridWorldEnv:
    """A natively batched :class:`GridWorldEnv` of ``num_envs`` grids from an ``env`` config section.

    Examples:
        >>> env = make_env({"grid": "two-rooms", "task": "goal", "max_steps": 20, "start": None}, 4, seed=0)
        >>> env.batch_size, env.max_steps
        (torch.Size([4]), 20)
    """
    return GridWorldEnv(**_env_kwargs(env_cfg), batch_size=[num_envs], seed=seed)


def cell_dir(out_dir: str | os.PathLike, *parts: str) -> Path:
    """``<out_dir>/cells/<parts...>``, created."""
    path = Path(out_dir, "cells", *parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


# ------------------------------------------------------------------------------------------------ trajectories
@torch.no_grad()
def greedy_trajectories(
    policy: Callable, env_cfg: Mapping[str, Any], num: int, length: int, seed: int, *, epsilon: float = 0.0
) -> TensorDict:
    """``num`` trajectories of ``policy`` (run greedily), one episode per row, padded with a mask.

    Rows stop at their first episode end (or after ``length`` steps; the batch stops once every row has ended);
    ``("collector", "mask")`` marks the valid steps, as in :func:`~torchrl_options.envs.generate_demonstrations`.
    With ``epsilon > 0`` the policy's action is replaced, with that probability at each step, by a uniformly random
    one (drawn from a generator seeded by ``seed``); the recorded ``"action"`` is the one taken. The paper's
    exploration setting uses ``epsilon=0`` (greedy trajectories).

    Examples:
        >>> from torchrl_options.envs import ValueIterationSupervisor
        >>> env_cfg = {"grid": "two-rooms", "task": "goal"}
        >>> policy = ValueIterationSupervisor(make_env(env_cfg, 1, 0), seed=0)
        >>> data = greedy_trajectories(policy, env_cfg, num=3, length=60, seed=0)
        >>> data.shape[0], data.shape[1] <= 60, bool(data["collector", "mask"][:, 0].all())
        (3, True, True)
    """
    check_number(epsilon, "epsilon", lo=0.0, hi=1.0)
    env = make_env({**dict(env_cfg), "max_steps": length}, num, seed)
    num_actions = int(env.full_action_spec_unbatched["action"].n)
    generator = torch.Generator().manual_seed(seed)
    steps, finished = [], torch.zeros(num, dtype=torch.bool)
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(length):
            td = policy(td)
            if epsilon > 0:
                explore = torch.rand(num, generator=generator) < epsilon
                random_action = torch.randint(num_actions, (num,), generator=generator)
                action = td.get("action")
                td.set("action", torch.where(explore.reshape(action.shape), random_action.reshape(action.shape), action))
            td = env.step(td)
            steps.append(td.exclude("action_value", "chosen_action_value"))
            finished |= td.get(("next", "done")).reshape(num)
            if finished.all():
                break
            td = step_mdp(td, keep_other=False, exclude_action=True)
    data = torch.stack(steps, dim=1)
    done = data.get(("next", "done")).reshape(num, -1).long()
    valid = (done.cumsum(-1) - done) == 0
    data.set(("collector", "mask"), valid)
    return data


def _trajectories(cfg: Mapping[str, Any], seed: int) -> TensorDict:
    """Demonstrations of the value-iteration supervisor, per the ``demos`` section."""
    demos = cfg["demos"]
    env_kwargs = _env_kwargs({**dict(cfg["env"]), **dict(demos.get("env") or {})})
    env_kwargs.pop("max_steps", None)
    grid = env_kwargs.pop("grid")
    return generate_demonstrations(
        grid, num_trajectories=demos["num"], length=demos["length"], seed=1000 * seed + 17, **env_kwargs
    )


# ------------------------------------------------------------------------------------------------ discovery
def discover_cached(
    trajectories: TensorDict | Callable[[], TensorDict],
    path: str | os.PathLike,
    *,
    num_options: int,
    meta_control: str,
    seed: int,
    discovery: Mapping[str, Any],
    progress: bool = False,
    desc: str = "DDO",
):
    """DDO options, loaded from ``path`` when it exists, else discovered and saved there.

    ``trajectories`` may be a callable, so that a resumed run does not even regenerate them. ``desc`` labels the
    progress bar (which run the discovery fits).
    """
    path = Path(path)
    if path.exists():
        logger.info("options: loading %s", path)
        return load_options(path)
    data = trajectories() if callable(trajectories) else trajectories
    result = discover_options(
        data, num_options, meta_control=meta_control, num_iterations=_discovery_iterations(discovery), seed=seed,
        progress=progress, return_info=True, desc=desc, usage_floor=discovery.get("usage_floor"),
        **_discovery_kwargs(discovery),
    )  # fmt: skip
    final = result.history[-1] if result.history else {}
    with atomic_replace(path) as tmp:
        save_options(
            result.options, tmp, meta_control=result.meta_control,
            metadata={"num_options": num_options, "meta_control": meta_control, "seed": seed, "final": final},
        )  # fmt: skip
    return result.options


def discover_hierarchy_cached(
    trajectories: TensorDict | Callable[[], TensorDict],
    path: str | os.PathLike,
    *,
    num_options: list[int],
    meta_control: str,
    seed: int,
    discovery: Mapping[str, Any],
    progress: bool = False,
    desc: str = "DDO",
) -> OptionHierarchy:
    """A multi-level hierarchy (H2u / H2s), loaded from ``path`` when it exists, else discovered and saved
    (``desc`` labels the progress bars)."""
    path = Path(path)
    if path.exists():
        logger.info("hierarchy: loading %s", path)
        return load_hierarchy(path)
    if discovery.get("usage_floor") is not None:
        raise ValueError(
            f"discovery.usage_floor applies to one-level discovery, got {discovery['usage_floor']} for levels {num_options}."
        )
    data = trajectories() if callable(trajectories) else trajectories
    lower = _discovery_iterations(discovery)
    upper = lower if discovery.get("upper_level_iterations") is None else int(discovery["upper_level_iterations"])
    hierarchy = discover_hierarchy(
        data, num_options, meta_control=meta_control, num_iterations=[lower]
        + [upper] * (len(num_options) - 1), seed=seed, progress=progress, desc=desc, **_discovery_kwargs(discovery),
    )  # fmt: skip
    with atomic_replace(path) as tmp:
        save_hierarchy(hierarchy, tmp, metadata={"num_options": num_options, "meta_control": meta_control, "seed": seed})
    return hierarchy


# ---------------------------------------------------------------------------------------------------- DQN
def _dqn_config(cfg: Mapping[str, Any], mode: str, seed: int) -> OptionsDQNConfig:
    dqn = dict(cfg["dqn"])
    dqn["hidden_sizes"] = tuple(dqn.get("hidden_sizes", (2,)))
    # dqn.max_decisions limits episodes in decisions (an option run to termination is one); env.max_steps then
    # only caps primitive steps, and a cap at or below the decision limit would cut option episodes short
    max_decisions, max_steps = dqn.get("max_decisions"), dict(cfg["env"]).get("max_steps")
    if max_decisions is not None and mode != "actions" and max_steps is not None and max_steps <= max_decisions:
        logger.warning(
            "dqn.max_decisions=%s with env.max_steps=%s: the step cap ends episodes before options can use the "
            "decision limit; raise env.max_steps (e.g. 10x).", max_decisions, max_steps,
        )  # fmt: skip
    # one natively batched env: OptionsDQN's num_envs=1 calls the factory once and does not wrap it
    return OptionsDQNConfig(mode=mode, num_envs=1, seed=seed, **dqn)


def _ppo_config(cfg: Mapping[str, Any], mode: str, seed: int):
    from torchrl_options.agents.ppo import OptionsPPOConfig

    ppo = dict(cfg["ppo"])
    if "hidden_sizes" in ppo:
        ppo["hidden_sizes"] = tuple(ppo["hidden_sizes"])
    return OptionsPPOConfig(mode=mode, num_envs=1, seed=seed, **ppo)


def make_agent(
    cfg: Mapping[str, Any], mode: str, seed: int, options=None, num_options: int | None = None
) -> OptionsDQN:
    """An :class:`OptionsDQN` on ``cfg["num_envs"]`` batched grids (a ``GridWorldEnv(batch_size=[N])``), or an
    :class:`~torchrl_options.agents.OptionsPPO` (settings from the ``ppo`` section) with ``cfg["algorithm"] == "ppo"``.

    ``options`` may be an :class:`~torchrl_options.OptionHierarchy`: its lower levels then run in nested
    executors inside the env and the DQN chooses among primitives and the options of every level. Keys of ``cfg``
    not set take their defaults (:func:`~torchrl_options.experiments.recipe_config.plain_settings`).
    """
    cfg = plain_settings(cfg, keep_none=AGENT_SECTIONS)
    env_cfg, num_envs = dict(cfg["env"]), int(cfg["num_envs"])
    env_seed = 1000 * seed + 101
    inner = []
    if isinstance(options, OptionHierarchy):
        inner = options.executors()[:-1]
        options, num_options = options.options(options.num_levels), options.num_options[-1]

    def factory():
        env = make_env(env_cfg, num_envs, env_seed)
        for executor in inner:
            env = env.append_transform(executor.clone())
        return env

    torch.manual_seed(seed)  # the recipe seeds the global generator (network init, exploration); the agent does not
    if cfg.get("algorithm", "dqn") == "ppo":
        from torchrl_options.agents.ppo import OptionsPPO

        return OptionsPPO(factory, _ppo_config(cfg, mode, seed), options=options, num_options=num_options)
    return OptionsDQN(factory, _dqn_config(cfg, mode, seed), options=options, num_options=num_options)


def train_episodes(
    agent: OptionsDQN,
    num_episodes: int,
    checkpoint: str | os.PathLike | None = None,
    *,
    checkpoint_every: int = 100,
    include_buffer: bool = True,
    final_buffer: bool = False,
    progress: bool = False,
    desc: str = "DQN",
    on_episodes: Callable[[list[float], int], None] | None = None,
) -> tuple[list[float], list[int]]:
    """Trains ``agent`` until ``num_episodes`` episodes (counted over the batched envs) have finished.

    Resumes from ``checkpoint`` when it exists and saves it every ``checkpoint_every`` episodes (and at the
    end). ``on_episodes(new_returns, first_index)`` is called with each chunk's new returns (for loggers).

    A checkpoint of an unfinished run holds the replay buffer (``include_buffer``: what a bit-for-bit resume
    needs); the final one only with ``final_buffer`` (an agent that trains on from it, e.g. the pre-trained agent
    that the exploration setting's baseline continues): a finished cell needs its log, not its buffer (most of
    a checkpoint's size).

    Returns:
        The first ``num_episodes`` returns and the frames at which each ended.
    """
    checkpoint = None if checkpoint is None else Path(checkpoint)
    if checkpoint is not None and checkpoint.exists():
        agent.load_state_dict(load_file(checkpoint, what="DQN checkpoint", map_location=agent.device))
        resume_logger.info("%s: resuming from %s at episode %d of %d", desc, checkpoint, len(agent.log.episode_returns), num_episodes)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=num_episodes, desc=desc, unit="ep", leave=False)
        bar.update(min(len(agent.log.episode_returns), num_episodes))
    reported = len(agent.log.episode_returns)
    while len(agent.log.episode_returns) < num_episodes:
        target = min(len(agent.log.episode_returns) + checkpoint_every, num_episodes)

        def stop(agent_: OptionsDQN, _batch) -> bool:
            if bar is not None:
                bar.update(min(len(agent_.log.episode_returns), num_episodes) - bar.n)
                recent = agent_.log.episode_returns[-50:]
                if recent:
                    bar.set_postfix(ret=f"{sum(recent) / len(recent):.2f}")
            return len(agent_.log.episode_returns) >= target

        # the budget is only a bound: the callback stops at the target number of episodes
        agent.train(total_frames=10**12, callback=stop)
        if checkpoint is not None:
            finished = len(agent.log.episode_returns) >= num_episodes
            save_file(agent.state_dict(include_buffer=final_buffer if finished else include_buffer), checkpoint)
        if on_episodes is not None:
            on_episodes(agent.log.episode_returns[reported:num_episodes], reported)
        reported = min(len(agent.log.episode_returns), num_episodes)
    if bar is not None:
        bar.close()
    return agent.log.episode_returns[:num_episodes], agent.log.episode_end_frames[:num_episodes]


# ---------------------------------------------------------------------------------------------- the cell
def _cell_logger(cfg: Mapping[str, Any], cell: Cell):
    log_cfg = dict(cfg.get("logger") or {})
    backend = log_cfg.get("backend", "csv")
    if not backend:
        return None
    from torchrl.record.loggers import get_logger

    name = f"{log_cfg.get('exp_name', 'gridworld')}-{cell.name}"
    kwargs = {}
    if backend == "wandb":
        kwargs = {"project": log_cfg.get("project_name", "torchrl-options"), "offline": log_cfg.get("offline", True)}
    return get_logger(backend, logger_name=str(Path(cfg["out_dir"], "logs")), experiment_name=name, **kwargs)


def _pretrained_agent(cfg: Mapping[str, Any], setting: str, seed: int, progress: bool) -> tuple[OptionsDQN, Path]:
    """The actions-only agent after ``pretrain_episodes`` (shared by the conditions of a seed)."""
    path = cell_dir(cfg["out_dir"], f"{setting}-seed{seed}") / "pretrain.pt"
    agent = make_agent(cfg, "actions", seed)
    train_episodes(
        agent, int(cfg["settings"][setting]["pretrain_episodes"]), path, checkpoint_every=int(cfg["checkpoint_every"]),
        final_buffer=True, progress=progress, desc=f"{setting}: actions-only pre-training, seed {seed}",
    )  # fmt: skip
    return agent, path


def _agent_rollouts(agent: OptionsDQN, cfg: Mapping[str, Any], rollouts: Mapping[str, Any], seed: int) -> TensorDict:
    """The pre-trained agent's rollouts that DDO learns from, per a greedy setting's ``greedy`` section: ``num``
    rollouts of ``length`` steps, with ``epsilon`` (``"agent"``: the agent's own final exploration rate; the paper:
    0, greedy) and ``keep`` (``"all"``, the paper's; ``"rewarded"``: only the pieces that end in a reward,
    :func:`~torchrl_options.data.rewarded_segments`)."""
    from torchrl_options.data import rewarded_segments

    epsilon = rollouts.get("epsilon", 0.0)
    if epsilon == "agent":
        epsilon = float(agent.config.eps_end)
    data = greedy_trajectories(agent.actor, cfg["env"], rollouts["num"], rollouts["length"], 1000 * seed + 7,
                               epsilon=float(epsilon))  # fmt: skip
    if rollouts.get("keep", "all") == "rewarded":
        reward = data.get(("next", "reward")).reshape(data.shape)
        if not bool((reward[data.get(("collector", "mask"))] > 0).any()):
            logger.warning(
                "seed %d: none of the agent's %d rollouts is rewarded; DDO learns from all of them (keep: all).",
                seed, data.shape[0],
            )  # fmt: skip
            return data
        data = rewarded_segments(data)
    return data


def cell_options(cfg: Mapping[str, Any], cell: Cell, *, progress: bool = False):
    """The options of a cell's condition (``None`` for actions only), discovered or loaded from the cache (keys of
    ``cfg`` not set take their defaults)."""
    cfg = plain_settings(cfg, keep_none=AGENT_SECTIONS)
    condition = cfg["conditions"][cell.condition]
    if condition["mode"] == "actions":
        return None
    setting = cfg["settings"][cell.setting]
    discovery = dict(cfg["discovery"])
    num_options = int(condition.get("num_options", discovery["num_options"]))
    meta = condition.get("meta_control", "uniform")
    name = f"options-K{num_options}-{meta}.pt"
    path = cell_dir(cfg["out_dir"], f"{cell.setting}-seed{cell.seed}") / name
    if setting["source"] == "supervisor":
        source = lambda: _trajectories(cfg, cell.seed)  # noqa: E731
    elif setting["source"] == "greedy":

        def source() -> TensorDict:
            traj_path = path.with_name("greedy_trajectories.pt")
            if traj_path.exists():
                return tensordict_from_plain(load_file(traj_path, what="trajectories file"), str(traj_path))
            agent, _ = _pretrained_agent(cfg, cell.setting, cell.seed, progress)
            data = _agent_rollouts(agent, cfg, dict(setting["greedy"]), cell.seed)
            save_file(tensordict_to_plain(data), traj_path)
            return data

    else:
        raise ValueError(f"setting source must be 'supervisor' or 'greedy', got {setting['source']!r}.")
    levels = int(condition.get("levels", 1))
    desc = f"DDO {cell.setting} seed {cell.seed}: {num_options} options, {meta} meta-control"
    if levels > 1:
        return discover_hierarchy_cached(
            source, path.with_name(f"hierarchy-K{num_options}x{levels}-{meta}.pt"), num_options=[num_options] * levels,
            meta_control=meta, seed=cell.seed, discovery=discovery, progress=progress, desc=desc,
        )  # fmt: skip
    return discover_cached(
        source, path, num_options=num_options, meta_control=meta, seed=cell.seed, discovery=discovery,
        progress=progress, desc=desc,
    )  # fmt: skip


def run_gridworld_cell(cell: Cell, cfg: Mapping[str, Any]) -> CellResult:
    """Runs one (setting, condition, seed) cell and returns its per-episode returns (resumable).

    ``cfg`` keys: ``out_dir``, ``env`` (GridWorldEnv arguments), ``num_envs``, ``demos`` (``num``, ``length``,
    ``env`` overrides), ``discovery`` (DDO settings), ``algorithm`` (``dqn``, the default, or ``ppo`` with a ``ppo``
    section of :class:`~torchrl_options.agents.OptionsPPOConfig` fields), ``dqn`` (:class:`OptionsDQNConfig` fields; ``max_decisions``
    limits episodes in decisions, with ``env.max_steps`` as a larger cap on primitive steps), ``episodes``,
    ``checkpoint_every``, ``settings`` (per setting: ``source`` and, for ``greedy``, ``pretrain_episodes`` and
    ``greedy: {num, length}``), ``conditions`` (per condition: ``mode``, ``meta_control``, optional ``levels``
    and an optional ``episodes`` that overrides the global one), ``logger`` and ``progress``. Keys not set take
    their defaults (a composed config holds every key of the recipes' schema: ``None``, or ``???`` in the agent's
    section, where ``None`` is a value).
    """
    with scoped_seed(cell.seed):  # the cell's random numbers come from its seed; the caller's are left as they were
        return _run_cell(cell, plain_settings(cfg, keep_none=AGENT_SECTIONS))  # a key at None (the schema's "not set") takes its default


def _run_cell(cell: Cell, cfg: dict[str, Any]) -> CellResult:
    progress = bool(cfg.get("progress", False))
    setting = cfg["settings"][cell.setting]
    condition = cfg["conditions"][cell.condition]
    mode = condition["mode"]
    ckpt = cell_dir(cfg["out_dir"], cell.name) / ("ppo.pt" if cfg.get("algorithm", "dqn") == "ppo" else "dqn.pt")
    options = cell_options(cfg, cell, progress=progress)
    if mode == "actions" and setting["source"] == "greedy":
        # the baseline is not reset: it continues the pre-trained agent
        agent, pre_path = _pretrained_agent(cfg, cell.setting, cell.seed, progress)
        if not ckpt.exists():
            agent.log.episode_returns.clear()
            agent.log.episode_lengths.clear()
            agent.log.episode_end_frames.clear()
    else:
        num_options = None if options is None or isinstance(options, OptionHierarchy) else int(options.num_options)
        agent = make_agent(cfg, mode, cell.seed, options=options, num_options=num_options)
    exp_logger = _cell_logger(cfg, cell)

    def log_returns(returns: list[float], first: int) -> None:
        if exp_logger is not None:
            for i, r in enumerate(returns):
                exp_logger.log_scalar("episode_return", float(r), step=first + i)

    # a condition may run longer than the others (e.g. actions only for 5000 episodes, options for 1000)
    num_episodes = int(condition.get("episodes") or cfg["episodes"])
    returns, frames = train_episodes(
        agent, num_episodes, ckpt, checkpoint_every=int(cfg["checkpoint_every"]), progress=progress,
        desc=f"DQN {cell.name}", on_episodes=log_returns,
    )  # fmt: skip
    with open(Path(cfg["out_dir"], "cells", "ran.txt"), "a") as f:
        f.write(cell.name + "\n")
    return CellResult(returns=[float(r) for r in returns], frames=[int(f) for f in frames])


# --------------------------------------------------------------------------------------------- the recipe
def reach_table(log, target: float, window: int, *, condition_order: Sequence[str] | None = None) -> str:
    """Markdown: per setting and condition, the episodes each seed needs for its ``window``-episode mean
    return to reach ``target`` (e.g. the two-rooms convergence of appendix B: a return of 1.0), with a 95%
    Student-t interval over seeds (cut to the counts possible); seeds that never reach it count with all their
    episodes."""
    from torchrl_options.experiments.intervals import mean_interval
    from torchrl_options.experiments.results import _count, condition_rank, episodes_to_reach, within

    lines = [
        f"| setting | condition | episodes to a {window}-episode mean return of {target:g} [95% t-interval] | "
        "seeds that reach it |",
        "|---|---|---|---|",
    ]
    rank = condition_rank(condition_order)
    for setting, condition in sorted(log.settings_and_conditions(), key=lambda k: (k[0], rank(k[1]))):
        counts, reached = [], 0
        runs = log.returns(setting, condition)
        for returns in runs.values():
            n = episodes_to_reach(returns, target, window)
            reached += n is not None
            counts.append(len(returns) if n is None else n)
        lengths = [len(r) for r in runs.values()]
        m, lo, hi = within(mean_interval(counts), min(window, *lengths), max(lengths))
        lines.append(f"| {setting} | {condition} | {_count(m)} [{_count(lo)}, {_count(hi)}] | {reached}/{len(runs)} |")
    return "\n".join(lines) + "\n"


def write_summary(
    log: ResultsLog | str | os.PathLike,
    out_dir: str | os.PathLike,
    title: str,
    summary_cfg: Mapping[str, Any] | None = None,
    *,
    condition_order: Sequence[str] | None = None,
) -> str:
    """Writes ``summary.md`` and ``curves.png`` for a ``results.csv`` to ``out_dir``; returns the summary: per
    condition, final returns and episodes to the baseline's with 95% Student-t intervals over seeds, and every
    condition against ``A`` paired by seed, with its verdict (``compare_to_baseline``).

    ``summary_cfg`` holds the recipes' ``summary`` keys: ``final_window`` (100), ``smooth_window`` (100),
    ``curve_window`` (50), and ``reach_return`` / ``reach_window`` for an extra table of the episodes to a return.
    Rows (and the curves' legends) come per setting in ``condition_order`` (the recipe's order of its
    ``conditions``, e.g. ``A, H1u, H1s``), other conditions after, alphabetically.

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options.experiments import ResultsLog
        >>> d = tempfile.mkdtemp()
        >>> log = ResultsLog(os.path.join(d, "results.csv"))
        >>> for seed in (0, 1):
        ...     log.append_cell("supervised", "A", seed, returns=[0.0, 1.0, 1.0, 1.0])
        >>> print(write_summary(log, d, "Demo", {"final_window": 2, "smooth_window": 2}).splitlines()[4])
        | supervised | A | 2 | 4 | 1.000 [1.000, 1.000] | 3 [3, 3] | 2/2 |
        >>> log.append_cell("supervised", "H1u", 0, returns=[1.0, 1.0, 1.5, 1.5])
        >>> print(write_summary(log, d, "Demo", {"final_window": 2, "smooth_window": 2}).splitlines()[-1])
        | supervised | H1u - A | +0.500 [-inf, +inf] | no evidence either way | 1 |
        >>> sorted(os.listdir(d))
        ['curves.png', 'results.csv', 'summary.md']
    """
    from torchrl_options.experiments.plotting import plot_curves
    from torchrl_options.experiments.results import (
        compare_to_baseline,
        comparison_markdown,
        ResultsLog,
        summarize,
        summary_markdown,
    )

    log = log if isinstance(log, ResultsLog) else ResultsLog(log)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary_cfg = dict(summary_cfg or {})
    final_window = int(summary_cfg.get("final_window", 100))
    summaries = summarize(log, final_window=final_window, smooth_window=int(summary_cfg.get("smooth_window", 100)),
                          condition_order=condition_order)  # fmt: skip
    text = f"# {title}\n\n" + summary_markdown(summaries, final_window=final_window)
    comparisons = comparison_markdown(
        compare_to_baseline(log, final_window=final_window, condition_order=condition_order), final_window=final_window
    )
    if comparisons:
        text += "\n" + comparisons
    if summary_cfg.get("reach_return") is not None:
        text += "\n" + reach_table(log, float(summary_cfg["reach_return"]), int(summary_cfg.get("reach_window", 10)),
                                    condition_order=condition_order)
    (out / "summary.md").write_text(text)
    plot_curves(log, out / "curves.png", smooth_window=int(summary_cfg.get("curve_window", 50)), title=title,
                condition_order=condition_order)
    return text


def write_option_pictures(cfg: Mapping[str, Any], seed: int) -> list[Path]:
    """``pictures/<setting>-seed<seed>-K<k>-<meta>.png`` for every option file of ``seed`` (figures 1 and 6, with
    titles, axes, legend, colour bar and caption) and, unless ``pictures.video`` is false, its video ``.avi`` (each
    option run from a few starts, :func:`~torchrl_options.experiments.option_pictures.option_video`); and
    ``pictures/<setting>-seed<seed>-hierarchy-....png`` for every hierarchy (figure 1: level-2 options coloured by
    the level-1 option running)."""
    from torchrl_options.experiments.option_pictures import draw_hierarchy, draw_options, option_video

    pictures_cfg = dict(cfg.get("pictures") or {})
    out = Path(cfg["out_dir"], "pictures")
    out.mkdir(parents=True, exist_ok=True)
    num_starts, max_length = int(pictures_cfg.get("num_starts", 3)), int(pictures_cfg.get("max_length", 30))
    written = []
    for setting in cfg["settings_to_run"]:
        folder = Path(cfg["out_dir"], "cells", f"{setting}-seed{seed}")
        for path in sorted(folder.glob("options-*.pt")):
            stem = f"{setting}-seed{seed}-{path.stem.removeprefix('options-')}"
            options = load_options(path)
            target = Path(out, f"{stem}.png")
            draw_options(
                options, cfg["env"], target, target_pos=pictures_cfg.get("target"), num_starts=num_starts,
                max_length=max_length, seed=seed, title=f"Options discovered by DDO: {setting} setting, seed {seed}, "
                f"{path.name} ({cfg['env'].get('grid', 'GridWorld')})",
            )  # fmt: skip
            written.append(target)
            if pictures_cfg.get("video", True):
                video = Path(out, f"{stem}.avi")
                option_video(
                    options, cfg["env"], video, target_pos=pictures_cfg.get("target"), num_starts=num_starts,
                    max_length=max_length, seed=seed,
                )  # fmt: skip
                written.append(video)
        for path in sorted(folder.glob("hierarchy-*.pt")):
            target = Path(out, f"{setting}-seed{seed}-{path.stem}.png")
            draw_hierarchy(
                load_hierarchy(path), cfg["env"], target, num_starts=num_starts, max_length=2 * max_length, seed=seed,
                title=f"Option hierarchy discovered by DDO: {setting} setting, seed {seed}, {path.name}",
            )  # fmt: skip
            written.append(target)
    return written
