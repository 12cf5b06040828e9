"""The CPU E-step against its memory-bandwidth floor and the naive K x K loop, side by side in one run (issue 52, 5).

What is timed, 1 thread (``torch.set_num_threads(1)``; run with ``OMP_NUM_THREADS=1``), float32, full-length rows,
the inputs of ``bench_forward_backward.make_inputs`` (softmax policies, sigmoid terminations, softmax meta-control):

* ``floor 7``: the time to read the four ``[B, T, K]`` inputs once and write three ``[B, T, K]`` outputs once,
  measured as a compiled streaming pass (one loop, ``o1 = a + b``, ``o2 = c + d``, ``o3 = a + d``) over arrays of
  exactly those shapes, written into preallocated outputs: the floor of the marginals alone (``u``, ``v``, ``w``).
* ``floor 11``: the same pass writing seven outputs: the floor of forward + gradient, which returns ``u``, ``v``,
  ``w`` and the four gradients.
* ``marginals``: ``forward_backward(..., validate=False)`` under ``torch.no_grad()`` (what DDO's E-step runs).
* ``fwd+grad``: ``forward_backward(..., validate=False)`` and ``torch.autograd.grad`` of the summed
  log-likelihood with respect to the four inputs.
* ``as a user``: ``forward_backward(...)`` with its defaults (``validate=True``, ``backend="auto"``) and
  ``log_likelihood.sum().backward()``, the gradients accumulated into the four leaves' ``.grad`` (set to ``None``
  first).
* ``naive``: the batched log-space loop over the full ``[B, K, K]`` transition (a ``logsumexp`` over the previous
  option at every step, the transition's ``logsumexp`` of its switch and stay terms), and ``torch.autograd.grad``
  of the summed log-likelihood with respect to the four inputs.

Method: one warm-up call of each, then ``--reps`` rounds in each of which every contender runs once, in an order
shuffled per round (interleaved, so that load from other processes hits all alike, and no contender always
follows the floor's passes, which leave the caches full of their own arrays). Medians over the rounds of the wall time and of
the process CPU time (with one thread and other jobs on the machine, CPU time is the closer estimate of an idle
machine's wall time; the ratios are given for both). ``x floor`` = ours / floor, ``naive / ours`` = naive / ours,
each from this run's medians.

    OMP_NUM_THREADS=1 python benchmarks/bench_estep_cpu.py                        # K = 4, 8, 16, 32
    OMP_NUM_THREADS=1 python benchmarks/bench_estep_cpu.py --ks 4,5,6,7,8,12,16,24,32 --reps 3
    OMP_NUM_THREADS=1 python benchmarks/bench_estep_cpu.py --no-naive --reps 15   # the floor and ours only

Only the public ``forward_backward`` is called, so the same script times another version of the package (put it
first on ``PYTHONPATH``).
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench_forward_backward import baseline_log_likelihood, make_inputs  # noqa: E402
from torchrl_options import forward_backward  # noqa: E402
from torchrl_options.inference.forward_backward import resolve_backend  # noqa: E402


def _streaming_passes():
    """Compiled streaming passes reading four arrays and writing three or seven (NumPy loops as a fallback)."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is the fast extra

        def read4_write3(a, b, c, d, o1, o2, o3):
            np.add(a, b, out=o1)
            np.add(c, d, out=o2)
            np.add(a, d, out=o3)

        def read4_write7(a, b, c, d, o1, o2, o3, o4, o5, o6, o7):
            read4_write3(a, b, c, d, o1, o2, o3)
            np.add(b, c, out=o4)
            np.subtract(a, b, out=o5)
            np.subtract(c, d, out=o6)
            np.subtract(a, d, out=o7)

        return read4_write3, read4_write7, "NumPy ufuncs (reads some inputs twice)"

    @numba.njit(nogil=True, fastmath=True)
    def read4_write3(a, b, c, d, o1, o2, o3):
        for i in range(a.shape[0]):
            x, y, z, t = a[i], b[i], c[i], d[i]
            o1[i] = x + y
            o2[i] = z + t
            o3[i] = x + t

    @numba.njit(nogil=True, fastmath=True)
    def read4_write7(a, b, c, d, o1, o2, o3, o4, o5, o6, o7):
        for i in range(a.shape[0]):
            x, y, z, t = a[i], b[i], c[i], d[i]
            o1[i] = x + y
            o2[i] = z + t
            o3[i] = x + t
            o4[i] = y + z
            o5[i] = x - y
            o6[i] = z - t
            o7[i] = x - t

    return read4_write3, read4_write7, "one compiled loop (Numba)"


def contenders(B, T, K, naive: bool):
    xs = make_inputs(B, T, K, torch.device("cpu"))
    flat = [x.detach().reshape(-1).numpy() for x in xs]
    outs = [np.empty_like(flat[0]) for _ in range(7)]
    pass3, pass7, _ = _streaming_passes()

    def floor7():
        pass3(*flat, *outs[:3])

    def floor11():
        pass7(*flat, *outs)

    def marginals():
        with torch.no_grad():
            forward_backward(*xs, validate=False)

    def fwd_grad():
        ll = forward_backward(*xs, validate=False).log_likelihood
        torch.autograd.grad(ll.sum(), xs)

    def user():
        for x in xs:
            x.grad = None
        forward_backward(*xs).log_likelihood.sum().backward()

    def naive_loop():
        torch.autograd.grad(baseline_log_likelihood(*xs).sum(), xs)

    out = {"floor 7": floor7, "floor 11": floor11, "marginals": marginals, "fwd+grad": fwd_grad, "as a user": user}
    if naive:
        out["naive"] = naive_loop
    return out, xs


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ks", default="4,8,16,32", help="comma-separated numbers of options K")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--reps", type=int, default=5, help="interleaved rounds after the warm-up")
    p.add_argument("--no-naive", action="store_true", help="skip the naive loop (seconds per call at K = 32)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    B, T = args.batch, args.steps
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; command: python {' '.join(sys.argv)}")
    print(f"torch={torch.__version__} threads={torch.get_num_threads()} OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}; floor pass: {_streaming_passes()[2]}")  # fmt: skip
    rows = []
    for K in [int(k) for k in args.ks.split(",")]:
        fns, xs = contenders(B, T, K, not args.no_naive)
        for f in fns.values():  # warm-up (and compilation)
            f()
        wall = {n: [] for n in fns}
        cpu = {n: [] for n in fns}
        load0 = os.getloadavg()[0]
        rng = random.Random(K)
        for _ in range(args.reps):
            order = list(fns.items())
            rng.shuffle(order)
            for name, f in order:
                t0, c0 = time.perf_counter(), time.process_time()
                f()
                wall[name].append(time.perf_counter() - t0)
                cpu[name].append(time.process_time() - c0)
        med_w = {n: statistics.median(v) * 1e3 for n, v in wall.items()}
        med_c = {n: statistics.median(v) * 1e3 for n, v in cpu.items()}
        rows.append((K, med_w, med_c, resolve_backend("auto", xs[0]), (load0, os.getloadavg()[0])))
        print_row(B, T, K, med_w, med_c, rows[-1][3], rows[-1][4])


def print_row(B, T, K, w, c, backend, loads):
    mb7 = 7 * B * T * K * 4 / 1e6
    print(f"\n(B, T, K) = ({B}, {T}, {K}); backend auto -> {backend}; load average {loads[0]:.1f} -> {loads[1]:.1f}; "
          f"floor 7 = {mb7:.1f} MB moved, floor 11 = {mb7 * 11 / 7:.1f} MB")  # fmt: skip
    print(f"  {'':<12} {'wall [ms]':>10} {'CPU [ms]':>10} {'x floor 7':>16} {'x floor 11':>16} {'naive / ours':>16}")
    for name in w:
        cells = [f"{w[name]:10.2f}", f"{c[name]:10.2f}"]
        for ref in ("floor 7", "floor 11"):
            cells.append(f"{w[name] / w[ref]:7.2f} / {c[name] / c[ref]:5.2f}" if name not in ("floor 7", "floor 11")
                         else f"{'':>15}")  # fmt: skip
        if "naive" in w and name not in ("naive", "floor 7", "floor 11"):
            cells.append(f"{w['naive'] / w[name]:7.1f} / {c['naive'] / c[name]:5.1f}")
        print(f"  {name:<12} " + " ".join(f"{x:>16}" if i >= 2 else x for i, x in enumerate(cells)))
    print("  (ratios: wall / CPU)")


if __name__ == "__main__":
    main()
