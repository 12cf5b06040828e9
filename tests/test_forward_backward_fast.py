"""The fast E-step backends ("chunked", "numba", "triton") against the reference forward-backward."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest
import torch

import torchrl_options.inference._chunked as chunked_mod
import torchrl_options.inference._numba_fb as numba_mod
from torchrl_options.inference.forward_backward import (
    _forward_backward_reference,
    forward_backward,
    numba_available,
    resolve_backend,
)

HAS_TRITON = importlib.util.find_spec("triton") is not None
HAS_CUDA = torch.cuda.is_available()
HAS_NUMBA = numba_available()
# the module (the package's attribute of that name is the function)
fb_mod = importlib.import_module("torchrl_options.inference.forward_backward")
needs_numba = pytest.mark.skipif(not HAS_NUMBA, reason="numba is not installed")


def make_case(B, T, K, dtype=torch.float32, *, pad=True, ninf=0.0, sharp=1.0, seed=0, device="cpu"):
    """Random inputs: softmax policies (``sharp`` scales the logits), sigmoid terminations, softmax meta-control,
    a fraction ``ninf`` of -inf policy entries (never all of a step's), random prefix masks and terminal rows."""
    g = torch.Generator().manual_seed(seed)
    log_pi = (sharp * torch.randn(B, T, K, generator=g, dtype=dtype)).log_softmax(-1)
    if ninf:
        kill = torch.rand(B, T, K, generator=g) < ninf
        kill[..., 0] &= ~kill[..., 1:].all(-1)
        log_pi = log_pi.masked_fill(kill, float("-inf"))
    logits = sharp * torch.randn(B, T, K, generator=g, dtype=dtype)
    log_term, log_cont = torch.nn.functional.logsigmoid(logits), torch.nn.functional.logsigmoid(-logits)
    log_eta = torch.randn(B, T, K, generator=g, dtype=dtype).log_softmax(-1)
    mask = None
    if pad:
        lengths = torch.randint(1, T + 1, (B,), generator=g)
        lengths[0] = T
        mask = torch.arange(T) < lengths[:, None]
        # padding may hold anything, NaN included
        log_pi = log_pi.masked_fill(~mask[..., None], float("nan"))
    terminal = torch.rand(B, generator=g) < 0.5
    xs = tuple(x.to(device) for x in (log_pi, log_term, log_cont, log_eta))
    return xs, (None if mask is None else mask.to(device)), terminal.to(device)


def assert_close_outputs(ref, out, dtype):
    rtol = 1e-5 if dtype == torch.float32 else 1e-10
    atol = 2e-6 if dtype == torch.float32 else 1e-12
    ll_ref = ref.log_likelihood
    rel = ((out.log_likelihood - ll_ref).abs() / ll_ref.abs().clamp_min(1.0)).max().item()
    assert rel < rtol, rel
    for name in ("u", "v", "w"):
        a, b = getattr(ref, name), getattr(out, name)
        assert a.shape == b.shape and a.dtype == b.dtype
        assert torch.allclose(a, b, rtol=rtol, atol=atol), (name, (a - b).abs().max().item())


def weighted_gradients(xs, mask, terminal, weights, backend):
    """The gradients of ``sum(weights * log P)`` with respect to the four inputs, and the backend's output."""
    leaves = [x.clone().requires_grad_() for x in xs]
    out = forward_backward(*leaves, mask=mask, terminal=terminal, backend=backend)
    (out.log_likelihood * weights).sum().backward()
    return [x.grad for x in leaves], out


CASES = [
    # B, T, K, dtype, pad, ninf, sharp
    (5, 37, 3, torch.float64, True, 0.2, 1.0),
    (5, 37, 3, torch.float32, True, 0.2, 1.0),
    (7, 100, 8, torch.float32, True, 0.0, 3.0),
    (6, 257, 5, torch.float64, True, 0.3, 5.0),
    (4, 64, 16, torch.float32, False, 0.1, 1.0),
    (3, 1, 4, torch.float64, False, 0.0, 1.0),
    (4, 2, 2, torch.float32, True, 0.0, 1.0),
    (2, 50, 1, torch.float64, True, 0.0, 1.0),
]


@pytest.mark.parametrize("B,T,K,dtype,pad,ninf,sharp", CASES)
def test_chunked_matches_reference(B, T, K, dtype, pad, ninf, sharp):
    xs, mask, terminal = make_case(B, T, K, dtype, pad=pad, ninf=ninf, sharp=sharp, seed=T * K)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="chunked")
    assert_close_outputs(ref, out, dtype)


@pytest.mark.parametrize("L", [1, 2, 3, 7, 40, 41])
def test_chunked_any_chunk_length(L):
    xs, mask, terminal = make_case(4, 41, 4, torch.float64, ninf=0.2, seed=L)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    m, t = mask, terminal
    zs = tuple(torch.where(m[..., None], x, 0.0) for x in xs)
    ll, u, v, w, bad = chunked_mod.chunked_forward_backward(*zs, m, t, chunk_length=L)
    assert not bad.any()
    torch.testing.assert_close(ll, ref.log_likelihood, rtol=1e-12, atol=1e-10)
    for a, b in ((u, ref.u), (v, ref.v), (w, ref.w)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chunked_gradients_equal_reference(dtype):
    xs, mask, terminal = make_case(6, 120, 4, dtype, ninf=0.1, seed=3)
    weights = torch.rand(6, dtype=dtype)
    grads = {}
    for backend in ("reference", "chunked"):
        grads[backend], out = weighted_gradients(xs, mask, terminal, weights, backend)
        # the gradient is the Expectation-Gradient of the backend's own marginals
        g = weights.view(-1, 1, 1)
        torch.testing.assert_close(grads[backend][0], g * out.u)
        torch.testing.assert_close(grads[backend][2], g * out.w)
        torch.testing.assert_close(grads[backend][3], g * out.v)
    tol = dict(rtol=1e-5, atol=2e-6) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for a, b in zip(grads["reference"], grads["chunked"]):
        torch.testing.assert_close(a, b, **tol)


def test_chunked_fallback_rows_are_recomputed(monkeypatch):
    """Rows whose chunk boundaries fail the check are recomputed by the reference: force every row to fail."""
    xs, mask, terminal = make_case(5, 60, 3, torch.float64, ninf=0.2, seed=11)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    monkeypatch.setattr(chunked_mod, "_CHECK_TOL", {torch.float64: (-1.0, 0.0), torch.float32: (-1.0, 0.0)})
    zs = tuple(torch.where(mask[..., None], x, 0.0) for x in xs)
    *_, bad = chunked_mod.chunked_forward_backward(*zs, mask, terminal)
    assert bad.all()
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="chunked")
    assert_close_outputs(ref, out, torch.float64)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_chunked_extreme_values(dtype):
    """Log-probabilities down to about -2000 (far beyond float64's range once exponentiated) with -inf entries:
    the chunked path (through its checks and, where needed, the fallback) gives the reference's answer in
    float64; in float32, where the reference itself carries the rounding of log values of that size, it is at
    least as close as the reference to the float64 answer."""
    B, T, K = 4, 300, 3
    xs, mask, terminal = make_case(B, T, K, dtype, ninf=0.3, seed=5)
    g = torch.Generator().manual_seed(1)
    log_pi = torch.where(torch.rand(B, T, K, generator=g) < 0.5, xs[0] * 400.0, xs[0])
    xs = (torch.where(torch.isnan(log_pi), 0.0, log_pi),) + xs[1:]
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="chunked")
    if dtype == torch.float64:
        assert_close_outputs(ref, out, dtype)
        return
    truth = forward_backward(*(x.double() for x in xs), mask=mask, terminal=terminal, backend="reference")
    for name in ("u", "v", "w"):
        err_ref = (getattr(ref, name).double() - getattr(truth, name)).abs().max().item()
        err_out = (getattr(out, name).double() - getattr(truth, name)).abs().max().item()
        assert err_out <= max(2 * err_ref, 1e-5), (name, err_out, err_ref)
    rel = ((out.log_likelihood.double() - truth.log_likelihood).abs() / truth.log_likelihood.abs()).max()
    assert rel < 1e-5


def test_chunked_zero_likelihood_names_row():
    xs, mask, terminal = make_case(4, 40, 3, torch.float32, pad=False, seed=2)
    log_pi = xs[0].clone()
    log_pi[2, 17] = float("-inf")
    with pytest.raises(ValueError, match=r"trajectories \[2\] have zero likelihood"):
        forward_backward(log_pi, *xs[1:], backend="chunked")


def test_backend_argument():
    xs, mask, terminal = make_case(2, 20, 3, pad=False)
    with pytest.raises(ValueError, match="backend"):
        forward_backward(*xs, backend="fast")
    assert resolve_backend("auto", xs[0]) == ("numba" if HAS_NUMBA else "chunked")
    assert resolve_backend("auto", xs[0][:, :4]) == ("numba" if HAS_NUMBA else "reference")
    if not (HAS_TRITON and os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")):
        with pytest.raises(ValueError, match="triton"):
            forward_backward(*xs, backend="triton")


def test_chunked_stable_100k_steps_float32():
    """100,000 float32 steps, near-deterministic probabilities and -inf entries: finite, u rows sum to one."""
    B, T, K = 2, 100_000, 4
    g = torch.Generator().manual_seed(0)
    logits = 30.0 * torch.randn(B, T, K, generator=g)
    log_pi = logits.log_softmax(-1)  # near-deterministic: many entries below -50
    kill = torch.rand(B, T, K, generator=g) < 0.25
    kill[..., 0] &= ~kill[..., 1:].all(-1)
    log_pi = log_pi.masked_fill(kill, float("-inf"))
    tl = 20.0 * torch.randn(B, T, K, generator=g) - 5.0
    log_term, log_cont = torch.nn.functional.logsigmoid(tl), torch.nn.functional.logsigmoid(-tl)
    log_eta = (20.0 * torch.randn(B, T, K, generator=g)).log_softmax(-1)
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[1, 77_777:] = False
    xs = (log_pi, log_term, log_cont, log_eta)
    zs = tuple(torch.where(mask[..., None], x, 0.0) for x in xs)
    ll, u, v, w, bad = chunked_mod.chunked_forward_backward(*zs, mask, torch.tensor([True, False]))
    assert not bad.any(), "the chunked path itself must handle this case (no fallback)"
    assert torch.isfinite(ll).all()
    for x in (u, v, w):
        assert torch.isfinite(x).all()
    sums = u.sum(-1)[mask]
    assert (sums - 1).abs().max() < 1e-4
    assert (u.sum(-1)[~mask] == 0).all()
    # and it agrees with the reference on a prefix that the reference can afford
    n = 3000
    ref = forward_backward(*(x[:, :n] for x in xs), terminal=True, backend="reference")
    out = forward_backward(*(x[:, :n] for x in xs), terminal=True, backend="chunked")
    assert_close_outputs(ref, out, torch.float32)


def _zeroed(xs, mask):
    return tuple(torch.where(mask[..., None], x, 0.0) for x in xs)


@needs_numba
@pytest.mark.parametrize("B,T,K,dtype,pad,ninf,sharp", CASES)
def test_numba_matches_reference(B, T, K, dtype, pad, ninf, sharp):
    xs, mask, terminal = make_case(B, T, K, dtype, pad=pad, ninf=ninf, sharp=sharp, seed=T * K)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    assert_close_outputs(ref, out, dtype)
    # the kernel itself, not the fallback, produced these
    m = torch.ones(B, T, dtype=torch.bool) if mask is None else mask
    *_, bad = numba_mod.numba_forward_backward(*_zeroed(xs, m), m, terminal)
    assert not bad.any()


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_gradients_equal_reference(dtype):
    xs, mask, terminal = make_case(6, 120, 4, dtype, ninf=0.1, seed=3)
    weights = torch.rand(6, dtype=dtype)
    grads = {}
    for backend in ("reference", "numba"):
        grads[backend], out = weighted_gradients(xs, mask, terminal, weights, backend)
    # the compiled gradient pass is the Expectation-Gradient of the kernel's own marginals, exactly
    g = weights.view(-1, 1, 1)
    last = mask.sum(1) - 1
    steps = torch.arange(mask.shape[1])
    term_weight = (steps < last[:, None]) | ((steps == last[:, None]) & terminal[:, None])
    exact = dict(rtol=0, atol=0)
    torch.testing.assert_close(grads["numba"][0], g * out.u, **exact)
    torch.testing.assert_close(grads["numba"][1], g * torch.where(term_weight[..., None], out.u - out.w, 0.0), **exact)
    torch.testing.assert_close(grads["numba"][2], g * out.w, **exact)
    torch.testing.assert_close(grads["numba"][3], g * out.v, **exact)
    tol = dict(rtol=1e-5, atol=2e-6) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for a, b in zip(grads["reference"], grads["numba"]):
        torch.testing.assert_close(a, b, **tol)


@needs_numba
def test_numba_flagged_rows_are_recomputed(monkeypatch):
    """Rows the kernel cannot certify are recomputed by the reference: force every row to be flagged."""
    xs, mask, terminal = make_case(5, 60, 3, torch.float64, ninf=0.2, seed=11)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    monkeypatch.setattr(numba_mod, "_FLOOR", 2.0)  # every non-zero message entry is below it
    *_, bad = numba_mod.numba_forward_backward(*_zeroed(xs, mask), mask, terminal)
    assert bad.all()
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    assert_close_outputs(ref, out, torch.float64)


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_numba_extreme_values(dtype):
    """Log-probabilities down to about -2000 with -inf entries: the kernel flags what float64 cannot hold and the
    answer is the reference's (float64), or at least as close as the reference to the float64 answer (float32)."""
    B, T, K = 4, 300, 3
    xs, mask, terminal = make_case(B, T, K, dtype, ninf=0.3, seed=5)
    g = torch.Generator().manual_seed(1)
    log_pi = torch.where(torch.rand(B, T, K, generator=g) < 0.5, xs[0] * 400.0, xs[0])
    xs = (torch.where(torch.isnan(log_pi), 0.0, log_pi),) + xs[1:]
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    if dtype == torch.float64:
        assert_close_outputs(ref, out, dtype)
        return
    truth = forward_backward(*(x.double() for x in xs), mask=mask, terminal=terminal, backend="reference")
    for name in ("u", "v", "w"):
        err_ref = (getattr(ref, name).double() - getattr(truth, name)).abs().max().item()
        err_out = (getattr(out, name).double() - getattr(truth, name)).abs().max().item()
        assert err_out <= max(2 * err_ref, 1e-5), (name, err_out, err_ref)


@needs_numba
def test_numba_zero_likelihood_names_row():
    xs, mask, terminal = make_case(4, 40, 3, torch.float32, pad=False, seed=2)
    log_pi = xs[0].clone()
    log_pi[2, 17] = float("-inf")
    with pytest.raises(ValueError, match=r"trajectories \[2\] have zero likelihood"):
        forward_backward(log_pi, *xs[1:], backend="numba")


@needs_numba
def test_numba_stable_100k_steps_float32():
    """100,000 float32 steps, near-deterministic probabilities and -inf entries: the kernel itself (no fallback)
    stays finite and normalised, and agrees with the reference on a prefix."""
    B, T, K = 2, 100_000, 4
    g = torch.Generator().manual_seed(0)
    log_pi = (30.0 * torch.randn(B, T, K, generator=g)).log_softmax(-1)
    kill = torch.rand(B, T, K, generator=g) < 0.25
    kill[..., 0] &= ~kill[..., 1:].all(-1)
    log_pi = log_pi.masked_fill(kill, float("-inf"))
    tl = 20.0 * torch.randn(B, T, K, generator=g) - 5.0
    log_term, log_cont = torch.nn.functional.logsigmoid(tl), torch.nn.functional.logsigmoid(-tl)
    log_eta = (20.0 * torch.randn(B, T, K, generator=g)).log_softmax(-1)
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[1, 77_777:] = False
    xs = (log_pi, log_term, log_cont, log_eta)
    ll, u, v, w, bad = numba_mod.numba_forward_backward(*_zeroed(xs, mask), mask, torch.tensor([True, False]))
    assert not bad.any(), "the kernel itself must handle this case (no fallback)"
    assert torch.isfinite(ll).all()
    for x in (u, v, w):
        assert torch.isfinite(x).all()
    assert ((u.sum(-1)[mask] - 1).abs().max() < 1e-4).item()
    assert (u.sum(-1)[~mask] == 0).all()
    n = 3000
    ref = forward_backward(*(x[:, :n] for x in xs), terminal=True, backend="reference")
    out = forward_backward(*(x[:, :n] for x in xs), terminal=True, backend="numba")
    assert_close_outputs(ref, out, torch.float32)


@needs_numba
def test_numba_thread_count_does_not_change_results():
    xs, mask, terminal = make_case(9, 50, 4, torch.float32, ninf=0.1, seed=4)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
        torch.set_num_threads(3)
        three = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    finally:
        torch.set_num_threads(threads)
    for name in ("log_likelihood", "u", "v", "w"):
        assert torch.equal(getattr(one, name), getattr(three, name)), name


@pytest.mark.parametrize("parts", [1, 2, 3, 7, 20])
def test_numba_row_split_covers_every_row_once(parts):
    import numpy as np

    lengths = np.array([5, 1, 100, 3, 3, 50, 7])
    ranges = numba_mod._split_rows(lengths, parts)
    assert ranges[0][0] == 0 and ranges[-1][1] == len(lengths)
    assert all(a < b for a, b in ranges) and all(r[1] == s[0] for r, s in zip(ranges, ranges[1:]))
    assert len(ranges) <= min(parts, len(lengths))


def test_auto_without_numba_falls_back(monkeypatch):
    """Without Numba installed, "auto" takes the PyTorch paths and an explicit "numba" says what to install."""
    monkeypatch.setattr(fb_mod, "numba_available", lambda: False)
    xs, mask, terminal = make_case(3, 20, 3, pad=False)
    assert resolve_backend("auto", xs[0]) == "chunked"
    assert resolve_backend("auto", xs[0][:, :4]) == "reference"
    with pytest.raises(ValueError, match="numba.*pip install"):
        forward_backward(*xs, backend="numba")
    ref = forward_backward(*xs, backend="reference")
    assert_close_outputs(ref, forward_backward(*xs), torch.float32)


@needs_numba
def test_numba_backend_argument_errors():
    xs, _, _ = make_case(2, 6, 3, pad=False)
    half = tuple(x.half() for x in xs)
    with pytest.raises(ValueError, match="float32 and float64"):
        forward_backward(*half, backend="numba")
    assert resolve_backend("auto", half[0]) != "numba"
    if HAS_CUDA:
        with pytest.raises(ValueError, match="CPU tensors"):
            forward_backward(*(x.cuda() for x in xs), backend="numba")


@needs_numba
def test_numba_kernels_compile_where_no_cache_location_exists():
    """A function Numba cannot cache (no source file, so no cache location) is compiled in memory instead."""
    from torchrl_options.inference._numba_kernels import _jit

    ns = {}
    exec(compile("def f(x):\n    return x + 1.0\n", "<generated>", "exec"), ns)
    assert _jit()(ns["f"])(1.0) == 2.0


_INTERPRET_SCRIPT = textwrap.dedent(
    """
    import os, sys, warnings
    os.environ["TRITON_INTERPRET"] = "1"
    warnings.simplefilter("ignore")
    import torch
    sys.path.insert(0, os.path.dirname(os.path.abspath({test_file!r})))
    from test_forward_backward_fast import make_case, assert_close_outputs, weighted_gradients
    from torchrl_options.inference.forward_backward import forward_backward, resolve_backend
    cases = [(5, 9, 3, torch.float32, 0.2), (4, 7, 5, torch.float64, 0.2), (3, 1, 4, torch.float32, 0.0),
             (3, 6, 2, torch.float32, 0.0), (2, 5, 17, torch.float32, 0.1)]
    for B, T, K, dtype, ninf in cases:
        xs, mask, terminal = make_case(B, T, K, dtype, ninf=ninf, seed=B * T * K)
        assert resolve_backend("triton", xs[0]) == "triton"
        ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
        weights = torch.rand(B, dtype=dtype) + 0.5
        grads = {{}}
        for backend in ("reference", "triton"):
            grads[backend], out = weighted_gradients(xs, mask, terminal, weights, backend)
        assert_close_outputs(ref, out, dtype)
        # the fused gradient kernel: the Expectation-Gradient of the kernel's own marginals, and the reference's
        torch.testing.assert_close(grads["triton"][0], weights[:, None, None] * out.u, rtol=0, atol=0)
        torch.testing.assert_close(grads["triton"][2], weights[:, None, None] * out.w, rtol=0, atol=0)
        torch.testing.assert_close(grads["triton"][3], weights[:, None, None] * out.v, rtol=0, atol=0)
        for a, b in zip(grads["reference"], grads["triton"]):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6)
    xs, mask, terminal = make_case(3, 6, 3, torch.float32, pad=False, seed=1)
    log_pi = xs[0].clone(); log_pi[1, 4] = float("-inf")
    try:
        forward_backward(log_pi, *xs[1:], backend="triton")
    except ValueError as e:
        assert "trajectories [1] have zero likelihood" in str(e), e
    else:
        raise AssertionError("no zero-likelihood error")
    print("OK")
    """
)


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed")
def test_triton_kernel_under_interpreter():
    """The Triton kernel, run by Triton's CPU interpreter (in a subprocess: the mode is read at import)."""
    script = _INTERPRET_SCRIPT.format(test_file=__file__)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "OK" in res.stdout, res.stdout + res.stderr


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_CUDA, reason="needs CUDA")
@pytest.mark.parametrize("backend", ["triton", "chunked", "auto"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_backends_match_reference(backend, dtype):
    if backend == "triton" and not HAS_TRITON:
        pytest.skip("triton is not installed")
    xs, mask, terminal = make_case(33, 300, 16, dtype, ninf=0.2, sharp=3.0, seed=7)
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    xs_c = tuple(x.cuda() for x in xs)
    out = forward_backward(*xs_c, mask=mask.cuda(), terminal=terminal.cuda(), backend=backend)
    out_cpu = type(out)(*(x.cpu() for x in (out.log_likelihood, out.u, out.v, out.w)))
    assert_close_outputs(ref, out_cpu, dtype)


@pytest.mark.gpu
@pytest.mark.skipif(not (HAS_CUDA and HAS_TRITON), reason="needs CUDA and triton")
@pytest.mark.parametrize("B,T,K", [(33, 300, 16), (70, 129, 5), (3, 1, 4)])
def test_triton_cuda_gradients_match_reference(B, T, K):
    """Identical gradients: the fused gradient kernel against the reference path's autograd, weighted rows."""
    xs, mask, terminal = make_case(B, T, K, torch.float32, ninf=0.2, sharp=3.0, seed=B + T + K, device="cuda")
    weights = torch.rand(B, device="cuda") + 0.5
    grads = {}
    for backend in ("reference", "triton"):
        grads[backend], out = weighted_gradients(xs, mask, terminal, weights, backend)
    torch.testing.assert_close(grads["triton"][0], weights[:, None, None] * out.u, rtol=0, atol=0)
    torch.testing.assert_close(grads["triton"][3], weights[:, None, None] * out.v, rtol=0, atol=0)
    for a, b in zip(grads["reference"], grads["triton"]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6)


@pytest.mark.gpu
@pytest.mark.skipif(not (HAS_CUDA and HAS_TRITON), reason="needs CUDA and triton")
def test_triton_cuda_stable_100k_steps():
    B, T, K = 4, 100_000, 8
    g = torch.Generator().manual_seed(0)
    log_pi = (30.0 * torch.randn(B, T, K, generator=g)).log_softmax(-1)
    kill = torch.rand(B, T, K, generator=g) < 0.25
    kill[..., 0] &= ~kill[..., 1:].all(-1)
    log_pi = log_pi.masked_fill(kill, float("-inf"))
    tl = 20.0 * torch.randn(B, T, K, generator=g) - 5.0
    xs = (log_pi, torch.nn.functional.logsigmoid(tl), torch.nn.functional.logsigmoid(-tl),
          (20.0 * torch.randn(B, T, K, generator=g)).log_softmax(-1))
    out = forward_backward(*(x.cuda() for x in xs), terminal=True, backend="triton")
    assert torch.isfinite(out.log_likelihood).all()
    assert ((out.u.sum(-1) - 1).abs().max() < 1e-4).item()
