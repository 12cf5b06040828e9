"""End-to-end DDO discovery time on the paper's four-rooms demonstrations (50 x 1000 steps, K = 4 options).

Generates the value-iteration supervisor's demonstrations (timed separately), then runs
:func:`~torchrl_options.discover_options` (full batch, uniform meta-control, the paper's 2-tanh-unit MLPs) and
reports the wall time, the time per iteration, the log-likelihood per step along the way, and the iteration at
which it converged: the first iteration after which the log-likelihood per step never improves by more than
``--tol`` (default 1e-3 nats/step) over the best seen so far.

    python benchmarks/bench_discovery.py --iterations 300 --threads 2
"""
from __future__ import annotations

import argparse
import time

import torch

from torchrl_options import discover_options
from torchrl_options.envs.supervisor import generate_demonstrations


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trajectories", type=int, default=50)
    p.add_argument("--length", type=int, default=1000)
    p.add_argument("--options", type=int, default=4)
    p.add_argument("--iterations", type=int, default=300)
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tol", type=float, default=1e-3)
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    data = generate_demonstrations("four-rooms", args.trajectories, args.length, seed=args.seed)
    t_demo = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = discover_options(
        data, num_options=args.options, num_iterations=args.iterations, lr=args.lr, seed=args.seed,
        progress=False, return_info=True,
    )
    t_disc = time.perf_counter() - t0
    ll = [h["log_likelihood_per_step"] for h in result.history]
    best, converged = float("-inf"), len(ll)
    for i, x in enumerate(ll):
        if x > best + args.tol:
            best, converged = x, i + 1
    per_iter = t_disc / max(1, len(ll))
    print(f"threads={torch.get_num_threads()} demonstrations {tuple(data.shape)} generated in {t_demo:.1f} s")
    print(f"discovery: {len(ll)} iterations in {t_disc:.1f} s ({per_iter * 1e3:.0f} ms / iteration)")
    for i in sorted({0, len(ll) // 4, len(ll) // 2, 3 * len(ll) // 4, len(ll) - 1}):
        print(f"  iteration {i + 1:>5}: log-likelihood per step {ll[i]:.4f}")
    print(f"converged (no gain > {args.tol} nats/step afterwards) at iteration {converged}, "
          f"after about {converged * per_iter:.1f} s; final log-likelihood per step {ll[-1]:.4f}")


if __name__ == "__main__":
    main()
