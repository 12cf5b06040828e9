"""Benchmark of the DDO E-step: forward pass + gradient of ``forward_backward`` against a careful batched baseline.

What is timed, on the same float32 inputs (full-length rows, non-terminal):

* ``baseline``: the batched log-space loop that builds the ``[B, K, K]`` log-transition matrix at every step
  (``log pi_h + log(psi_h eta_h' + (1 - psi_h) [h = h'])``) and takes a ``logsumexp`` over the previous option,
  then ``torch.autograd.grad`` of the summed log-likelihood with respect to ``log_pi`` (which is the marginals u);
* each backend of ``forward_backward(..., validate=False, backend=...)`` (``reference``, ``chunked``, ``numba``,
  ``triton`` on CUDA, and ``auto``): the forward pass and ``torch.autograd.grad`` with respect to all four inputs.

Method: per thread count, per shape, one warm-up call of each (its time is printed as ``first``), then ``--reps``
rounds in each of which every contender runs once, in turn (interleaved, so that load from other processes hits all
of them alike); the table gives the median wall time of the rounds, ``baseline / backend`` of the medians, and the
median process CPU time (all threads; on a loaded machine, with one thread, the closer figure to an idle machine's
wall time, since time spent waiting for a core is not counted). The memory floor
is the time to read the four inputs and write u, v, w once (``7 B T K`` elements) at the bandwidth of a large
``copy_`` measured with the same thread count; ``x floor`` is the backend's median over that.

    python benchmarks/bench_forward_backward.py                       # CPU, 1 and 2 threads, the issue's shapes
    python benchmarks/bench_forward_backward.py --threads 1 --shapes "64,1000,8;16,100,4"
    python benchmarks/bench_forward_backward.py --compile-time        # also Numba's first-call time, cold and cached
    python benchmarks/bench_forward_backward.py --breakdown           # where the numba backend's time goes
    git show OLD:torchrl_options/inference/_numba_kernels.py > /tmp/old_kernels.py   # another version's kernels,
    python benchmarks/bench_forward_backward.py --breakdown --backends numba@/tmp/old_kernels.py  # interleaved
    python benchmarks/bench_forward_backward.py --device cuda         # adds (4096, 1000, 16) and the Triton kernel
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # spinning OpenMP waits distort timings on a shared machine

import torch  # noqa: E402

from torchrl_options.inference.forward_backward import (  # noqa: E402
    forward_backward,
    numba_available,
    resolve_backend,
    triton_available,
)


def baseline_log_likelihood(log_pi, log_term, log_cont, log_eta):
    """The baseline: a batched log-space loop over the full [B, K, K] transition matrix (full-length rows)."""
    B, T, K = log_pi.shape
    log_eye = torch.eye(K, dtype=log_pi.dtype, device=log_pi.device).log()  # 0 on the diagonal, -inf elsewhere
    a = log_eta[:, 0]
    for t in range(T - 1):
        # log M[b, h, h'] = log pi_h + log(psi_h eta_h' + (1 - psi_h) [h = h'])
        switch = (log_pi[:, t] + log_term[:, t]).unsqueeze(-1) + log_eta[:, t + 1].unsqueeze(1)
        stay = (log_pi[:, t] + log_cont[:, t]).unsqueeze(-1) + log_eye
        log_m = torch.stack([switch, stay]).logsumexp(0)
        a = (a.unsqueeze(-1) + log_m).logsumexp(1)
    return (a + log_pi[:, T - 1]).logsumexp(-1)


def make_inputs(B, T, K, device, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    log_pi = (2.0 * torch.randn(B, T, K, generator=g, dtype=dtype)).log_softmax(-1)
    logits = torch.randn(B, T, K, generator=g, dtype=dtype)
    log_term = torch.nn.functional.logsigmoid(logits - 2.0)
    log_cont = torch.nn.functional.logsigmoid(2.0 - logits)
    log_eta = torch.randn(B, T, K, generator=g, dtype=dtype).log_softmax(-1)
    return [x.to(device).requires_grad_() for x in (log_pi, log_term, log_cont, log_eta)]


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


_OTHER_KERNELS = {}


def other_kernels(path):
    """The Numba kernels module of another version of the package, loaded from ``path`` (a copy of
    ``torchrl_options/inference/_numba_kernels.py``, e.g. ``git show OLD:torchrl_options/inference/_numba_kernels.py
    > /tmp/old_kernels.py``), for the ``numba@PATH`` contenders."""
    if path not in _OTHER_KERNELS:
        import importlib.util

        name = "_bench_kernels_" + "".join(c if c.isalnum() else "_" for c in os.path.abspath(path))
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # Numba's cache finds the module by name
        spec.loader.exec_module(module)
        _OTHER_KERNELS[path] = module
    return _OTHER_KERNELS[path]


def run_once(name, xs):
    if name == "baseline":
        ll = baseline_log_likelihood(*xs)
        return torch.autograd.grad(ll.sum(), xs[0])
    if name.startswith("numba@"):  # the numba backend with another version's kernels (same Python around them)
        from torchrl_options.inference import _numba_fb as nf

        kept = nf._kernels()
        nf._KERNELS = other_kernels(name[len("numba@"):])
        try:
            ll = forward_backward(*xs, backend="numba", validate=False).log_likelihood
            return torch.autograd.grad(ll.sum(), xs)
        finally:
            nf._KERNELS = kept
    ll = forward_backward(*xs, backend=name, validate=False).log_likelihood
    return torch.autograd.grad(ll.sum(), xs)


def timed(name, xs, device):
    """(wall, process CPU) seconds of one call."""
    sync(device)
    t0, c0 = time.perf_counter(), time.process_time()
    run_once(name, xs)
    sync(device)
    return time.perf_counter() - t0, time.process_time() - c0


def copy_bandwidth(device, nbytes=2**28):
    """Bytes read + written per second by a large ``copy_`` (best of 5), with the current thread count."""
    x = torch.ones(nbytes // 4, device=device)
    y = torch.empty_like(x)
    y.copy_(x)
    best = float("inf")
    for _ in range(5):
        sync(device)
        t0 = time.perf_counter()
        y.copy_(x)
        sync(device)
        best = min(best, time.perf_counter() - t0)
    return 2 * nbytes / best


def load() -> str:
    try:
        return "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:  # pragma: no cover
        return "load average unavailable"


_FIRST_CALL = """
import time, torch
t0 = time.perf_counter()
from torchrl_options import forward_backward
t1 = time.perf_counter()
x = torch.randn(2, 8, 3).log_softmax(-1)
for dtype in (torch.float32, torch.float64):
    xs = [x.to(dtype).requires_grad_() for _ in range(4)]
    out = forward_backward(*xs, backend="numba")
    out.log_likelihood.sum().backward()
print(f"{t1 - t0:.2f} {time.perf_counter() - t1:.2f}")
"""


def numba_first_call_times() -> tuple[str, str]:
    """Seconds for a fresh process's first ``backend="numba"`` calls (forward + gradient, float32 and float64),
    with an empty Numba cache (compilation) and then with the cache it left (loading)."""
    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for _ in range(2):
            res = subprocess.run([sys.executable, "-c", _FIRST_CALL], env=env, capture_output=True, text=True)
            if res.returncode:
                raise RuntimeError(res.stderr)
            out.append(res.stdout.split()[1])
    return out[0], out[1]


def numba_breakdown(B, T, K, reps, others=()):
    """Median process CPU times [ms] of the numba backend's parts at (B, T, K), float32, 1 thread, interleaved:
    the float32 kernel alone (what float32 inputs run; outputs allocated once) writing the marginals and the
    gradients or the marginals only, the float64 kernel alone (what takes the rows the float32 one cannot certify,
    and float64 inputs; outputs allocated once), the same with its outputs allocated per call, ``numba_forward_backward`` (the Python preparation around the kernel), ``forward_backward`` without
    autograd, the gradient kernel alone, ``numba_expectation_gradient`` (its outputs allocated per call), and
    forward + ``torch.autograd.grad`` with respect to all four inputs (what the main table times); for each path
    in ``others`` (another version's kernels, see :func:`other_kernels`) its forward-backward kernel alone and its
    forward + ``torch.autograd.grad``, interleaved with the rest."""
    import numpy as np

    from torchrl_options.inference import _numba_fb as nf

    k = nf._kernels()
    xs = make_inputs(B, T, K, torch.device("cpu"))
    d = [x.detach() for x in xs]
    mask = torch.ones(B, T, dtype=torch.bool)
    term = torch.zeros(B, dtype=torch.bool)
    nps = [x.numpy() for x in d]
    lengths = np.full(B, T, np.int64)
    termn = np.zeros(B, dtype=bool)
    floors = (nf._FLOOR, nf._Z_FLOOR, nf._S_FLOOR)
    ll, u, v, w, bad = nf.numba_forward_backward(*d, mask, term)
    g = torch.ones(B)
    kept = [np.empty((B, T, K), np.float32) for _ in range(4)]

    def kernel():
        k.fb_rows(*nps, lengths, termn, ll.double().numpy(), u.numpy(), v.numpy(), w.numpy(), bad.numpy(), *floors, 0, B)

    def kernel_alloc():
        outs = [torch.empty(B, T, K) for _ in range(3)]
        k.fb_rows(*nps, lengths, termn, np.empty(B), *(o.numpy() for o in outs), np.zeros(B, bool), *floors, 0, B)

    tiny = np.float32(nf._tiny32(K))
    flat = [x.reshape(B, T * K).numpy() for x in d]
    kept32 = [np.empty((B, T * K), np.float32) for _ in range(7)]
    st32 = np.zeros(B, np.int8)

    def kernel32(grads):
        k.fb32_rows(*flat, T, K, lengths, termn, np.empty(B), *kept32, grads, st32, tiny, k.EXP_CONSTANTS, 0, B)

    def grad_kernel():
        k.grad_rows(g.numpy(), u.numpy(), v.numpy(), w.numpy(), lengths, termn, *kept, 0, B)

    def full():
        out = forward_backward(*xs, validate=False, backend="numba")
        torch.autograd.grad(out.log_likelihood.sum(), xs)

    def no_grad():
        with torch.no_grad():
            forward_backward(*d, validate=False, backend="numba")

    parts = {
        "float32 kernel, gradients (outputs kept)": lambda: kernel32(True),
        "float32 kernel, marginals only": lambda: kernel32(False),
        "fb kernel (outputs kept)": kernel,
        "fb kernel (outputs allocated)": kernel_alloc,
        "numba_forward_backward": lambda: nf.numba_forward_backward(*d, mask, term),
        "forward_backward, no autograd": no_grad,
        "gradient kernel (outputs kept)": grad_kernel,
        "numba_expectation_gradient": lambda: nf.numba_expectation_gradient(g, u, v, w, mask, term),
        "forward + autograd.grad": full,
    }
    for path in others:
        mod, tag = other_kernels(path), os.path.basename(path)

        def other_kernel(mod=mod):
            mod.fb_rows(*nps, lengths, termn, ll.double().numpy(), u.numpy(), v.numpy(), w.numpy(), bad.numpy(),
                        *floors, 0, B)  # fmt: skip

        parts[f"fb kernel (outputs kept), {tag}"] = other_kernel
        parts[f"forward + autograd.grad, {tag}"] = lambda path=path: run_once("numba@" + path, xs)
    times = {name: [] for name in parts}
    for f in parts.values():
        f()
    for _ in range(reps):
        for name, f in parts.items():
            c0 = time.process_time()
            f()
            times[name].append(time.process_time() - c0)
    return {name: statistics.median(t) * 1e3 for name, t in times.items()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--shapes", default=None, help="semicolon-separated B,T,K (default: the issue's shapes)")
    p.add_argument("--reps", type=int, default=5, help="interleaved rounds after the warm-up")
    p.add_argument("--threads", default="1,2", help="comma-separated thread counts (torch.set_num_threads)")
    p.add_argument("--backends", default=None, help="default: baseline and every backend that can run, and auto; "
                   "numba@FILE: the numba backend with the kernels of FILE (another version's _numba_kernels.py)")
    p.add_argument("--compile-time", action="store_true", help="also time Numba's first call in a fresh process")
    p.add_argument("--breakdown", action="store_true", help="only the numba backend's parts (1 thread, CPU time)")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    if args.shapes:
        shapes = [tuple(int(v) for v in s.split(",")) for s in args.shapes.split(";")]
    else:
        shapes = [(64, 1000, 8), (64, 1000, 32)] + ([(4096, 1000, 16)] if device.type == "cuda" else [])
    if args.backends:
        backends = args.backends.split(",")
    else:
        backends = ["baseline", "reference", "chunked"]
        backends += ["numba"] if device.type == "cpu" and numba_available() else []
        backends += ["triton"] if device.type == "cuda" and triton_available(device) else []
        backends += ["auto"]
    print(f"device={device} torch={torch.__version__} numba={'yes' if numba_available() else 'no'}; {load()}")
    if device.type == "cuda":
        print(f"gpu={torch.cuda.get_device_name(device)}")
    if args.compile_time and numba_available():
        cold, warm = numba_first_call_times()
        print(f"numba first call (fresh process, forward + gradient, float32 and float64): {cold} s with an empty "
              f"cache (compilation), {warm} s with the cache (loading)")  # fmt: skip
    if args.breakdown:
        torch.set_num_threads(1)
        bw = copy_bandwidth(device)
        print(f"numba backend, parts: median process CPU time of {args.reps} interleaved rounds, 1 thread; copy "
              f"bandwidth {bw / 1e9:.1f} GB/s")  # fmt: skip
        for B, T, K in shapes:
            floor = 7 * B * T * K * 4 / bw
            print(f"\n{B}, {T}, {K} (memory floor {floor * 1e3:.2f} ms); {load()}")
            others = [b[len("numba@"):] for b in (args.backends or "").split(",") if b.startswith("numba@")]
            for name, ms in numba_breakdown(B, T, K, args.reps, others).items():
                print(f"  {name:<42} {ms:8.2f} ms {ms / 1e3 / floor:6.1f}x floor")
        return
    for threads in [int(n) for n in args.threads.split(",")]:
        torch.set_num_threads(threads)
        bw = copy_bandwidth(device)
        print(f"\nthreads={torch.get_num_threads()}; copy bandwidth {bw / 1e9:.1f} GB/s; {load()}")
        header = (f"{'B':>5} {'T':>6} {'K':>4}  {'backend':<16} {'first [ms]':>10} {'median [ms]':>11} "
                  f"{'vs baseline':>11} {'x floor':>8} {'CPU [ms]':>9}")  # fmt: skip
        print(header)
        print("-" * len(header))
        for B, T, K in shapes:
            xs = make_inputs(B, T, K, device)
            floor = 7 * B * T * K * xs[0].element_size() / bw
            first = {name: timed(name, xs, device)[0] for name in backends}
            times = {name: [] for name in backends}
            for _ in range(args.reps):
                for name in backends:
                    times[name].append(timed(name, xs, device))
            med = {name: statistics.median(t[0] for t in ts) for name, ts in times.items()}
            cpu = {name: statistics.median(t[1] for t in ts) for name, ts in times.items()}
            base = med.get("baseline")
            for name in backends:
                label = f"auto->{resolve_backend('auto', xs[0])}" if name == "auto" else name
                label = "numba@" + os.path.basename(name[6:]) if name.startswith("numba@") else label
                ratio = f"{base / med[name]:10.1f}x" if base else f"{'-':>11}"
                print(f"{B:>5} {T:>6} {K:>4}  {label:<16} {first[name] * 1e3:>10.1f} {med[name] * 1e3:>11.2f} "
                      f"{ratio} {med[name] / floor:>7.1f}x {cpu[name] * 1e3:>9.2f}")  # fmt: skip
            print(f"{'':>18}memory floor: {7 * B * T * K * xs[0].element_size() / 1e6:.1f} MB (4 inputs read, u, v, w "
                  f"written) / {bw / 1e9:.1f} GB/s = {floor * 1e3:.2f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
