"""Checks and times the fused Triton forward-backward kernel on a CUDA GPU, over launch shapes, in one run.

For each shape: correctness of ``forward_backward(..., backend="triton")`` against the float64 reference on fresh
random inputs with ragged masks, terminal and non-terminal rows and impossible actions (relative error of the
log-likelihood and of u, v, w), with the allocator's free memory poisoned with NaN before the call so that an
unwritten output cannot pass; then the kernel's median time (``triton.testing.do_bench``) for each
``(block_b, num_warps)`` launch shape, and the time of the whole ``forward_backward`` forward + gradient.

The memory floor: the fewest bytes (the four inputs read once, u, v, w written once) over the bandwidth of a
large device-to-device copy measured in the same run. The kernel itself moves more: it reads the inputs in both
passes and writes then reads the forward messages, 13 tensors of B*T*K instead of 7.

    python benchmarks/bench_triton_fb.py                              # (4096, 1000, 16) and (64, 1000, 8)
    python benchmarks/bench_triton_fb.py --shapes "4096,1000,16" --variants "4,1;8,1;8,2"
"""
from __future__ import annotations

import argparse

import torch


def make_case(B, T, K, seed, device):
    """Random log-probabilities with ragged lengths, mixed terminal rows and some impossible actions."""
    g = torch.Generator().manual_seed(seed)
    log_pi = (3.0 * torch.randn(B, T, K, generator=g, dtype=torch.float64)).log_softmax(-1)
    kill = torch.rand(B, T, K, generator=g) < 0.1
    kill[..., 0] &= ~kill[..., 1:].all(-1)  # every step keeps at least one possible option
    log_pi = log_pi.masked_fill(kill, float("-inf"))
    logits = 2.0 * torch.randn(B, T, K, generator=g, dtype=torch.float64)
    log_term = torch.nn.functional.logsigmoid(logits - 1.0)
    log_cont = torch.nn.functional.logsigmoid(1.0 - logits)
    log_eta = torch.randn(B, T, K, generator=g, dtype=torch.float64).log_softmax(-1)
    lengths = torch.randint(1, T + 1, (B,), generator=g)
    lengths[0] = T
    mask = torch.arange(T).unsqueeze(0) < lengths.unsqueeze(1)
    terminal = torch.rand(B, generator=g) < 0.5
    xs = tuple(x.to(device) for x in (log_pi, log_term, log_cont, log_eta))
    return xs, mask.to(device), terminal.to(device)


def poison(device, nbytes):
    """Fill free memory of the caching allocator with NaN, so that reused blocks hold NaN, not stale results."""
    x = torch.full((nbytes // 4,), float("nan"), device=device)
    del x


def rel_err(out, ref):
    out, ref = out.double(), ref.double()
    finite = torch.isfinite(ref)
    if not torch.equal(finite, torch.isfinite(out)):
        return float("inf")
    num = (out[finite] - ref[finite]).norm()
    den = ref[finite].norm().clamp_min(1e-30)
    return (num / den).item()


def copy_bandwidth(device, nbytes=2**30):
    import triton.testing

    x = torch.randn(nbytes // 4, device=device)
    y = torch.empty_like(x)
    ms = triton.testing.do_bench(lambda: y.copy_(x), warmup=50, rep=300, return_mode="median")
    return 2 * nbytes / (ms * 1e-3)


def main(argv=None):
    import triton.testing

    from torchrl_options.inference._triton_fb import triton_forward_backward
    from torchrl_options.inference.forward_backward import forward_backward

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shapes", default="4096,1000,16;64,1000,8")
    p.add_argument("--variants", default="1,1;2,1;4,1;8,1;16,1;4,2;8,2;16,2;16,4;32,4",
                   help="semicolon-separated block_b,num_warps")
    p.add_argument("--checks", type=int, default=2, help="fresh random cases checked per shape")
    p.add_argument("--profile", action="store_true", help="print the CUDA kernels of forward + gradient")
    args = p.parse_args(argv)
    device = torch.device("cuda")
    print(f"gpu={torch.cuda.get_device_name(device)} torch={torch.__version__} triton={triton.__version__}")
    bw = copy_bandwidth(device)
    print(f"device copy bandwidth (read + write): {bw / 1e9:.0f} GB/s")
    rows = []
    for shape in args.shapes.split(";"):
        B, T, K = (int(v) for v in shape.split(","))
        cells = B * T * K
        # ---- correctness, float32 against the float64 reference, fresh inputs each time
        for c in range(args.checks):
            xs64, mask, terminal = make_case(B, T, K, seed=100 + c, device=device)
            ref = forward_backward(*xs64, mask=mask, terminal=terminal, backend="reference", validate=False)
            xs32 = tuple(x.float() for x in xs64)
            poison(device, 16 * cells * 4)
            out = forward_backward(*xs32, mask=mask, terminal=terminal, backend="triton")
            torch.cuda.synchronize()
            errs = [rel_err(o, r) for o, r in zip((out.log_likelihood, out.u, out.v, out.w),
                                                 (ref.log_likelihood, ref.u, ref.v, ref.w))]
            written = all(torch.isfinite(o).all().item() for o in (out.u, out.v, out.w))
            ok = written and max(errs) < 1e-5
            print(f"check B={B} T={T} K={K} case {c}: rel err ll {errs[0]:.1e} u {errs[1]:.1e} v {errs[2]:.1e} "
                  f"w {errs[3]:.1e}, all written {written}: {'OK' if ok else 'FAIL'}")
            del xs64, ref, out
        # ---- timing on full-length random rows (no padding: every step does work)
        g = torch.Generator(device=device).manual_seed(0)
        log_pi = (2.0 * torch.randn(B, T, K, device=device, generator=g)).log_softmax(-1)
        logits = torch.randn(B, T, K, device=device, generator=g)
        xs = (log_pi, torch.nn.functional.logsigmoid(logits - 2.0), torch.nn.functional.logsigmoid(2.0 - logits),
              torch.randn(B, T, K, device=device, generator=g).log_softmax(-1))
        mask = torch.ones(B, T, dtype=torch.bool, device=device)
        terminal = torch.ones(B, dtype=torch.bool, device=device)
        floor = 7 * cells * 4 / bw
        kernel_bytes = 13 * cells * 4
        for v in ["default"] + args.variants.split(";"):
            bb, nw = (None, None) if v == "default" else (int(x) for x in v.split(","))
            try:
                ms = triton.testing.do_bench(
                    lambda: triton_forward_backward(*xs, mask, terminal, block_b=bb, num_warps=nw),
                    warmup=25, rep=200, return_mode="median")
            except Exception as err:  # a launch shape the compiler refuses
                print(f"variant block_b={bb} num_warps={nw}: failed ({type(err).__name__}: {err})")
                continue
            name = "kernel, default launch" if bb is None else f"kernel b{bb} w{nw}"
            rows.append((B, T, K, name, ms, floor, kernel_bytes / (ms * 1e-3) / 1e9))
        ms = triton.testing.do_bench(
            lambda: forward_backward(*xs, mask=mask, terminal=terminal, backend="triton", validate=False),
            warmup=25, rep=200, return_mode="median")
        rows.append((B, T, K, "forward_backward", ms, floor, kernel_bytes / (ms * 1e-3) / 1e9))
        xg = [x.clone().requires_grad_() for x in xs]

        def full():
            ll = forward_backward(*xg, mask=mask, terminal=terminal, backend="triton", validate=False).log_likelihood
            return torch.autograd.grad(ll.sum(), xg)

        ms = triton.testing.do_bench(full, warmup=25, rep=200, return_mode="median")
        rows.append((B, T, K, "forward_backward+grad", ms, floor, (kernel_bytes + 7 * cells * 4) / (ms * 1e-3) / 1e9))
        if args.profile:
            from torch.profiler import profile, ProfilerActivity

            with profile(activities=[ProfilerActivity.CUDA]) as prof:
                for _ in range(3):
                    full()
                torch.cuda.synchronize()
            print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=12))
        del xs, xg
    print()
    print(f"{'B':>5} {'T':>5} {'K':>3}  {'what':<22} {'median ms':>10} {'floor ms':>9} {'x floor':>8} {'GB/s moved':>11}")
    for B, T, K, what, ms, floor, gbs in rows:
        print(f"{B:>5} {T:>5} {K:>3}  {what:<22} {ms:>10.3f} {floor * 1e3:>9.3f} {ms / (floor * 1e3):>8.1f} {gbs:>11.0f}")


if __name__ == "__main__":
    main()
