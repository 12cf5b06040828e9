"""The float32 compiled E-step (numba backend, float32 inputs) and its vector layer, against float64 references."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from test_forward_backward_fast import assert_close_outputs, make_case, weighted_gradients
from torchrl_options import forward_backward
from torchrl_options.inference.forward_backward import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not installed")


def _e_step(*args, **kwargs):
    from torchrl_options.inference._numba_fb import numba_e_step

    return numba_e_step(*args, **kwargs)


def _truth(xs, mask, terminal):
    """The log-space reference on the float64 copies of the inputs."""
    return forward_backward(*(x.double() for x in xs), mask=mask, terminal=terminal, backend="reference")


def _max_err(out, ref):
    return max((getattr(out, n).double() - getattr(ref, n)).abs().max().item() for n in ("u", "v", "w"))


@pytest.mark.parametrize("K", [1, 2, 3, 4, 5, 8, 9, 16, 17, 32])
@pytest.mark.parametrize("ninf", [0.0, 0.2])
def test_matches_reference_with_padding_and_variable_lengths(K, ninf):
    """Random lengths (row 0 full, lengths down to 1), terminal and non-terminal rows, NaN in the padding, -inf
    entries: the float32 kernel itself (no row handed to the float64 kernel) agrees with the float32 reference
    and is at least as close as the reference to the float64 answer."""
    xs, mask, terminal = make_case(9, 150, K, torch.float32, pad=True, ninf=ninf, sharp=2.0, seed=100 + K)
    mask[1, 1:] = False  # a row of one step
    res = _e_step(*xs, mask, terminal)
    assert res.float32_rows_recomputed == 0 and not res.bad.any() and not res.invalid.any()
    assert res.clean  # the caller's lean path: nothing to name or recompute
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    ref32 = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    assert_close_outputs(ref32, out, torch.float32)
    truth = _truth(xs, mask, terminal)
    assert _max_err(out, truth) <= max(_max_err(ref32, truth), 5e-7)
    rel = ((out.log_likelihood.double() - truth.log_likelihood).abs() / truth.log_likelihood.abs().clamp_min(1)).max().item()
    assert rel < 1e-6
    for x in (out.u, out.v, out.w):
        assert (x[~mask] == 0).all()
    last = mask.sum(1) - 1
    assert (out.w[torch.arange(9), last] == 0).all()
    if ninf:  # impossible actions get exactly zero posterior
        assert (out.u[(xs[0] == -math.inf) & mask[..., None]] == 0).all()


@pytest.mark.parametrize("K,T", [(1, 5), (2, 6), (3, 5), (9, 3)])
def test_exact_against_enumeration_float32(K, T):
    """The float32 kernel itself (no row handed to the float64 kernel) against brute force over every latent
    sequence, computed in float64 from the same float32 inputs: the log-likelihood, ``u``, ``v``, ``w`` and the
    gradients of ``sum(log P)`` with respect to the four inputs (autograd of the enumeration), with padding
    (NaN there), terminal and non-terminal rows. K = 9 takes two 8-lane vectors per step."""
    from _enumeration import latent_sequences

    B = 4
    xs, _, _ = make_case(B, T, K, torch.float32, pad=False, sharp=2.0, seed=300 + 10 * K + T)
    lengths = [T, T - 1, 2, 1]
    mask = torch.arange(T)[None, :] < torch.tensor(lengths)[:, None]
    terminal = torch.tensor([True, False, False, True])
    xs = [x.masked_fill(~mask[..., None], float("nan")) for x in xs]
    res = _e_step(*xs, mask, terminal, grads=True)
    assert res.float32_rows_recomputed == 0 and not res.bad.any() and not res.invalid.any()
    leaves = [x.clone().requires_grad_() for x in xs]
    out = forward_backward(*leaves, mask=mask, terminal=terminal)  # the defaults: auto -> numba, float32 kernel
    out.log_likelihood.sum().backward()
    for b, L in enumerate(lengths):
        row = [x[b, :L].double().requires_grad_() for x in xs]
        joint = list(latent_sequences(*row, L, bool(terminal[b])))
        logz = torch.logsumexp(torch.stack([j[0] for j in joint]), 0)
        u = torch.zeros(L, K, dtype=torch.float64)
        v, w = torch.zeros_like(u), torch.zeros_like(u)
        for lp, hs, sw in joint:
            p = (lp - logz).exp().detach()
            for t in range(L):
                u[t, hs[t]] += p
                if sw[t]:
                    v[t, hs[t]] += p
                if t < L - 1 and not sw[t + 1]:
                    w[t, hs[t]] += p
        assert abs(out.log_likelihood[b].item() - logz.item()) <= 2e-6 * max(1.0, abs(logz.item()))
        for got, want in zip((out.u, out.v, out.w), (u, v, w)):
            assert (got[b, :L].double() - want).abs().max().item() < 1e-6
            assert (got[b, L:] == 0).all()
        for leaf, g, x in zip(leaves, torch.autograd.grad(logz, row, allow_unused=True), row):
            g = torch.zeros_like(x) if g is None else g  # a one-step row reads no log_cont
            assert (leaf.grad[b, :L].double() - g).abs().max().item() < 1e-6
            assert (leaf.grad[b, L:] == 0).all()


def test_single_option_is_exactly_one():
    xs, mask, terminal = make_case(3, 40, 1, torch.float32, pad=True, seed=3)
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    assert (out.u[mask] == 1).all()


def test_long_trajectory_finite_and_normalised():
    """100,000 float32 steps of ordinary inputs: the float32 kernel certifies both rows (no fallback), everything
    is finite, u sums to one at every valid step, v + w is u, and the whole agrees with the float64 kernel."""
    B, T, K = 2, 100_000, 8
    xs, _, _ = make_case(B, T, K, torch.float32, pad=False, sharp=3.0, seed=7)
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[1, 61_234:] = False
    terminal = torch.tensor([True, False])
    res = _e_step(*xs, mask, terminal)
    assert res.float32_rows_recomputed == 0 and not res.bad.any()
    assert torch.isfinite(res.log_likelihood).all()
    for x in (res.u, res.v, res.w):
        assert torch.isfinite(x).all() and (x >= 0).all()
    sums = res.u.sum(-1)
    assert (sums[mask] - 1).abs().max() < 1e-5
    assert (sums[~mask] == 0).all()
    assert (res.u[:, 1:] - res.v[:, 1:] - res.w[:, :-1])[mask[:, 1:]].abs().max() < 1e-5
    ref = _e_step(*(x.double() for x in xs), mask, terminal)  # the float64 kernel on float64 inputs
    assert _max_err(res, ref) < 2e-6
    rel = ((res.log_likelihood.double() - ref.log_likelihood).abs() / ref.log_likelihood.abs()).max().item()
    assert rel < 1e-6


def test_sharp_rows_go_to_the_float64_kernel():
    """Near-deterministic inputs the float32 kernel cannot certify are recomputed by the float64 kernel; the
    answer stays at least as close to the float64 one as the float32 reference's."""
    xs, mask, terminal = make_case(8, 200, 4, torch.float32, pad=True, ninf=0.2, sharp=40.0, seed=11)
    res = _e_step(*xs, mask, terminal)
    assert res.float32_rows_recomputed > 0 and not res.clean
    out = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    truth = _truth(xs, mask, terminal)
    ref32 = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    assert _max_err(out, truth) <= max(2 * _max_err(ref32, truth), 1e-6)


def test_certificate_failure_is_recomputed(monkeypatch):
    """Force every row out of the float32 kernel's certificate: the float64 kernel's answer comes back."""
    import torchrl_options.inference._numba_fb as numba_mod

    xs, mask, terminal = make_case(5, 60, 6, torch.float32, pad=True, seed=12)
    before = forward_backward(*xs, mask=mask, terminal=terminal, backend="numba")
    monkeypatch.setattr(numba_mod, "_tiny32", lambda K: 10.0)
    res = _e_step(*xs, mask, terminal, grads=True)
    assert res.float32_rows_recomputed == 5 and not res.clean
    assert_close_outputs(before, res, torch.float32)
    # the gradients of the recomputed rows are still the Expectation-Gradient of their marginals
    gp, gt, gc, ge = res.grads
    assert torch.equal(gp, res.u) and torch.equal(gc, res.w) and torch.equal(ge, res.v)


@pytest.mark.parametrize("weights", ["ones", "random"])
def test_gradients_are_the_expectation_gradient_exactly(weights):
    """The gradients written by the kernel (upstream gradient 1, or scaled for other weights) are exactly
    ``g u``, ``g (u - w)`` where log_term enters, ``g w``, ``g v`` of the returned marginals, and match the
    reference's autograd."""
    B = 6
    xs, mask, terminal = make_case(B, 120, 8, torch.float32, ninf=0.1, seed=5)
    g = torch.ones(B) if weights == "ones" else torch.rand(B) + 0.5
    grads, out = weighted_gradients(xs, mask, terminal, g, "numba")
    last = mask.sum(1) - 1
    steps = torch.arange(mask.shape[1])
    tw = (steps < last[:, None]) | ((steps == last[:, None]) & terminal[:, None])
    gv = g.view(-1, 1, 1)
    exact = dict(rtol=0, atol=0)
    torch.testing.assert_close(grads[0], gv * out.u, **exact)
    torch.testing.assert_close(grads[1], gv * torch.where(tw[..., None], out.u - out.w, 0.0), **exact)
    torch.testing.assert_close(grads[2], gv * out.w, **exact)
    torch.testing.assert_close(grads[3], gv * out.v, **exact)
    ref, _ = weighted_gradients(xs, mask, terminal, g, "reference")
    for a, b in zip(ref, grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6)


def test_second_backward_and_autograd_grad():
    """retain_graph: the second backward recomputes the gradient from the saved marginals, equal to the first."""
    xs, mask, terminal = make_case(4, 50, 5, torch.float32, seed=6)
    leaves = [x.clone().requires_grad_() for x in xs]
    out = forward_backward(*leaves, mask=mask, terminal=terminal)
    first = torch.autograd.grad(out.log_likelihood.sum(), leaves, retain_graph=True)
    second = torch.autograd.grad(out.log_likelihood.sum() * 2, leaves)
    for a, b in zip(first, second):
        torch.testing.assert_close(2 * a, b, rtol=0, atol=0)


def test_values_checked_by_the_kernel():
    """A NaN or +inf among the valid entries raises the ValueError naming the tensor and the entry (the float32
    kernel finds it; with validate=False too), while NaN in the padding is ignored."""
    xs, mask, terminal = make_case(3, 20, 4, torch.float32, pad=False, seed=2)
    for index, name in enumerate(("log_pi", "log_term", "log_cont", "log_eta")):
        for bad in (float("nan"), float("inf")):
            ys = [x.clone() for x in xs]
            ys[index][2, 19, 3] = bad
            for validate in (True, False):
                with pytest.raises(ValueError, match=rf"{name} contains NaN or \+inf at \(b, t, k\) = \(2, 19, 3\)"):
                    forward_backward(*ys, validate=validate)
    mask = torch.ones(3, 20, dtype=torch.bool)
    mask[1, 10:] = False
    ys = [x.clone() for x in xs]
    for y in ys:
        y[1, 10:] = float("nan")
    ref = forward_backward(*(x[1:2, :10] for x in xs))
    out = forward_backward(*ys, mask=mask)
    torch.testing.assert_close(out.u[1:2, :10], ref.u, rtol=0, atol=0)


def test_output_memory_is_recycled_only_when_released():
    """Outputs still referenced are never handed out again; released ones are reused (no fresh page faults)."""
    xs, _, _ = make_case(4, 30, 8, torch.float32, pad=False, seed=9)
    a = forward_backward(*xs)
    b = forward_backward(*xs)
    ptrs_a = {t.data_ptr() for t in (a.u, a.v, a.w)}
    ptrs_b = {t.data_ptr() for t in (b.u, b.v, b.w)}
    assert not ptrs_a & ptrs_b
    kept = a.u.clone()
    view = a.u[:, 3]  # a view keeps the storage, hence the array, alive
    del a
    c = forward_backward(*xs)
    assert view.data_ptr() not in {t.data_ptr() for t in (c.u, c.v, c.w)}
    torch.testing.assert_close(view, kept[:, 3], rtol=0, atol=0)
    del b, c
    d = forward_backward(*xs)
    assert {t.data_ptr() for t in (d.u, d.v, d.w)} & ptrs_b


def test_thread_count_does_not_change_results():
    xs, mask, terminal = make_case(9, 80, 8, torch.float32, ninf=0.1, seed=4)
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


# --- the vector layer ---------------------------------------------------------------------------------------------


def _simd_kernels():
    import numba

    from torchrl_options.inference import _simd as s

    @numba.njit
    def exp_all(x, out, ec):
        c = s.exp_constants(ec)
        for i in range(0, x.size - 7, 8):
            s.vstore(out, i, s.vexp(s.vload(x, i), c))

    @numba.njit
    def partial(x, out, n):
        v = s.vload_n(x, 0, n, np.float32(-5.0))
        s.vstore_n(out, 0, s.vmul(v, s.vsplat(np.float32(2.0))), n)
        a, b = s.vsum2(s.vload(x, 0), s.vload(x, 8))
        return s.vsum(s.vload(x, 0)), s.vhmax(s.vload(x, 0)), s.vhmin(s.vload(x, 0)), a, b

    return exp_all, partial


def test_vexp_accuracy_and_zeros():
    exp_all, _ = _simd_kernels()
    x = np.concatenate([-np.linspace(0, 86.9, 200_000), [-87.5, -100.0, -np.inf, 0.0, -1e-30, -0.5]])
    x = x[: x.size // 8 * 8].astype(np.float32)
    out = np.empty_like(x)
    from torchrl_options.inference._simd import EXP_CONSTANTS

    exp_all(x, out, EXP_CONSTANTS)
    ref = np.exp(x.astype(np.float64))
    ok = x >= -87
    assert np.max(np.abs(out[ok] - ref[ok]) / ref[ok]) < 2.5e-7  # about 2 float32 ulp
    assert (out[~ok] == 0).all()


@pytest.mark.parametrize("n", [0, 1, 3, 7, 8])
def test_partial_loads_and_stores_touch_only_n_lanes(n):
    _, partial = _simd_kernels()
    x = np.arange(1, 17, dtype=np.float32)
    out = np.full(16, 99.0, np.float32)
    s, mx, mn, a, b = partial(x, out, n)
    expected = np.where(np.arange(8) < n, 2 * x[:8], 99.0)
    assert (out[:8] == expected).all() and (out[8:] == 99.0).all()
    assert (s, mx, mn) == (x[:8].sum(), 8.0, 1.0)
    assert (a, b) == (x[:8].sum(), x[8:].sum())



def test_eight_maxima_at_once_and_the_sum_in_every_lane():
    """``vhmax8`` is ``vhmax`` of each of its eight inputs (``-inf`` and ties of zeros included); ``vsumv`` holds
    ``vsum``'s value, bit for bit, in every lane; ``vfirst`` is lane 0."""
    import numba

    from torchrl_options.inference import _simd as s

    @numba.njit
    def lanes(x, y, out):
        m = s.vhmax8(s.vload(x, 0), s.vload(x, 8), s.vload(x, 16), s.vload(x, 24), s.vload(x, 32), s.vload(x, 40),
                     s.vload(x, 48), s.vload(x, 56))  # fmt: skip
        s.vstore(out, 0, m)
        for i in range(8):
            out[8 + i] = s.vhmax(s.vload(x, 8 * i))
        s.vstore(out, 16, s.vsumv(s.vload(y, 0)))
        out[24] = s.vsum(s.vload(y, 0))
        out[25] = s.vfirst(s.vload(x, 8))

    rng = np.random.default_rng(0)
    for trial in range(100):
        x = (rng.standard_normal(64) * 10 ** rng.uniform(-3, 3, 64)).astype(np.float32)
        x[rng.integers(0, 64, 6)] = -np.inf
        if trial % 10 == 0:
            x[8 * (trial // 10 % 8): 8 * (trial // 10 % 8) + 8] = -np.inf  # a vector of -inf only
        y = np.where(np.isfinite(x[:8]), x[:8], np.float32(trial)).astype(np.float32)
        out = np.empty(32, np.float32)
        lanes(x, y, out)
        assert np.array_equal(out[:8], x.reshape(8, 8).max(1)) and np.array_equal(out[:8], out[8:16])
        assert (out[16:24] == out[24]).all() and out[25] == x[8]
        assert abs(float(out[24]) - float(y.astype(np.float64).sum())) <= 1e-6 * np.abs(y).sum()


@pytest.mark.parametrize("K", [3, 8, 12])
@pytest.mark.parametrize("T,step", [(40, 17), (43, 41), (43, 38), (9, 0)])
def test_a_step_no_option_can_produce_is_named_wherever_it_falls(K, T, step):
    """A step whose every ``log pi`` is ``-inf`` (zero likelihood) inside a block of eight steps of the shift pass,
    in its tail (rows whose length is not a multiple of 8) or at the first step: the row is named, the others
    stay as the reference has them."""
    xs, mask, terminal = make_case(4, T, K, torch.float32, pad=False, seed=3)
    log_pi = xs[0].clone()
    log_pi[2, step] = float("-inf")
    with pytest.raises(ValueError, match=r"trajectories \[2\] have zero likelihood"):
        forward_backward(log_pi, *xs[1:], backend="numba")
    keep = torch.tensor([0, 1, 3])
    sub = [x[keep] for x in (log_pi, *xs[1:])]
    out = forward_backward(*sub, backend="numba")
    assert_close_outputs(forward_backward(*sub, backend="reference"), out, torch.float32)


def test_without_the_float32_kernel_float32_takes_the_float64_kernel(monkeypatch):
    """Where the float32 kernel could not be compiled, float32 inputs run the float64 kernel: same answers, same
    gradient identities."""
    import torchrl_options.inference._numba_fb as numba_mod

    xs, mask, terminal = make_case(5, 40, 6, torch.float32, seed=1)
    fast = forward_backward(*xs, mask=mask, terminal=terminal)
    monkeypatch.setattr(numba_mod, "_FLOAT32_KERNEL_OK", False)
    grads, out = weighted_gradients(xs, mask, terminal, torch.ones(5), "numba")
    assert_close_outputs(fast, out, torch.float32)
    torch.testing.assert_close(grads[0], out.u, rtol=0, atol=0)
    torch.testing.assert_close(grads[3], out.v, rtol=0, atol=0)


@pytest.mark.parametrize("valid", ["all", "padded"])
def test_lengths_from_an_all_valid_mask_and_a_padded_one(valid):
    """The lengths come without a sum when every step is valid and from the mask's rows otherwise: the same answers
    as the float32 reference either way, and the all-valid mask equal to passing none."""
    xs, mask, terminal = make_case(6, 37, 5, torch.float32, pad=valid == "padded", seed=21)
    if mask is None:
        mask = torch.ones(6, 37, dtype=torch.bool)
    terminal = torch.as_tensor(terminal).expand(6)
    res = _e_step(*xs, mask, terminal)
    assert res.clean and bool(mask.all()) == (valid == "all")
    ref = forward_backward(*xs, mask=mask, terminal=terminal, backend="reference")
    assert_close_outputs(ref, res, torch.float32)
    if valid == "all":
        none = forward_backward(*xs, terminal=terminal, backend="numba")
        assert torch.equal(none.u, res.u) and torch.equal(none.log_likelihood, res.log_likelihood)


def test_output_buffers_stay_bounded():
    """The recycled memory never exceeds its bound; arrays still held are never dropped or handed out twice."""
    from torchrl_options.inference._numba_fb import _OutputBuffers

    pool = _OutputBuffers(max_bytes=10 * 4 * 100)
    held = [pool.empty((10, 10), np.float32) for _ in range(3)]  # 1200 bytes: the third is not kept
    assert len({t.data_ptr() for t in held}) == 3
    assert pool._bytes <= pool.max_bytes
    ptr = held[0].data_ptr()
    del held[0]
    again = pool.empty((10, 10), np.float32)
    assert again.data_ptr() == ptr
    other = pool.empty((5, 5), np.float32)  # another shape: room is made from free arrays only
    assert pool._bytes <= pool.max_bytes
    assert len({again.data_ptr(), held[0].data_ptr(), held[1].data_ptr(), other.data_ptr()}) == 4
