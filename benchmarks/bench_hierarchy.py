"""Benchmark of the multi-level E-step: ``hierarchical_forward_backward`` forward pass + gradient.

Compares its three exact backends on the same inputs, in one run: ``structured`` (the pop/push recursion over
the tree of call stacks, T sequential steps), ``dense`` (S x S transition matrices, one log-space product per
step) and ``chunked`` (the dense matrices multiplied time-parallel, about 2 sqrt(T) sequential steps; the
``auto`` choice from 48 steps while ``B T S^2 (D + 1) <= 2^24``: its float64 matrices are memory-bound, and the
structured recursion wins on larger batches). The default shape is the four-rooms level-2 minibatch: 10 trajectories of 1000
steps, 4 level-1 and 4 level-2 options (S = 20 call stacks).

Prints the time of forward + gradient with respect to the top level's inputs (best of ``--repeats`` after a warm-up
call), the largest difference of the log-likelihood from the structured backend, and the speed-up over it.

    python benchmarks/bench_hierarchy.py
    python benchmarks/bench_hierarchy.py --shapes 10,1000,4,4 50,1000,4,4 --threads 2
"""
from __future__ import annotations

import argparse
import time

import torch

from torchrl_options.hierarchy import hierarchical_forward_backward

BACKENDS = ("structured", "dense", "chunked")


def make_inputs(B: int, T: int, A: int, sizes: list[int], seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    log_pi, log_term, log_cont = [], [], []
    n = A
    for K in sizes:
        log_pi.append((2.0 * torch.randn(B, T, K, n, generator=g)).log_softmax(-1))
        x = torch.randn(B, T, K, generator=g) - 1.0
        log_term.append(torch.nn.functional.logsigmoid(x))
        log_cont.append(torch.nn.functional.logsigmoid(-x))
        n += K
    log_eta = torch.randn(B, T, sizes[-1], generator=g).log_softmax(-1)
    action = torch.randint(A, (B, T), generator=g)
    for x in (log_pi[-1], log_term[-1], log_cont[-1]):
        x.requires_grad_()
    return action, log_pi, log_term, log_cont, log_eta


def run_once(backend: str, inputs) -> tuple[float, torch.Tensor]:
    action, log_pi, log_term, log_cont, log_eta = inputs
    start = time.perf_counter()
    ll = hierarchical_forward_backward(
        action, log_pi, log_term, log_cont, log_eta, backend=backend, validate=False
    ).log_likelihood
    torch.autograd.grad(ll.sum(), [log_pi[-1], log_term[-1], log_cont[-1]])
    return time.perf_counter() - start, ll.detach()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", nargs="+", default=["10,1000,4,4", "50,1000,4,4", "10,1000,2,2,2"],
                        help="B,T,K_1,...,K_D (A = 4)")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), A = 4, forward + gradient, best of {args.repeats}")
    header = f"{'B':>4} {'T':>6} {'sizes':>8} {'backend':>11} {'time (ms)':>10} {'max |dll|':>10} {'speed-up':>9}"
    print(header)
    print("-" * len(header))
    for shape in args.shapes:
        B, T, *sizes = (int(v) for v in shape.split(","))
        inputs = make_inputs(B, T, 4, sizes)
        times, lls = {}, {}
        for backend in BACKENDS:
            run_once(backend, inputs)  # warm-up
            best = float("inf")
            for _ in range(args.repeats):
                t, ll = run_once(backend, inputs)
                best = min(best, t)
            times[backend], lls[backend] = best, ll
        for backend in BACKENDS:
            diff = (lls[backend] - lls["structured"]).abs().max().item()
            print(f"{B:>4} {T:>6} {'x'.join(map(str, sizes)):>8} {backend:>11} {1e3 * times[backend]:>10.1f} "
                  f"{diff:>10.2e} {times['structured'] / times[backend]:>8.2f}x")  # fmt: skip


if __name__ == "__main__":
    main()
