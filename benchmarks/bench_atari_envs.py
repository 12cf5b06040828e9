"""Env steps per second of the Atari RAM pipeline: one game per agent against batches of games.

The Atari recipe's agents are small (a one-hot RAM embedding and three 32-unit tanh layers), so on CPU an env step
costs mostly TorchRL's per-step work (transforms, the policy's TensorDict modules, the collector), not the
emulator. Batching games shares that work among them, if the batch is one env to TorchRL:

- ``single``: one game, ``make_atari_ram_env(game)`` (the recipe's default, ``num_envs=1``) — the baseline;
- ``SerialEnv xN``: ``N`` games in TorchRL's ``SerialEnv`` (``atari.num_envs=N``): every game still goes through
  its own TorchRL env and transforms each step;
- ``vector xN``: ``N`` games in one gymnasium ``SyncVectorEnv`` (``atari.num_envs=N atari.vector_env=true``,
  :func:`~torchrl_options.envs.atari.make_atari_ram_env` with ``num_envs=N``): TorchRL sees one env with batch
  ``[N]``.

Measured for three workloads, variants taking turns round by round so that load on a shared machine affects all
alike:

- ``rollout``: random actions, the env alone;
- ``A``: OptionsDQN training over actions, the ``cores16`` preset's settings (2 gradient steps per 50 env steps,
  kept per env step when batching: ``updates_per_batch`` scaled with ``N``), fused Adam;
- ``H1``: the same over actions + ``K`` options (random ``OptionsMLP`` networks, as DDO's have this shape),
  with the :class:`~torchrl_options.transforms.OptionExecutor` over the batch.

Run (1 thread per process, as in the recipe's sweeps)::

    python benchmarks/bench_atari_envs.py --rounds 3 --frames 4000
    python benchmarks/bench_atari_envs.py --game Seaquest --num-envs 16
"""
from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import torch
from torchrl.envs import SerialEnv

from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
from torchrl_options.envs.atari import make_atari_ram_env, ram_q_network
from torchrl_options.modules import OptionsMLP


def make_factory(variant: str, game: str, n: int):
    one = partial(make_atari_ram_env, game, max_episode_steps=200, ram_encoding="bytes")
    if variant == "single":
        return one, 1
    if variant == "serial":
        return partial(SerialEnv, n, one), n
    return partial(one, num_envs=n), n


def rollout_rate(factory, frames: int, n: int) -> float:
    env = factory()
    env.set_seed(0)
    env.rollout(10, break_when_any_done=False)
    steps = max(frames // n, 1)
    t0 = time.perf_counter()
    env.rollout(steps, break_when_any_done=False)
    rate = steps * n / (time.perf_counter() - t0)
    if not env.is_closed:
        env.close()
    return rate


def train_rate(factory, n: int, frames: int, num_options: int, num_actions: int) -> float:
    mode = "both" if num_options else "actions"
    config = OptionsDQNConfig(mode=mode, frames_per_batch=50 * n, batch_size=32, learning_starts=200,
                              updates_per_batch=2 * n, lr=1e-3, gamma=0.85, eps_init=0.05, eps_end=0.05,
                              eps_annealing_frames=1, hard_update_interval=100, seed=0)
    torch.manual_seed(0)
    options = OptionsMLP(128, num_actions, num_options, num_cells=[32, 32]) if num_options else None
    q_net = ram_q_network(num_actions + num_options, encoding="one_hot", num_cells=[32, 32, 32])
    agent = OptionsDQN(factory, config, options=options, num_options=num_options or None, q_network=q_net,
                       optimizer=partial(torch.optim.Adam, fused=True))
    agent.train(total_frames=400)  # fill the buffer past learning_starts
    t0 = time.perf_counter()
    agent.train(total_frames=frames)
    rate = frames / (time.perf_counter() - t0)
    if not agent.env.is_closed:
        agent.env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=4000, help="env steps per measurement")
    parser.add_argument("--game", type=str, default="Pooyan")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--num-options", type=int, default=7, help="K of the H1 workload (Pooyan: 7)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    n = args.num_envs
    probe = make_atari_ram_env(args.game)
    num_actions = int(probe.action_spec.n)
    probe.close()
    variants = {"single": "single", f"SerialEnv x{n}": "serial", f"vector x{n}": "vector"}
    workloads = {"rollout": None, "A": 0, "H1": args.num_options}
    rates = {(v, w): [] for v in variants for w in workloads}
    for _ in range(args.rounds):
        for w, k in workloads.items():
            for v, kind in variants.items():
                factory, batch = make_factory(kind, args.game, n)
                if k is None:
                    rate = rollout_rate(factory, args.frames, batch)
                else:
                    rate = train_rate(factory, batch, args.frames, k, num_actions)
                rates[(v, w)].append(rate)
    print(f"{args.game}, {args.frames} env steps per measurement, threads={args.threads}, "
          f"medians over {args.rounds} rounds; ratio = variant / single")
    print("| variant | " + " | ".join(f"{w} steps/s | ratio" for w in workloads) + " |")
    print("|---|" + "---|---|" * len(workloads))
    for v in variants:
        cells = []
        for w in workloads:
            r, base = statistics.median(rates[(v, w)]), statistics.median(rates[("single", w)])
            cells.append(f"{r:.0f} | {r / base:.2f}x")
        print(f"| {v} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
