"""Benchmark of the DDO E-step: forward pass + gradient (= the marginals) of ``forward_backward``.

Compares, in one run and on the same inputs:

* ``naive``: the straightforward batched log-space loop that builds the [B, K, K] log-transition matrix and takes a
  logsumexp per step; the marginals come from autograd (``torch.autograd.grad`` of the log-likelihood);
* ``reference``: ``forward_backward(..., backend="reference")``, the one-step-at-a-time O(K) recursion;
* ``chunked``: the time-parallel CPU path; ``triton``: the fused GPU kernel (CUDA only); ``auto``: the default.

Prints time (best of ``--repeats`` after a warm-up call, whose time is reported separately as ``first``),
throughput in B*T*K cells per second, and the ratio of the naive time to each. On CUDA it also prints the
memory-bandwidth floor: reading the four inputs and writing u, v, w once, at the bandwidth of a device copy.

    python benchmarks/bench_forward_backward.py                    # CPU: (64,1000,8) and (64,1000,32)
    python benchmarks/bench_forward_backward.py --device cuda      # adds (4096,1000,16)
    python benchmarks/bench_forward_backward.py --shapes 16,200,4 --repeats 5 --threads 1
"""
from __future__ import annotations

import argparse
import time

import torch

from torchrl_options.inference.forward_backward import forward_backward, resolve_backend


def naive_log_likelihood(log_pi, log_term, log_cont, log_eta):
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


def run_once(name, xs):
    if name == "naive":
        ll = naive_log_likelihood(*xs)
    else:
        ll = forward_backward(*xs, backend=name, validate=False).log_likelihood
    return torch.autograd.grad(ll.sum(), xs)


def time_it(name, xs, repeats, device):
    sync(device)
    t0 = time.perf_counter()
    run_once(name, xs)
    sync(device)
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        run_once(name, xs)
        sync(device)
        best = min(best, time.perf_counter() - t0)
    return first, best


def copy_bandwidth(device, nbytes=2**30):
    x = torch.empty(nbytes // 4, device=device)
    y = torch.empty_like(x)
    y.copy_(x)
    sync(device)
    t0 = time.perf_counter()
    for _ in range(5):
        y.copy_(x)
    sync(device)
    return 2 * nbytes * 5 / (time.perf_counter() - t0)  # bytes read + written per second


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--shapes", default=None, help="semicolon-separated B,T,K (default: the issue's shapes)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--naive-repeats", type=int, default=1, help="repeats of the (slow) naive baseline")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (CPU)")
    p.add_argument("--backends", default="naive,reference,chunked,triton,auto")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.shapes:
        shapes = [tuple(int(v) for v in s.split(",")) for s in args.shapes.split(";")]
    else:
        shapes = [(64, 1000, 8), (64, 1000, 32)] + ([(4096, 1000, 16)] if device.type == "cuda" else [])
    backends = args.backends.split(",")
    if device.type != "cuda":
        backends = [b for b in backends if b != "triton"]
    print(f"device={device} threads={torch.get_num_threads()} torch={torch.__version__}")
    if device.type == "cuda":
        print(f"gpu={torch.cuda.get_device_name(device)}")
        bw = copy_bandwidth(device)
        print(f"device copy bandwidth: {bw / 1e9:.0f} GB/s")
    header = f"{'B':>5} {'T':>6} {'K':>4}  {'backend':<18} {'first [s]':>10} {'time [s]':>10} {'Mcells/s':>10} {'vs naive':>9}"
    print(header)
    print("-" * len(header))
    for B, T, K in shapes:
        xs = make_inputs(B, T, K, device)
        cells = B * T * K
        naive_time = None
        for name in backends:
            label = f"auto->{resolve_backend('auto', xs[0])}" if name == "auto" else name
            reps = args.naive_repeats if name == "naive" else args.repeats
            first, best = time_it(name, xs, reps, device)
            if name == "naive":
                naive_time = best
            ratio = f"{naive_time / best:8.1f}x" if naive_time else f"{'-':>9}"
            print(f"{B:>5} {T:>6} {K:>4}  {label:<18} {first:>10.4f} {best:>10.4f} {cells / best / 1e6:>10.1f} {ratio}")
        if device.type == "cuda":
            nbytes = 7 * cells * xs[0].element_size()
            floor = nbytes / bw
            print(f"{'':>18}memory floor: {nbytes / 1e9:.2f} GB (4 inputs read, u/v/w written) / {bw / 1e9:.0f} GB/s "
                  f"= {floor * 1e3:.2f} ms; 10x floor = {10 * floor * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
