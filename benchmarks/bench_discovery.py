"""End-to-end DDO discovery time on the paper's four-rooms demonstrations (50 x 1000 steps, K = 4 options).

Generates the value-iteration supervisor's demonstrations (timed separately), then runs
:func:`~torchrl_options.discover_options` (full batch, uniform meta-control, the paper's 2-tanh-unit MLPs) and
reports the wall time, the process CPU time (what the run costs on an idle machine: with other jobs on the cores,
the wall time is longer), the time per iteration and the log-likelihood per step along the way.

Each iteration is one E-step (exact forward-backward) and ``--m-steps`` Adam steps on the expected complete-data
log-likelihood (``--m-steps 1``: the paper's plain Expectation-Gradient).

Converged, by definition: the stopping rule of ``discover_options(tol=..., patience=...)`` fired, i.e. the
log-likelihood per step gained less than ``--tol`` nats over the last ``--patience`` iterations. With
``--reference-iterations N`` the same configuration is then run for N iterations without the stopping rule, and the
benchmark checks that the converged value is within ``--reference-gap`` (0.01) nats per step of that long run.

    python benchmarks/bench_discovery.py --threads 1
    python benchmarks/bench_discovery.py --threads 2 --reference-iterations 600
    python benchmarks/bench_discovery.py --m-steps 1 --lr 0.1 --iterations 400 --tol 0   # the old schedule
    python benchmarks/bench_discovery.py --threads 2 --no-numba   # as without the `fast` extra (E-step "chunked")
    python benchmarks/bench_discovery.py --threads 2 --e-step reference   # any E-step backend in place of "auto"
"""
from __future__ import annotations

import argparse
import importlib
import os
import time

# OpenMP threads that spin while they wait make --threads 2 ten times slower when other jobs share the cores
# (measured: an E-step 2.8 s instead of 0.18 s); sleeping waits cost nothing on an idle machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from torchrl_options import discover_options  # noqa: E402
from torchrl_options.envs.supervisor import generate_demonstrations  # noqa: E402


def _load() -> str:
    try:
        return "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:  # pragma: no cover
        return "load average unavailable"


def _run(data, args, num_iterations: int, tol: float | None):
    t0, c0 = time.perf_counter(), time.process_time()
    result = discover_options(
        data, num_options=args.options, num_iterations=num_iterations, m_steps=args.m_steps, lr=args.lr,
        tol=tol, patience=args.patience, init=args.init, restarts=1, num_cells=2, seed=args.seed, progress=False,
        return_info=True,
    )  # fmt: skip
    return result, time.perf_counter() - t0, time.process_time() - c0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trajectories", type=int, default=50)
    p.add_argument("--length", type=int, default=1000)
    p.add_argument("--options", type=int, default=4)
    p.add_argument("--iterations", type=int, default=500, help="the most iterations (E-steps)")
    p.add_argument("--m-steps", type=int, default=10, help="Adam steps per E-step (1: Expectation-Gradient)")
    p.add_argument("--lr", type=float, default=0.1)
    p.add_argument("--tol", type=float, default=1e-3, help="stopping rule, nats per step (0: run all iterations)")
    p.add_argument("--patience", type=int, default=20, help="stopping-rule window, in iterations")
    p.add_argument("--init", default="random", choices=["random", "kmeans"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--reference-iterations", type=int, default=0, help="also run this long without stopping")
    p.add_argument("--reference-gap", type=float, default=0.01)
    p.add_argument("--no-numba", action="store_true", help="run as if Numba were not installed (before/after)")
    p.add_argument("--e-step", default="auto", help="the forward_backward backend that 'auto' stands for")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    fb = importlib.import_module("torchrl_options.inference.forward_backward")
    if args.no_numba:
        fb.numba_available = lambda: False
    if args.e_step != "auto":
        resolve = fb.resolve_backend
        fb.resolve_backend = lambda backend, x: resolve(args.e_step if backend == "auto" else backend, x)
    e_step = fb.resolve_backend("auto", torch.zeros(args.trajectories, args.length, args.options))
    print(
        f"threads={torch.get_num_threads()}, {os.cpu_count()} CPUs, OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}, "
        f"{_load()} at start; E-step backend: {e_step}"
    )
    t0 = time.perf_counter()
    data = generate_demonstrations("four-rooms", args.trajectories, args.length, seed=args.seed)
    print(f"demonstrations {tuple(data.shape)} generated in {time.perf_counter() - t0:.1f} s")

    tol = args.tol if args.tol > 0 else None
    result, wall, cpu = _run(data, args, args.iterations, tol)
    ll = [h["log_likelihood_per_step"] for h in result.history]
    n = len(ll)
    print(
        f"discovery (K={args.options}, m_steps={args.m_steps}, lr={args.lr}, init={args.init}, seed={args.seed}): "
        f"{n} iterations in {wall:.1f} s wall, {cpu:.1f} s CPU ({wall / n * 1e3:.0f} ms wall, "
        f"{cpu / n * 1e3:.0f} ms CPU per iteration); {_load()} at the end"
    )
    for i in sorted({0, 4, 9, 24, 49, n // 2, n - 1} & set(range(n))):
        print(f"  iteration {i + 1:>5}: log-likelihood per step {ll[i]:.4f}")
    if result.converged:
        print(
            f"converged (gain < {args.tol} nats/step over the last {args.patience} iterations) at iteration {n}, "
            f"after {wall:.1f} s wall ({cpu:.1f} s CPU); final log-likelihood per step {ll[-1]:.4f}"
        )
    else:
        print(f"NOT converged within {n} iterations ({wall:.1f} s); final log-likelihood per step {ll[-1]:.4f}")
    if args.reference_iterations:
        ref, ref_wall, _ = _run(data, args, args.reference_iterations, None)
        ref_ll = ref.final_log_likelihood_per_step
        gap = ref_ll - ll[-1]
        print(
            f"reference: {args.reference_iterations} iterations ({ref_wall:.1f} s) reach {ref_ll:.4f}; the converged "
            f"value is {gap:.4f} nats/step below it: {'within' if gap <= args.reference_gap else 'NOT within'} "
            f"{args.reference_gap}"
        )


if __name__ == "__main__":
    main()
