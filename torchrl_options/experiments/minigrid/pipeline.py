"""The MiniGrid recipe's resumable stages: segmentation cells (bot demonstrations, DDO, scores) and RL cells (PPO or
DQN over actions, or actions + options from the same level or from an easier one), with the options of a
(level, seed) discovered once and cached. See :class:`~torchrl_options.experiments.minigrid.MiniGridConfig`."""
from __future__ import annotations

import json
import logging
import os
import time
from functools import partial

import torch
from filelock import FileLock

from torchrl_options.checkpoints import load_file, save_file, scoped_seed
from torchrl_options.experiments.minigrid.config import MiniGridConfig
from torchrl_options.experiments.sweep import Cell, CellResult

__all__ = [
    "episode_cut_warning",
    "load_minigrid_options",
    "minigrid_cells",
    "level_options",
    "run_minigrid_cell",
    "save_minigrid_options",
    "segmentation_method",
]

logger = logging.getLogger(__name__)

_FORMAT = "torchrl_options.minigrid-options/1"


def segmentation_method(config: MiniGridConfig) -> dict:
    """The discovery settings of the recipe's cells (see :mod:`~torchrl_options.experiments.minigrid.segmentation`):
    the options run in the env, so they have MiniGrid's 7 actions even if the bot never takes ``done``.

    Examples:
        >>> segmentation_method(MiniGridConfig(num_options=4, ddo_iterations=50))
        {'network': 'mlp', 'num_options': 4, 'num_iterations': 50, 'num_actions': 7}
    """
    from torchrl_options.envs.minigrid import MINIGRID_ACTIONS

    method = {"network": config.network, "num_options": config.num_options, "num_iterations": config.ddo_iterations}
    if config.network == "mlp":  # a module built for the network has the 7 actions already
        method["num_actions"] = len(MINIGRID_ACTIONS)
    return method


def save_minigrid_options(options: torch.nn.Module, path: str, metadata: dict | None = None) -> None:
    """Writes an :class:`~torchrl_options.OptionsMLP` or :class:`~torchrl_options.modules.GridConvOptions` (class,
    configuration, weights) as plain data (``save_options`` does not know the conv module yet)."""
    payload = {"format": _FORMAT, "class": type(options).__name__, "config": dict(options.config),
               "state_dict": {k: v.detach().cpu() for k, v in options.state_dict().items()},
               "metadata": dict(metadata or {})}  # fmt: skip
    save_file(payload, path)


def load_minigrid_options(path: str) -> tuple[torch.nn.Module, dict]:
    """Reads what :func:`save_minigrid_options` wrote (without running code from the file): ``(options, metadata)``."""
    from torchrl_options.modules import GridConvOptions, OptionsMLP

    payload = load_file(path, what="MiniGrid options")
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(f"{path}: not a MiniGrid options file (format {_FORMAT!r}).")
    config = dict(payload["config"])
    for key in ("in_keys", "out_keys"):
        config[key] = [tuple(k) if isinstance(k, list) else k for k in config[key]]
    if payload["class"] == "OptionsMLP":
        module = OptionsMLP(config.pop("in_features"), config.pop("num_actions"), config.pop("num_options"), **config)
    elif payload["class"] == "GridConvOptions":
        module = GridConvOptions(config.pop("num_actions"), config.pop("num_options"), **config)
    else:
        raise ValueError(f"{path}: unknown options class {payload['class']!r}.")
    module.load_state_dict(payload["state_dict"])
    return module, dict(payload.get("metadata", {}))


def level_options(level: str, seed: int, config: MiniGridConfig, out_dir: str) -> tuple[torch.nn.Module, dict]:
    """The options of ``(level, seed)``: from ``<out_dir>/options/<level>/seed<s>.pt``, else discovered by a
    segmentation cell (its record appended to ``<out_dir>/segmentation.jsonl``) and cached. A file lock makes a
    second process wait for the first one's options."""
    from torchrl_options.experiments.minigrid.segmentation import segmentation_cell
    from torchrl_options.experiments.minigrid.summary import append_record

    folder = os.path.join(out_dir, "options", level)
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, f"seed{seed}.pt")
    with FileLock(path + ".lock"):
        if os.path.exists(path):
            return load_minigrid_options(path)
        record, options = segmentation_cell(level, seed, method=segmentation_method(config),
                                            num_demonstrations=config.num_demonstrations, return_options=True)
        append_record(os.path.join(out_dir, "segmentation.jsonl"), record)
        metadata = {"level": level, "seed": seed, "num_options": config.num_options, "network": config.network,
                    "label_accuracy": record["subgoal"]["ddo"]["label_accuracy"]}  # fmt: skip
        save_minigrid_options(options.cpu(), path, metadata)
        return options, metadata


def _chunk_frames(checkpoint_every: int, frames_per_batch: int) -> int:
    """The frames of one checkpoint chunk of an RL cell: ``checkpoint_every`` rounded down to whole collector batches
    (at least one)."""
    return max(1, checkpoint_every // frames_per_batch) * frames_per_batch


def _frames_per_batch(config: MiniGridConfig, algorithm: str) -> int:
    """The collector batch of ``algorithm``'s agent (:func:`_make_agent`): ``frames_per_batch`` for PPO, the DQN
    agent's own default for DQN."""
    if algorithm == "ppo":
        return config.frames_per_batch
    from torchrl_options.agents import OptionsDQNConfig

    return OptionsDQNConfig.frames_per_batch


def episode_cut_warning(config: MiniGridConfig) -> str | None:
    """Why the RL cells' checkpoint chunks are too short for ``rl_level``'s episodes, or ``None`` when they are not.

    A cell trains in chunks of ``checkpoint_every`` frames (rounded down to whole collector batches), each a fresh
    ``train`` call that restarts the envs' episodes (so that a resumed cell is the uninterrupted one). An episode
    still running at a chunk's end is cut there and never recorded. Those are mostly the long, failed ones: the
    success rate is then biased up, and the agents learn from episodes shorter than the level's limit. With a
    chunk's steps per env against an episode limit ``L`` (``max_episode_steps``, else the level's own), fewer than
    ``10 L`` is flagged; a cell trained in a single chunk never cuts.

    Examples:
        >>> episode_cut_warning(MiniGridConfig(rl_level="BabyAI-UnlockPickup-v0")) is None  # doctest: +SKIP
        True
    """
    batches = {_frames_per_batch(config, c.partition("-")[0]) for c in config.conditions}
    chunk = min(_chunk_frames(config.checkpoint_every, b) for b in batches)
    if chunk >= config.rl_frames:
        return None
    limit = config.max_episode_steps
    if limit is None:
        from torchrl_options.envs.minigrid import make_minigrid_gym

        env = make_minigrid_gym(config.rl_level)
        limit = int(env.unwrapped.max_steps)
        env.close()
    steps = chunk // config.num_envs
    if steps >= 10 * limit:
        return None
    single = max(-(-config.rl_frames // b) * b for b in batches)
    return (
        f"checkpoint_every={config.checkpoint_every} frames over num_envs={config.num_envs} envs gives each env "
        f"{steps} steps per chunk, against {limit}-step episodes on {config.rl_level}: every chunk restarts the "
        "episodes, so the ones still running at its end (mostly failures) are cut and not recorded, which biases "
        f"the success rate up. Set checkpoint_every to at least {10 * limit * config.num_envs}, or to at least "
        f"{single} (one chunk per cell)."
    )


def minigrid_cells(config: MiniGridConfig) -> list[Cell]:
    """The RL cells: ``rl_level`` x ``conditions`` x seeds ``0 .. rl_seeds - 1``, conditions outermost.

    Examples:
        >>> [c.name for c in minigrid_cells(MiniGridConfig(conditions=["ppo-A", "ppo-H1"], rl_seeds=1))]
        ['BabyAI-UnlockPickup-v0-ppo-A-seed0', 'BabyAI-UnlockPickup-v0-ppo-H1-seed0']
    """
    return [Cell(config.rl_level, c, s) for c in config.conditions for s in range(config.rl_seeds)]


def _make_agent(config: MiniGridConfig, algorithm: str, seed: int, options, num_options):
    from torchrl_options.agents import OptionsDQN, OptionsDQNConfig, OptionsPPO, OptionsPPOConfig
    from torchrl_options.envs.minigrid import make_minigrid_env

    limit = {} if config.max_episode_steps is None else {"max_steps": config.max_episode_steps}
    factory = partial(make_minigrid_env, config.rl_level, **limit)
    mode = "actions" if options is None else "both"
    torch.manual_seed(seed)  # network initialisation and sampling draw from the global generator
    if algorithm == "ppo":
        ppo = OptionsPPOConfig(
            mode=mode, num_envs=config.num_envs, parallel=config.parallel, total_frames=config.rl_frames,
            frames_per_batch=config.frames_per_batch, num_epochs=config.ppo_epochs,
            minibatch_size=config.ppo_minibatch, lr=config.lr, gamma=config.gamma,
            entropy_coeff=config.entropy_coeff, hidden_sizes=tuple(config.hidden_sizes), seed=seed,
        )  # fmt: skip
        return OptionsPPO(factory, ppo, options=options, num_options=num_options)
    dqn = OptionsDQNConfig(
        mode=mode, num_envs=config.num_envs, parallel=config.parallel, total_frames=config.rl_frames, lr=config.lr,
        gamma=config.gamma, hidden_sizes=tuple(config.hidden_sizes), eps_init=1.0, eps_end=0.05,
        eps_annealing_frames=config.dqn_eps_frames, seed=seed,
    )  # fmt: skip
    return OptionsDQN(factory, dqn, options=options, num_options=num_options)


def run_minigrid_cell(cell: Cell, *, config: MiniGridConfig | dict, out_dir: str, progress: bool = False) -> CellResult:
    """Runs one RL cell ``(rl_level, "<algorithm>-<A|H1|H1t>", seed)``, resuming from its checkpoint.

    Trains in chunks of ``checkpoint_every`` frames (each a fresh ``train`` call, checkpointed with every random
    state: a resumed cell is the uninterrupted one). The options of ``H1`` (``rl_level``'s) and ``H1t``
    (``transfer_source``'s) come from :func:`level_options`. The cell's random numbers come from its seed; the
    caller's global random states are restored when it ends.

    Returns:
        The episode returns and the frame count at the end of each episode (frames of the RL run only; the
        demonstrations' frames are in ``info["demonstration_frames"]``).
    """
    if isinstance(config, dict):
        config = MiniGridConfig.from_dict(config)
    algorithm, _, kind = cell.condition.partition("-")
    with scoped_seed(cell.seed):
        return _run_cell(cell, algorithm, kind, config, out_dir, progress)


def _run_cell(cell: Cell, algorithm: str, kind: str, config: MiniGridConfig, out_dir: str, progress: bool) -> CellResult:
    t0 = time.time()
    options, metadata = None, {}
    if kind in ("H1", "H1t"):
        source = config.rl_level if kind == "H1" else config.transfer_source
        options, metadata = level_options(source, cell.seed, config, out_dir)
    agent = _make_agent(config, algorithm, cell.seed + 1000, options, config.num_options if options is not None else None)
    folder = os.path.join(out_dir, "rl")
    os.makedirs(folder, exist_ok=True)
    partial_path = os.path.join(folder, f"{cell.name}.partial.pt")
    if os.path.exists(partial_path):
        agent.load(partial_path)
        logger.info("%s: resumed at %d frames", cell.name, agent.frames)
    chunk = _chunk_frames(config.checkpoint_every, agent.config.frames_per_batch)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.rl_frames, initial=agent.frames, desc=cell.name, unit="frame", leave=False)
    try:
        while agent.frames < config.rl_frames:
            before = agent.frames
            agent.train(total_frames=min(chunk, config.rl_frames - agent.frames))
            if bar is not None:
                bar.update(agent.frames - before)
            if agent.frames < config.rl_frames:
                save_file(agent.state_dict(include_buffer=True), partial_path)
    finally:
        if bar is not None:
            bar.close()
        if not agent.env.is_closed:
            agent.env.close()
    log = agent.log
    if not log.episode_returns:
        raise ValueError(
            f"{cell.name}: no episode ended in rl_frames={config.rl_frames} frames over {config.num_envs} envs: raise "
            "rl_frames or lower max_episode_steps (an episode lasts up to the level's step limit)."
        )
    info = {"seconds": time.time() - t0, "frames": agent.frames, "options": metadata}
    with open(os.path.join(folder, f"{cell.name}.json"), "w") as f:
        json.dump(info, f)
    if os.path.exists(partial_path):
        os.remove(partial_path)
    return CellResult(returns=[float(r) for r in log.episode_returns], frames=[int(f) for f in log.episode_end_frames],
                      info=info)  # fmt: skip
