"""OptionsDQN's gradient step and training throughput with the default Adam against a fused Adam.

The Atari RAM Q-network (the paper's one-hot 128 x 256 input as an embedding, then dense tanh layers) has about
1M parameters in its first layer; ``torch.optim.Adam`` on CPU updates them tensor op by tensor op, which costs
more than the forward and backward of a 32-sample batch. ``OptionsDQN(..., optimizer=partial(torch.optim.Adam,
fused=True))`` (``atari.fused_adam=true`` in the recipe) runs the update as one fused kernel. Same algorithm;
results differ only by floating-point rounding.

Two measurements, the variants taking turns round by round so that load on a shared machine affects all alike:

- ``update``: one gradient step (forward, backward, optimizer step) on a batch of random RAM states, ms;
- ``train``: env steps per second of an actions-only OptionsDQN on an ALE RAM game (needs ale-py), with the
  recipe's ``cores16`` settings (2 gradient steps per 50 env steps).

Run::

    python benchmarks/bench_dqn_update.py --rounds 5
    python benchmarks/bench_dqn_update.py --rounds 3 --train-frames 3000 --game Pooyan
"""
from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import torch

from torchrl_options.envs.atari import ram_q_network

VARIANTS = {
    "adam (default)": partial(torch.optim.Adam),
    "adam foreach": partial(torch.optim.Adam, foreach=True),
    "adam fused": partial(torch.optim.Adam, fused=True),
}


def time_updates(make_opt, num_outputs: int, hidden: list[int], batch: int, steps: int) -> float:
    torch.manual_seed(0)
    net = ram_q_network(num_outputs, encoding="one_hot", num_cells=hidden)
    opt = make_opt(net.parameters(), lr=1e-3)
    x = torch.randint(0, 256, (batch, 128), dtype=torch.uint8)
    target = torch.randn(batch, num_outputs)

    def step():
        loss = (net(x) - target).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    for _ in range(3):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return (time.perf_counter() - t0) / steps * 1e3


def train_rate(make_opt, game: str, frames: int) -> float:
    from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
    from torchrl_options.envs.atari import make_atari_ram_env

    config = OptionsDQNConfig(mode="actions", frames_per_batch=50, batch_size=32, learning_starts=200,
                              updates_per_batch=2, lr=1e-3, gamma=0.85, eps_init=0.05, eps_end=0.05,
                              eps_annealing_frames=1, hard_update_interval=100, seed=0)
    factory = partial(make_atari_ram_env, game, max_episode_steps=200, ram_encoding="bytes")
    q_net = ram_q_network(factory().action_spec.n, encoding="one_hot", num_cells=[32, 32, 32])
    agent = OptionsDQN(factory, config, q_network=q_net, optimizer=make_opt)
    agent.train(total_frames=400)  # fill the buffer past learning_starts
    t0 = time.perf_counter()
    agent.train(total_frames=frames)
    rate = frames / (time.perf_counter() - t0)
    agent.env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--hidden", type=str, default="32,32,32")
    parser.add_argument("--outputs", type=int, default=13, help="Q-network outputs (Pooyan: 6 actions + 7 options)")
    parser.add_argument("--steps", type=int, default=50, help="gradient steps per round")
    parser.add_argument("--game", type=str, default="Pooyan")
    parser.add_argument("--train-frames", type=int, default=0, help="env steps per round of `train` (0: skip)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    hidden = [int(h) for h in args.hidden.split(",")]
    updates = {k: [] for k in VARIANTS}
    rates = {k: [] for k in VARIANTS}
    for _ in range(args.rounds):
        for name, make_opt in VARIANTS.items():
            updates[name].append(time_updates(make_opt, args.outputs, hidden, args.batch, args.steps))
            if args.train_frames:
                rates[name].append(train_rate(make_opt, args.game, args.train_frames))
    base = "adam (default)"
    print(f"threads={args.threads}, batch={args.batch}, hidden={hidden}, outputs={args.outputs}, "
          f"medians over {args.rounds} rounds")
    print(f"| optimizer | update (ms) | speed-up | train env steps/s ({args.game}) | ratio |")
    print("|---|---|---|---|---|")
    for name in VARIANTS:
        u = statistics.median(updates[name])
        if rates[name]:
            r, rb = statistics.median(rates[name]), statistics.median(rates[base])
            train = f"{r:.0f} | {r / rb:.2f}x"
        else:
            train = "not run (--train-frames 0) | -"
        print(f"| {name} | {u:.2f} | {statistics.median(updates[base]) / u:.2f}x | {train} |")


if __name__ == "__main__":
    main()
