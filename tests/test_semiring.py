"""The one semiring-parameterised scan (``inference/semiring.py``) against brute-force enumeration: log-sum-exp
gives the likelihood and, by autograd, the marginals; max-plus gives the Viterbi score and, by autograd, the best
latent sequence, which :func:`viterbi`'s backpointers and the reference forward-backward must agree with."""
import pytest
import torch

from _enumeration import latent_sequences
from torchrl_options.inference import forward_backward, viterbi
from torchrl_options.inference.semiring import chunked_forward_messages, forward_messages, LOG, MAX, scan_score


def _inputs(B, T, K, seed):
    g = torch.Generator().manual_seed(seed)
    log_pi = torch.randn(B, T, K, generator=g, dtype=torch.float64).log_softmax(-1) * 2
    psi = torch.rand(B, T, K, generator=g, dtype=torch.float64)
    log_eta = torch.randn(B, T, K, generator=g, dtype=torch.float64).log_softmax(-1)
    return log_pi, psi.log(), torch.log1p(-psi), log_eta


def _brute_force(x, b, L, terminal):
    """(logsumexp, max, argmax sequence, marginals u v w) over every latent sequence of row ``b``."""
    log_pi, log_term, log_cont, log_eta = (t[b] for t in x)
    K = log_pi.shape[-1]
    joint = list(latent_sequences(log_pi, log_term, log_cont, log_eta, L, terminal))
    scores = torch.stack([j[0] for j in joint])
    logz = scores.logsumexp(0)
    u, v, w = (torch.zeros(L, K, dtype=torch.float64) for _ in range(3))
    for lp, hs, bs in joint:
        p = (lp - logz).exp()
        for t in range(L):
            u[t, hs[t]] += p
            v[t, hs[t]] += p * bs[t]
            if t < L - 1 and not bs[t + 1]:
                w[t, hs[t]] += p
    best = joint[int(scores.argmax())]
    return logz, scores.max(), best, (u, v, w)


@pytest.mark.parametrize("K,T", [(1, 3), (2, 4), (3, 4)])
def test_both_semirings_against_enumeration(K, T):
    """Padded and terminal rows: the log scan's total and gradient are the likelihood and the marginals; the
    max-plus scan's total and gradient are the best sequence's score and its indicator; viterbi and
    forward_backward return the same."""
    B = 3
    x = _inputs(B, T, K, seed=10 * K + T)
    lengths = torch.tensor([T, T - 1, 2])
    mask = torch.arange(T) < lengths.unsqueeze(1)
    terminal = torch.tensor([False, True, True])
    zeroed = [torch.where(mask.unsqueeze(-1), t, 0.0).requires_grad_() for t in x]
    logz = scan_score(LOG, *zeroed, mask, terminal)
    g_pi, _, g_cont, g_eta = torch.autograd.grad(logz.sum(), zeroed)
    best = scan_score(MAX, *zeroed, mask, terminal)
    p_pi, _, _, p_eta = torch.autograd.grad(best.sum(), zeroed)
    fb = forward_backward(*x, mask=mask, terminal=terminal, backend="reference")
    vit = viterbi(*x, mask=mask, terminal=terminal)
    chunked = viterbi(*x, mask=mask, terminal=terminal, backend="chunked")
    for b in range(B):
        L = int(lengths[b])
        ref_logz, ref_max, (_, hs, bs), (u, v, w) = _brute_force(x, b, L, bool(terminal[b]))
        torch.testing.assert_close(logz[b], ref_logz)
        torch.testing.assert_close(fb.log_likelihood[b], ref_logz)
        for grad, marginal in ((g_pi, u), (g_eta, v), (g_cont, w)):
            torch.testing.assert_close(grad[b, :L], marginal)
            assert (grad[b, L:] == 0).all()
        torch.testing.assert_close(best[b], ref_max)
        torch.testing.assert_close(vit.log_prob[b], ref_max)
        # the max-plus gradient is the best sequence: one option per step, one start per switch
        assert p_pi[b, :L].argmax(-1).tolist() == list(hs) == vit.options[b, :L].tolist()
        assert p_pi[b, :L].sum(-1).tolist() == [1.0] * L
        assert (p_eta[b, :L].sum(-1) > 0.5).tolist() == [bool(s) for s in bs] == vit.switches[b, :L].tolist()
        assert (vit.options[b, L:] == -1).all() and not vit.switches[b, L:].any()
    assert torch.equal(chunked.options, vit.options) and torch.equal(chunked.switches, vit.switches)
    torch.testing.assert_close(chunked.log_prob, vit.log_prob)


def test_viterbi_backpointers_agree_with_the_max_plus_gradient_on_long_rows():
    """On rows too long to enumerate, viterbi's explicit backpointers follow the same choices as autograd of the
    shared max-plus scan (its ties included)."""
    x = _inputs(4, 60, 5, seed=3)
    mask = torch.arange(60) < torch.tensor([[60], [41], [7], [1]])
    terminal = torch.tensor([True, False, True, False])
    zeroed = [torch.where(mask.unsqueeze(-1), t, 0.0).requires_grad_() for t in x]
    best = scan_score(MAX, *zeroed, mask, terminal)
    p_pi, _, _, p_eta = torch.autograd.grad(best.sum(), zeroed)
    vit = viterbi(*x, mask=mask, terminal=terminal)
    torch.testing.assert_close(vit.log_prob, best.detach())
    assert torch.equal(vit.options, torch.where(mask, p_pi.argmax(-1), -1))
    assert torch.equal(vit.switches, mask & (p_eta.sum(-1) > 0.5))


@pytest.mark.parametrize("semiring", [LOG, MAX], ids=["log", "max"])
@pytest.mark.parametrize("T,L", [(1, 3), (2, 1), (9, 3), (30, 4), (31, 40)])
def test_chunked_scan_matches_the_sequential_scan(semiring, T, L):
    """The chunked scan (transfer matrices composed per chunk, a scan across chunks, messages recovered) gives the
    sequential scan's messages and switch masses in either semiring, chunks that do not divide T included."""
    log_pi, log_term, log_cont, log_eta = _inputs(3, T, 4, seed=T)
    switch, stay = log_pi + log_term, log_pi + log_cont
    ref, _, ref_s = forward_messages(semiring, switch, stay, log_eta)
    alpha, s = chunked_forward_messages(semiring, switch, stay, log_eta, L)
    torch.testing.assert_close(alpha, ref)
    if T > 1:
        torch.testing.assert_close(s, torch.stack(ref_s, 1))


def test_chunked_viterbi_matches_the_reference_on_long_padded_rows():
    x = _inputs(5, 300, 6, seed=7)
    mask = torch.arange(300) < torch.tensor([[300], [299], [150], [17], [1]])
    terminal = torch.tensor([True, False, True, False, True])
    ref = viterbi(*x, mask=mask, terminal=terminal)
    out = viterbi(*x, mask=mask, terminal=terminal, backend="chunked")
    assert torch.equal(out.options, ref.options) and torch.equal(out.switches, ref.switches)
    torch.testing.assert_close(out.log_prob, ref.log_prob)
    with pytest.raises(ValueError, match="backend must be one of"):
        viterbi(*x, backend="numba")
