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

The road to paper scale (``--protocol``): per game and env setting (``project``: the recipe's defaults; ``paper``:
the authors' ``-ram-v0``, ``env_semantics=paper``), the env steps/s of one core for the ``faithful`` preset's own
agents (the pipeline's ``_make_agent``: 8 games in a vector env, one-hot Q-network, one-hot options of the game's K,
its replay ratio) over actions (``A``) and over actions + options (``H1``), a random policy's mean episode length,
and from them the core-hours of the paper's protocol (per seed: 1000 phase-1 episodes, 100 demonstrations, 4000
episodes for each of ``A`` and ``H1``, 50 greedy rollouts every 100 episodes; 50 seeds)::

    python benchmarks/bench_atari_envs.py --protocol --frames 2000
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


def _faithful_config(setting: str, frames: int):
    from torchrl_options.experiments.atari import AtariConfig

    # the faithful preset's agents (recipes/config/preset/faithful.yaml) on CPU, checkpoints off
    return AtariConfig(env_semantics="paper" if setting == "paper" else "project", max_episode_steps=10_000,
                       discount_per="decision" if setting == "paper" else "step", num_envs=8, vector_env=True,
                       frames_per_batch=256, updates_per_batch=16, learning_starts=256, fused_adam=True,
                       checkpoint_every=0, device="cpu")  # fmt: skip


def protocol_rates(game: str, setting: str, frames: int) -> dict[str, float]:
    """Env steps/s of the faithful agents over actions (``A``) and actions + options (``H1``, one-hot options of
    the game's K with random weights), random rollouts (``rollout``, 8 games batched), and a random policy's mean
    episode length (``episode_steps``, 3 episodes of one game)."""
    from torchrl_options.envs.atari import PAPER_NUM_OPTIONS
    from torchrl_options.experiments.atari.utils import _close, _env_factory, _make_agent
    from torchrl_options.modules import OneHotByteOptions

    config = _faithful_config(setting, frames)
    out = {}
    env = _env_factory(game, config, 0, batched=True)()
    env.set_seed(0)
    env.rollout(10, break_when_any_done=False)
    t0 = time.perf_counter()
    env.rollout(max(frames // 8, 1), break_when_any_done=False)
    out["rollout"] = max(frames // 8, 1) * 8 / (time.perf_counter() - t0)
    env.close()
    one = _env_factory(game, config, 0)()
    one.set_seed(0)
    lengths = [one.rollout(10_000).shape[-1] for _ in range(3)]
    out["episode_steps"] = statistics.mean(lengths)
    one.close()
    k = PAPER_NUM_OPTIONS.get(game, 4)
    for workload in ("A", "H1"):
        if workload == "A":
            agent = _make_agent(game, config, 0, "actions")
        else:
            probe = _env_factory(game, config, 0)()
            num_actions = int(probe.action_spec.n)
            probe.close()
            torch.manual_seed(0)
            options = OneHotByteOptions(128, num_actions, k, num_cells=list(config.options_num_cells), value_scale=1 / 255)
            agent = _make_agent(game, config, 0, "both", options=options, num_options=k)
        agent.train(total_frames=512)  # past learning_starts
        t0 = time.perf_counter()
        agent.train(total_frames=frames)
        out[workload] = frames / (time.perf_counter() - t0)
        _close(agent)
    return out


def protocol_core_hours(rates: dict[str, float], episode_steps: float) -> dict[str, float]:
    """Core-hours of one seed of the paper's protocol in one game, with episodes of ``episode_steps`` steps: phase 1
    and ``A`` at ``rates["A"]`` (5000 episodes), ``H1`` at ``rates["H1"]`` (4000), 100 demonstrations and the greedy
    evaluations (50 rollouts every 100 episodes: 10 in phase 1, 40 in each condition's phase 3) at
    ``rates["rollout"]``.

    Examples:
        >>> h = protocol_core_hours({"A": 1000.0, "H1": 500.0, "rollout": 2000.0}, 100.0)
        >>> round(h["train"], 3), round(h["rollouts"], 3)
        (0.361, 0.064)
    """
    train = (5000 * episode_steps / rates["A"] + 4000 * episode_steps / rates["H1"]) / 3600
    rollouts = (100 + 50 * (10 + 40 + 40)) * episode_steps / rates["rollout"] / 3600
    return {"train": train, "rollouts": rollouts, "total": train + rollouts}


def protocol_main(args) -> None:
    from torchrl_options.envs.atari import ATARI_GAMES

    games = [args.game] if args.game != "all" else list(ATARI_GAMES)
    print(f"env steps/s on one core (threads={args.threads}), {args.frames} env steps per measurement; the faithful "
          "preset's agents, 8 games per vector env; core-hours per seed of the paper's protocol at a random policy's "
          "episode length (a lower bound: trained agents live longer) and at the 10,000-step cap (an upper bound)\n")
    print("| game | env | rollout steps/s | A steps/s | H1 steps/s | random episode (steps) | core-h per seed "
          "(random length) | core-h per seed (cap) | core-h, 50 seeds (random length) |")
    print("|---|---|---|---|---|---|---|---|---|")
    totals = {"project": [0.0, 0.0], "paper": [0.0, 0.0]}
    for game in games:
        for setting in ("project", "paper"):
            r = protocol_rates(game, setting, args.frames)
            low = protocol_core_hours(r, r["episode_steps"])["total"]
            high = protocol_core_hours(r, 10_000)["total"]
            totals[setting][0] += 50 * low
            totals[setting][1] += 50 * high
            print(f"| {game} | {setting} | {r['rollout']:.0f} | {r['A']:.0f} | {r['H1']:.0f} | "
                  f"{r['episode_steps']:.0f} | {low:.1f} | {high:.1f} | {50 * low:.0f} |")
    for setting, (low, high) in totals.items():
        print(f"\n{setting}: {len(games)} game(s) x 50 seeds: {low:.0f} core-hours at a random policy's episode "
              f"length, {high:.0f} at the 10,000-step cap.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=4000, help="env steps per measurement")
    parser.add_argument("--game", type=str, default="Pooyan")
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--num-options", type=int, default=7, help="K of the H1 workload (Pooyan: 7)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--protocol", action="store_true",
                        help="per game (--game all: the five) and env setting: the faithful agents' rates and core-hours")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.protocol:
        return protocol_main(args)
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
