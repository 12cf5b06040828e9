"""The E-step (every CPU backend) against exact enumeration, its gradient identities, stability and bad input."""
import math

import pytest
import torch

from _enumeration import latent_sequences
from torchrl_options import forward_backward
from torchrl_options.inference.forward_backward import numba_available

# Every CPU backend must pass the numerical tests below ("auto" resolves to one of them).
CPU_BACKENDS = [
    "reference",
    "chunked",
    pytest.param("numba", marks=pytest.mark.skipif(not numba_available(), reason="numba is not installed")),
]


@pytest.fixture(params=CPU_BACKENDS)
def backend(request):
    return request.param


def _random_inputs(B, T, K, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    log_pi = torch.randn(B, T, K, generator=g, dtype=dtype).log_softmax(-1) * 2
    psi = torch.rand(B, T, K, generator=g, dtype=dtype)
    log_eta = torch.randn(B, T, K, generator=g, dtype=dtype).log_softmax(-1)
    return log_pi, psi.log(), torch.log1p(-psi), log_eta


def _enumerate(log_pi, log_term, log_cont, log_eta, L, terminal):
    """Brute force over every latent sequence (b_0 = 1; a new option may be the same one)."""
    K = log_pi.shape[-1]
    joint = list(latent_sequences(log_pi, log_term, log_cont, log_eta, L, terminal))
    logz = torch.logsumexp(torch.stack([j[0] for j in joint]), 0)
    u = torch.zeros(L, K, dtype=log_pi.dtype)
    v, w = torch.zeros_like(u), torch.zeros_like(u)
    for lp, hs, b in joint:
        p = (lp - logz).exp()
        for t in range(L):
            u[t, hs[t]] += p
            if b[t]:
                v[t, hs[t]] += p
            if t < L - 1 and not b[t + 1]:
                w[t, hs[t]] += p
    return logz, u, v, w


@pytest.mark.parametrize("K,T", [(1, 4), (2, 5), (3, 4)])
def test_exact_against_enumeration_with_padding_and_terminal_rows(K, T, backend):
    B = 4
    inputs = _random_inputs(B, T, K, seed=K * 10 + T)
    lengths = [T, T - 1, 2, 1]
    mask = torch.arange(T)[None, :] < torch.tensor(lengths)[:, None]
    terminal = torch.tensor([True, False, True, False])
    out = forward_backward(*inputs, mask=mask, terminal=terminal, backend=backend)
    for b, L in enumerate(lengths):
        logz, u, v, w = _enumerate(*(x[b] for x in inputs), L, bool(terminal[b]))
        torch.testing.assert_close(out.log_likelihood[b], logz, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.u[b, :L], u, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.v[b, :L], v, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.w[b, :L], w, rtol=0, atol=1e-12)
        # padding is zero, and w is zero at the last valid step
        for x in (out.u, out.v, out.w):
            assert (x[b, L:] == 0).all()
        assert (out.w[b, L - 1] == 0).all()


def test_marginal_consistency(backend):
    inputs = _random_inputs(3, 30, 4, seed=3)
    out = forward_backward(*inputs, backend=backend)
    torch.testing.assert_close(out.u.sum(-1), torch.ones(3, 30, dtype=torch.float64))
    # an option active at t+1 either started there or continued from t
    torch.testing.assert_close(out.u[:, 1:], out.v[:, 1:] + out.w[:, :-1])
    torch.testing.assert_close(out.v[:, 0], out.u[:, 0])


@pytest.mark.parametrize("terminal", [False, True])
def test_gradient_is_expectation_gradient(terminal, backend):
    B, T, K = 3, 12, 3
    log_pi, log_term, log_cont, log_eta = (x.requires_grad_() for x in _random_inputs(B, T, K, seed=7))
    mask = torch.arange(T)[None, :] < torch.tensor([12, 7, 1])[:, None]
    out = forward_backward(log_pi, log_term, log_cont, log_eta, mask=mask, terminal=terminal, backend=backend)
    out.log_likelihood.sum().backward()
    torch.testing.assert_close(log_pi.grad, out.u)
    torch.testing.assert_close(log_eta.grad, out.v)
    torch.testing.assert_close(log_cont.grad, out.w)
    last = mask.sum(1) - 1
    expected_term = out.u - out.w
    for b in range(B):
        expected_term[b, last[b]] = out.u[b, last[b]] if terminal else 0.0
    torch.testing.assert_close(log_term.grad, expected_term)


def test_gradient_matches_autograd_of_enumeration(backend):
    T, K = 4, 2
    inputs = [x[0].clone().requires_grad_() for x in _random_inputs(1, T, K, seed=11)]
    logz, *_ = _enumerate(*inputs, T, True)
    grads = torch.autograd.grad(logz, inputs)
    fb_inputs = [x.detach().unsqueeze(0).requires_grad_() for x in inputs]
    out = forward_backward(*fb_inputs, terminal=True, backend=backend)
    fb_grads = torch.autograd.grad(out.log_likelihood.sum(), fb_inputs)
    for g, h in zip(grads, fb_grads):
        torch.testing.assert_close(h[0], g)


def test_gradient_scales_with_upstream_gradient(backend):
    inputs = [x.requires_grad_() for x in _random_inputs(2, 6, 3, seed=5)]
    out = forward_backward(*inputs, backend=backend)
    (out.log_likelihood * torch.tensor([2.0, -3.0], dtype=torch.float64)).sum().backward()
    torch.testing.assert_close(inputs[0].grad, out.u * torch.tensor([2.0, -3.0], dtype=torch.float64).view(2, 1, 1))


def test_single_option_is_behaviour_cloning(backend):
    B, T = 3, 25
    log_pi, log_term, log_cont, _ = _random_inputs(B, T, 1, seed=2)
    log_eta = torch.zeros(B, T, 1, dtype=torch.float64)
    out = forward_backward(log_pi, log_term, log_cont, log_eta, backend=backend)
    # with one option the likelihood is the behaviour-cloning one: sum_t log pi(a_t|s_t), whatever psi is
    torch.testing.assert_close(out.log_likelihood, log_pi.sum((1, 2)))
    assert (out.u == 1).all()


def test_float32_matches_float64(backend):
    inputs = _random_inputs(4, 200, 5, seed=4)
    out64 = forward_backward(*inputs, backend=backend)
    out32 = forward_backward(*(x.float() for x in inputs), backend=backend)
    assert out32.u.dtype == torch.float32
    torch.testing.assert_close(out32.log_likelihood.double(), out64.log_likelihood, rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(out32.u.double(), out64.u, rtol=0, atol=1e-4)


def test_long_float32_trajectory_is_stable(backend):
    """100,000 steps, near-deterministic probabilities and -inf entries: finite and normalised, no clipping."""
    if backend == "reference":
        pytest.skip("the reference takes about 40 s here; test_chunked_stable_100k_steps_float32 compares it on a prefix")
    B, T, K = 2, 100_000, 4
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(B, T, K, generator=g) * 30  # near-deterministic choices
    log_pi = logits.log_softmax(-1)
    # options 2 and 3 cannot produce the action on a third of the steps each
    impossible = torch.rand(B, T, K, generator=g) < torch.tensor([0.0, 0.0, 0.33, 0.33])
    log_pi = torch.where(impossible, float("-inf"), log_pi)
    term_logits = torch.randn(B, T, K, generator=g) * 20
    log_term = torch.nn.functional.logsigmoid(term_logits)
    log_cont = torch.nn.functional.logsigmoid(-term_logits)
    log_eta = (torch.randn(B, T, K, generator=g) * 10).log_softmax(-1)
    out = forward_backward(log_pi, log_term, log_cont, log_eta, terminal=True, backend=backend)
    assert torch.isfinite(out.log_likelihood).all()
    assert out.log_likelihood.lt(0).all()
    for x in (out.u, out.v, out.w):
        assert torch.isfinite(x).all()
        assert (x >= 0).all() and (x <= 1 + 1e-5).all()
    assert (out.u.sum(-1) - 1).abs().max() < 1e-4
    assert (out.v[:, 1:].sum(-1) + out.w[:, :-1].sum(-1) - 1).abs().max() < 1e-4
    assert (out.u[impossible] == 0).all()


def test_impossible_entries_get_zero_posterior(backend):
    log_pi, log_term, log_cont, log_eta = _random_inputs(1, 6, 3, seed=9)
    log_pi[0, 2, 1] = -math.inf
    log_eta[0, :, 2] = -math.inf  # option 2 is never started
    out = forward_backward(log_pi, log_term, log_cont, log_eta, backend=backend)
    assert out.u[0, 2, 1] == 0
    assert (out.u[0, :, 2] == 0).all()
    logz, u, _, _ = _enumerate(log_pi[0], log_term[0], log_cont[0], log_eta[0], 6, False)
    torch.testing.assert_close(out.u[0], u, rtol=0, atol=1e-12)


def test_padding_content_is_ignored(backend):
    inputs = list(_random_inputs(2, 8, 3, seed=1))
    mask = torch.arange(8)[None, :] < torch.tensor([8, 5])[:, None]
    ref = forward_backward(*inputs, mask=mask, backend=backend)
    for x in inputs:
        x[1, 5:] = float("nan")
    out = forward_backward(*inputs, mask=mask, backend=backend)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood)
    torch.testing.assert_close(out.u, ref.u)


def test_batched_equals_one_by_one(backend):
    inputs = _random_inputs(3, 10, 2, seed=6)
    mask = torch.arange(10)[None, :] < torch.tensor([10, 4, 7])[:, None]
    out = forward_backward(*inputs, mask=mask, backend=backend)
    for b in range(3):
        L = int(mask[b].sum())
        single = forward_backward(*(x[b : b + 1, :L] for x in inputs), backend=backend)
        torch.testing.assert_close(out.log_likelihood[b : b + 1], single.log_likelihood)
        torch.testing.assert_close(out.u[b : b + 1, :L], single.u)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    inputs = _random_inputs(3, 50, 4, dtype=torch.float32, seed=8)
    cpu = forward_backward(*inputs)
    gpu = forward_backward(*(x.cuda() for x in inputs))
    torch.testing.assert_close(gpu.u.cpu(), cpu.u, rtol=1e-5, atol=1e-5)


class TestBadInput:
    def _ok(self):
        return list(_random_inputs(2, 5, 3, dtype=torch.float32))

    @pytest.mark.parametrize("index,name", [(0, "log_pi"), (1, "log_term"), (2, "log_cont"), (3, "log_eta")])
    def test_shape_mismatch_names_argument(self, index, name):
        inputs = self._ok()
        if index == 0:
            inputs = [x[:, :, :2] if i else x for i, x in enumerate(inputs)]
            name = "log_term"
        else:
            inputs[index] = inputs[index][:, :4]
        with pytest.raises(ValueError, match=name):
            forward_backward(*inputs)

    def test_wrong_ndim(self):
        inputs = self._ok()
        inputs[3] = inputs[3][0]
        with pytest.raises(ValueError, match="log_eta.*3 dimensions"):
            forward_backward(*inputs)

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    @pytest.mark.parametrize("index,name", [(0, "log_pi"), (1, "log_term"), (2, "log_cont"), (3, "log_eta")])
    def test_nan_or_pos_inf(self, bad, index, name):
        inputs = self._ok()
        inputs[index][1, 2, 0] = bad
        with pytest.raises(ValueError, match=f"{name} contains NaN or \\+inf"):
            forward_backward(*inputs)

    def test_non_prefix_mask(self):
        mask = torch.tensor([[True, False, True, True, True], [True] * 5])
        with pytest.raises(ValueError, match="mask.*prefix"):
            forward_backward(*self._ok(), mask=mask)

    def test_empty_row_mask(self):
        mask = torch.tensor([[False] * 5, [True] * 5])
        with pytest.raises(ValueError, match="mask"):
            forward_backward(*self._ok(), mask=mask)

    def test_mask_shape_and_dtype(self):
        with pytest.raises(ValueError, match="mask"):
            forward_backward(*self._ok(), mask=torch.ones(2, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask"):
            forward_backward(*self._ok(), mask=torch.ones(2, 5))

    def test_empty_batch(self):
        inputs = [x[:0] for x in self._ok()]
        with pytest.raises(ValueError, match="empty batch"):
            forward_backward(*inputs)

    def test_terminal_shape(self):
        with pytest.raises(ValueError, match="terminal"):
            forward_backward(*self._ok(), terminal=torch.ones(3, dtype=torch.bool))

    def test_dtype_mismatch(self):
        inputs = self._ok()
        inputs[2] = inputs[2].double()
        with pytest.raises(ValueError, match="log_cont.*dtype"):
            forward_backward(*inputs)

    def test_zero_likelihood(self, backend):
        inputs = self._ok()
        inputs[0][0, 3] = -math.inf  # no option can produce the action at step 3
        with pytest.raises(ValueError, match="zero likelihood"):
            forward_backward(*inputs, backend=backend)
