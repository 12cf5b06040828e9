"""Two rooms, actions + options (AO): which decisions the agent takes, and what its Q-function says at the start.

Trains one AO agent of the two-rooms recipe (same config, options discovered or loaded from ``out_dir``) and prints,
every 100 episodes: the mean return of the last 100 episodes, the share of decisions that were primitive actions,
and the Q-values of the best primitive action and of the best option at the start state.

    python recipes/two_rooms_ao_diagnostic.py --seed 0 env.max_steps=200 dqn.max_decisions=20
    python recipes/two_rooms_ao_diagnostic.py --seed 0 env.max_steps=200 dqn.max_decisions=20 dqn.discount_per=decision

Anything after the options is a Hydra override of ``recipes/config/two_rooms.yaml``.
"""
from __future__ import annotations

import argparse
import os

import torch
from hydra import compose, initialize_config_dir

from torchrl_options.experiments import Cell
from torchrl_options.experiments.gridworld import cell_options, make_agent
from torchrl_options.experiments.recipe_runner import recipe_guard
from torchrl_options.experiments.gridworld_config import gridworld_settings


def main(argv=None) -> list[tuple[int, float, float, float, float]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--every", type=int, default=100)
    p.add_argument("overrides", nargs="*")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    config_dir = os.path.join(os.path.dirname(os.path.abspath(__file__)), "config")
    with initialize_config_dir(config_dir, version_base="1.3"):
        cfg = compose("two_rooms", overrides=["out_dir=outputs/two_rooms_ao_diagnostic", "progress=false"] + args.overrides)
    for name in ("seed", "episodes", "every"):
        minimum = 0 if name == "seed" else 1
        if getattr(args, name) < minimum:
            raise ValueError(f"--{name} must be an int >= {minimum}, got {getattr(args, name)}.")
    cfg = gridworld_settings(cfg)  # the recipe settings, checked before any work
    options = cell_options(cfg, Cell("supervised", "AO", args.seed))
    K = int(cfg["discovery"]["num_options"])
    agent = make_agent(cfg, "both", args.seed, options, K)
    A = agent.env.action_spec.n - K
    counts = {"primitive": 0, "option": 0}
    rows = []

    def callback(agent, batch) -> bool:
        decided = batch["next", "option_decision"].reshape(-1).bool()
        chosen = batch["action"].reshape(-1)[decided]
        counts["primitive"] += int((chosen < A).sum())
        counts["option"] += int((chosen >= A).sum())
        n = len(agent.log.episode_returns)
        if n >= (len(rows) + 1) * args.every:
            with torch.no_grad():
                q = agent.actor(agent.env.reset())["action_value"].reshape(-1, A + K).mean(0)
            recent = agent.log.episode_returns[-args.every:]
            share = counts["primitive"] / max(counts["primitive"] + counts["option"], 1)
            rows.append((n, sum(recent) / len(recent), share, q[:A].max().item(), q[A:].max().item()))
            print(f"episode {n:5d}  return {rows[-1][1]:.2f}  primitive decisions {share:.2f}  "
                  f"Q(start): best primitive {rows[-1][3]:.3f}, best option {rows[-1][4]:.3f}", flush=True)
            counts["primitive"] = counts["option"] = 0
        return n >= args.episodes

    agent.train(total_frames=10**12, callback=callback)
    return rows


if __name__ == "__main__":
    with recipe_guard("outputs/two_rooms_ao_diagnostic", checkpoints="cells (options only: the DQN reruns)"):
        main()
