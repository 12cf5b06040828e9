"""What the Atari RAM pipeline builds and runs: a game's env factory, a DQN agent over actions (and options),
greedy rollouts of its Q-network, and its checkpoints."""
from __future__ import annotations

import logging
import os
from functools import partial

import torch
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.utils import step_mdp

from torchrl_options.checkpoints import load_file, scoped_seed
from torchrl_options.experiments.atari.config import AtariConfig

logger = logging.getLogger(__name__)


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
    with scoped_seed(seed):  # the Q-network's initial weights come from the seed alone
        q_net = ram_q_network(out, encoding=config.ram_encoding, num_cells=config.hidden_sizes)
    settings = config.dqn_settings()  # lr, gamma, batch_size, ...: the settings both configs have
    settings.update(
        num_envs=1 if config.vector_env else config.num_envs,  # a vector env is batched already
        hidden_sizes=tuple(config.hidden_sizes),
    )
    dqn_config = OptionsDQNConfig(
        **settings, mode=mode, total_frames=10**12, greedy_options=greedy_options,
        intra_option_actions=intra_option_actions, option_suffixes=option_suffixes, seed=seed,
    )  # fmt: skip
    torch.manual_seed(seed)  # the recipe seeds the global generator (network init, exploration); the agent does not
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


def _load_if(agent, path: str) -> bool:
    if os.path.exists(path):
        agent.load_state_dict(load_file(path, what="Atari DQN checkpoint", map_location=agent.device))
        logger.info("resumed from %s (%d episodes)", path, len(agent.log.episode_returns))
        return True
    return False


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
