"""Throughput of the PPO loop (collection, decision-level batches, GAE, ClipPPOLoss updates) with and without options.

The four-rooms PPO recipe's agent (``recipes/config/four_rooms_ppo.yaml``: 16 natively batched GridWorld envs,
the ``ppo`` section's settings) over actions only (A), over actions + 4 options (H1: an ``OptionsMLP`` of the
discovered options' size) and over actions + a two-level hierarchy (H2: 4 + 4 options, nested executors). The
options are untrained (throughput does not depend on what they learned, only on how long they run: untrained
options terminate at random, so they run a few steps each). The agents take turns, ``--frames`` frames each per
round, so that load on a shared machine affects all alike; the table gives the median frames/s over rounds, in wall
time and in process CPU time (which time slicing on a loaded machine does not distort), and the ratio to A.

Run::

    python benchmarks/bench_ppo.py --rounds 3 --frames 16000
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from torchrl_options import OptionsMLP
from torchrl_options.experiments.gridworld import make_agent
from torchrl_options.hierarchy import OptionHierarchy

CONFIG = Path(__file__).resolve().parents[1] / "recipes" / "config" / "four_rooms_ppo.yaml"


def agents(seed: int = 0) -> dict:
    cfg = OmegaConf.to_container(OmegaConf.load(CONFIG), resolve=False)
    cfg = {"env": cfg["env"], "num_envs": cfg["num_envs"], "ppo": cfg["ppo"], "algorithm": "ppo"}
    torch.manual_seed(seed)
    h1 = OptionsMLP(4, 4, 4, num_cells=2)
    hierarchy = OptionHierarchy(4, [OptionsMLP(4, 4, 4, num_cells=2), OptionsMLP(4, 8, 4, num_cells=2)])
    return {
        "A": make_agent(cfg, "actions", seed),
        "H1": make_agent(cfg, "both", seed, options=h1, num_options=4),
        "H2": make_agent(cfg, "both", seed, options=hierarchy),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=16000, help="frames per agent per round")
    args = parser.parse_args()
    torch.set_num_threads(1)
    runs = agents()
    wall = {name: [] for name in runs}
    cpu = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, agent in runs.items():
            before_frames, w, c = agent.frames, time.perf_counter(), time.process_time()
            agent.train(total_frames=args.frames)
            frames = agent.frames - before_frames
            wall[name].append(frames / (time.perf_counter() - w))
            cpu[name].append(frames / (time.process_time() - c))
    base_wall, base_cpu = statistics.median(wall["A"]), statistics.median(cpu["A"])
    print(f"PPO loop, four rooms (16 envs, frames_per_batch {runs['A'].config.frames_per_batch}), "
          f"{args.rounds} rounds x {args.frames} frames per agent")
    print("| agent | frames/s (wall) | frames/s (CPU) | ratio to A (wall) | ratio to A (CPU) |")
    print("|---|---|---|---|---|")
    for name in runs:
        w, c = statistics.median(wall[name]), statistics.median(cpu[name])
        print(f"| {name} | {w:,.0f} | {c:,.0f} | {w / base_wall:.2f} | {c / base_cpu:.2f} |")


if __name__ == "__main__":
    main()
