"""The Atari RAM experiment's resumable per-cell pipeline: phase 1 (DQN over actions), phase 2 (greedy
demonstrations and DDO, shared by the conditions of a seed), phase 3 (each condition), with checkpoints that make a
resumed cell the uninterrupted one, bit for bit. See :mod:`torchrl_options.experiments.atari`."""
from __future__ import annotations

import logging
import math
import os
import time

import torch
from filelock import FileLock
from tensordict.nn import TensorDictModuleBase

from torchrl_options.checkpoints import save_file, save_json_file, scoped_seed
from torchrl_options.checks import check_int
from torchrl_options.experiments.atari.conditions import _option_flags, CONDITIONS
from torchrl_options.experiments.atari.config import AtariConfig
from torchrl_options.experiments.atari.figures import write_option_frames
from torchrl_options.experiments.atari.utils import (
    _close,
    _env_factory,
    _greedy_rollouts,
    _load_if,
    _make_agent,
    _num_actions,
)
from torchrl_options.experiments.sweep import Cell, CellResult

__all__ = ["run_atari_cell", "option_usage", "demonstrations_log_likelihood"]

logger = logging.getLogger(__name__)


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
        max_steps = config.env_kwargs()["max_episode_steps"] or 27_000
        agent.record_evaluation(config.eval_episodes, episodes_per_game * max_steps)


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
            save_file(agent.state_dict(include_buffer=config.checkpoint_buffer), partial_path)


def _seed_lock(seed_dir: str) -> FileLock:
    """The lock of a seed's shared phases 1 and 2 (``<seed_dir>/.lock``): across processes and machines sharing
    the folder, on POSIX and Windows alike; the cells of a seed wait for the first one's checkpoint and options."""
    return FileLock(os.path.join(seed_dir, ".lock"))


def _phase1(game: str, config: AtariConfig, seed: int, seed_dir: str):
    path = os.path.join(seed_dir, "phase1.pt")
    agent = _make_agent(game, config, seed, "actions")
    if not _load_if(agent, path):
        partial_path = os.path.join(seed_dir, "phase1.partial.pt")
        _load_if(agent, partial_path)
        t0 = time.time()
        _train_episodes(agent, config.phase1_episodes, partial_path, config)
        save_file(agent.state_dict(include_buffer=config.checkpoint_buffer), path)
        logger.info("%s seed %d: phase 1 done in %.0fs", game, seed, time.time() - t0)
        if os.path.exists(partial_path):
            os.remove(partial_path)
    return agent, path


def _phase2(game: str, config: AtariConfig, seed: int, seed_dir: str, agent):
    """Greedy demonstrations of phase 1's DQN, their quality gate, and DDO; the options, cached in
    ``<seed_dir>/options.pt``, with what phase 2 measured in ``<seed_dir>/phase2.json`` (see :func:`phase2_report`)."""
    from torchrl_options.discovery import discover_options, load_options, save_options

    path = os.path.join(seed_dir, "options.pt")
    report = os.path.join(seed_dir, "phase2.json")
    if os.path.exists(path):
        options, _, metadata = load_options(path, with_meta_control=True)
        if not os.path.exists(report):  # written before the options since issue 53; rewritten for older runs
            save_json_file(metadata, report)
        return options, metadata
    t0 = time.time()
    demos = _greedy_rollouts(agent, game, config, seed, config.num_demonstrations, config.demo_max_steps)
    demo_frames = int(sum(t.numel() for t in demos))
    k = config.options_for(game)
    num_actions = _num_actions(game, config)
    demos = [t.select("observation", "action", ("next", "observation"), ("next", "done"), ("next", "terminated"),
                      ("next", "reward")) for t in demos]  # fmt: skip
    result = discover_options(
        demos,
        num_options=k,
        **_ddo_starts(config, int(demos[0]["observation"].shape[-1]), num_actions, k, seed),
        num_actions=num_actions,
        num_cells=list(config.options_num_cells),
        activation="tanh",
        num_iterations=config.ddo_iterations,
        batch_size=config.ddo_batch_size,
        lr=config.ddo_lr,
        m_steps=config.ddo_m_steps,
        tol=None,  # the paper's protocol: every iteration run
        usage_floor=config.ddo_usage_floor,
        device=config.device,
        seed=seed,
        progress=False,
        return_info=True,
    )
    options = result.options.cpu()
    demo_returns = [float(t["next", "reward"].sum()) for t in demos]
    epsilon = float(agent.exploration.eps)
    metadata = {
        "game": game,
        "num_options": k,
        "option_encoding": config.option_encoding,
        "demo_frames": demo_frames,
        "demo_returns": demo_returns,
        "log_likelihood_per_step": result.final_log_likelihood_per_step,
        # every demonstration step is the greedy action, which the epsilon-greedy demonstrator takes with
        # probability 1 - eps + eps / A
        "options_log_likelihood_per_step": demonstrations_log_likelihood(options, demos),
        "demonstrator_log_likelihood_per_step": math.log(1.0 - epsilon + epsilon / num_actions),
        "demonstrator_epsilon": epsilon,
        "option_duration": result.history[-1].get("option_duration", float("nan")) if result.history else float("nan"),
        # per option, the posterior share of the demonstrations' steps it is active (DDO's usage diagnostic)
        "option_usage": [float(u) for u in result.option_usage],
        **_quality_gate(game, config, seed, demo_returns),
        "seconds": time.time() - t0,
    }
    # the report first, then the options (both atomic): a run killed between them finds no options and redoes
    # phase 2 (the same, from the seed), so the report always goes with the options it describes
    save_json_file(metadata, report)
    save_options(options, path, metadata=metadata)
    logger.info("%s seed %d: DDO done, %s", game, seed, {k: v for k, v in metadata.items() if k != "demo_returns"})
    return options, metadata


def _ddo_starts(config: AtariConfig, num_bytes: int, num_actions: int, k: int, seed: int) -> dict:
    """Where phase 2's options come from, as ``discover_options`` keyword arguments. ``ddo_starts="one"``: the
    paper's protocol and the kept runs, one start (the one-hot network drawn from the seed alone); ``"defaults"``:
    a factory of fresh networks, so that DDO gets its default starts (segment starts, restarts)."""

    def one_hot_options() -> TensorDictModuleBase:
        from torchrl_options.modules import OneHotByteOptions

        return OneHotByteOptions(num_bytes, num_actions, k, num_cells=list(config.options_num_cells), value_scale=1 / 255)

    one_hot = config.option_encoding == "one_hot"
    if config.ddo_starts == "defaults":
        # "bytes": the default OptionsMLP of num_cells, fresh at each start as well
        return {"options_factory": one_hot_options if one_hot else None}
    options = None
    if one_hot:
        with scoped_seed(seed):  # the initial weights come from the seed alone
            options = one_hot_options()
    return {"options": options, "restarts": 1}


def demonstrations_log_likelihood(options, demos, *, chunk: int = 8) -> float:
    """The log-likelihood per step of trajectories under ``options`` (uniform meta-control, DDO's model: the
    options' actions and terminations marginalised over), every trajectory whole, ``chunk`` at a time.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP
        >>> one = OptionsMLP(2, 3, 1)  # one option: the likelihood is its policy's, whatever its terminations
        >>> demo = TensorDict({"observation": torch.randn(5, 2), "action": torch.zeros(5, dtype=torch.long),
        ...                    "next": {"observation": torch.randn(5, 2)}}, [5])
        >>> log_pi = one(demo.clone())["option_logits"][:, 0].log_softmax(-1)[:, 0]
        >>> abs(demonstrations_log_likelihood(one, [demo]) - float(log_pi.mean().detach())) < 1e-5
        True
    """
    from torchrl_options import as_trajectory_batch, DDOLoss

    loss = DDOLoss(options, None, reduction="sum", diagnostics=False)
    total, steps = 0.0, 0
    with torch.no_grad():
        for i in range(0, len(demos), chunk):
            batch = as_trajectory_batch(list(demos[i : i + chunk]))
            total -= float(loss(batch)["loss_ddo"])
            steps += int(batch.get(("collector", "mask")).sum())
    return total / max(steps, 1)


def _quality_gate(game: str, config: AtariConfig, seed: int, demo_returns: list[float]) -> dict:
    """The random policy's mean return on the same game (``demo_random_episodes`` episodes of at most
    ``demo_max_steps`` steps) and whether the demonstrations are no better (a degenerate demonstrator: logged)."""
    if not config.demo_random_episodes:
        return {"random_returns": [], "degenerate_demonstrator": None}
    env = _env_factory(game, config, seed)()
    env.set_seed(seed + 888)
    with torch.no_grad(), scoped_seed(seed + 888):  # the random actions come from the seed, the caller's RNG is kept
        returns = [float(env.rollout(config.demo_max_steps)["next", "reward"].sum())
                   for _ in range(config.demo_random_episodes)]  # fmt: skip
    env.close()
    demo_mean, random_mean = sum(demo_returns) / len(demo_returns), sum(returns) / len(returns)
    degenerate = demo_mean <= random_mean
    if degenerate:
        logger.warning(
            "%s seed %d: degenerate demonstrator: the %d greedy demonstrations return %.2f on average, no better than "
            "a random policy's %.2f over %d episodes; DDO runs on them as the paper's protocol does.",
            game, seed, len(demo_returns), demo_mean, random_mean, len(returns),
        )  # fmt: skip
    return {"random_returns": returns, "degenerate_demonstrator": bool(degenerate)}


def option_usage(agent, num_actions: int, start: int = 0) -> dict[str, float]:
    """How much an agent over actions + options used its options, from the decisions in its replay buffer.

    Reads the decisions stored from position ``start`` on (to skip decisions copied in by a warm start), up to
    the buffer's capacity, leaving out the one-step transitions of steps inside options (``"intra_option"``, with
    ``OptionsDQNConfig.intra_option_actions``). A decision is an option when its action index is ``num_actions`` or
    more. A decision's length is its ``"decision_steps"`` (written with ``discount_per="decision"``, where
    ``steps_to_next_obs`` is 1 for the bootstrap), else its ``steps_to_next_obs``.

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
    check_int(num_actions, "num_actions", minimum=1)
    check_int(start, "start", minimum=0)
    if not hasattr(agent, "replay_buffer"):
        raise TypeError(f"option_usage expects an agent with a replay buffer (an OptionsDQN), got {type(agent).__name__}.")
    n = len(agent.replay_buffer)
    if n <= start:
        return {"option_decision_share": float("nan"), "option_step_share": float("nan"), "mean_option_steps": float("nan")}
    data = agent.replay_buffer[start:n]
    if "intra_option" in data.keys():
        data = data[~data.get("intra_option").reshape(-1)]
    is_option = data.get("action").reshape(-1) >= num_actions
    # per decision, steps_to_next_obs is 1 whatever the length: the length is kept in "decision_steps"
    steps_key = "decision_steps" if "decision_steps" in data.keys() else "steps_to_next_obs"
    steps = data.get(steps_key).reshape(-1).float()
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

    The cell's random numbers come from its seed alone (each agent seeds torch when it is made); the caller's
    global random states are restored when the cell ends (:func:`~torchrl_options.checkpoints.scoped_seed`), and
    the thread count is the caller's (the recipe sets ``AtariConfig.torch_threads``).
    """
    if isinstance(config, dict):
        config = AtariConfig.from_dict(config)
    if cell.condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {cell.condition!r}.")
    with scoped_seed(cell.seed):  # every random state of the caller is left as it was
        return _run_cell(cell, config, out_dir)


def _run_cell(cell: Cell, config: AtariConfig, out_dir: str) -> CellResult:
    game, seed = cell.setting, cell.seed
    seed_dir = os.path.join(out_dir, game, f"seed{seed}")
    os.makedirs(seed_dir, exist_ok=True)
    t0 = time.time()
    with _seed_lock(seed_dir):
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
    save_json_file(info, os.path.join(seed_dir, f"{cell.condition}.json"))
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
