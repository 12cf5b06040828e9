"""Viterbi decoding against brute force, and the posterior argmax."""
import pytest
import torch

from _enumeration import latent_sequences
from torchrl_options import forward_backward, most_likely_options, viterbi


def _brute_viterbi(log_pi, log_term, log_cont, log_eta, L, terminal):
    return max(latent_sequences(log_pi, log_term, log_cont, log_eta, L, terminal), key=lambda j: float(j[0]))


@pytest.mark.parametrize("seed", range(4))
def test_viterbi_matches_brute_force(seed):
    g = torch.Generator().manual_seed(seed)
    B, T, K = 3, 5, 3
    log_pi = (torch.randn(B, T, K, generator=g, dtype=torch.float64) * 2).log_softmax(-1)
    psi = torch.rand(B, T, K, generator=g, dtype=torch.float64)
    log_eta = torch.randn(B, T, K, generator=g, dtype=torch.float64).log_softmax(-1)
    mask = torch.arange(T)[None] < torch.tensor([5, 3, 1])[:, None]
    terminal = torch.tensor([True, False, True])
    out = viterbi(log_pi, psi.log(), torch.log1p(-psi), log_eta, mask=mask, terminal=terminal)
    for b in range(B):
        L = int(mask[b].sum())
        lp, hs, bs = _brute_viterbi(log_pi[b], psi[b].log(), torch.log1p(-psi[b]), log_eta[b], L, bool(terminal[b]))
        torch.testing.assert_close(out.log_prob[b], lp)
        assert out.options[b, :L].tolist() == list(hs)
        assert out.switches[b, :L].tolist() == [bool(x) for x in bs]
        assert (out.options[b, L:] == -1).all() and not out.switches[b, L:].any()


def test_viterbi_long_float32_is_finite():
    g = torch.Generator().manual_seed(0)
    B, T, K = 2, 20_000, 3
    log_pi = (torch.randn(B, T, K, generator=g) * 20).log_softmax(-1)
    half = torch.full((B, T, K), 0.5).log()
    out = viterbi(log_pi, half, half, torch.full((B, T, K), 1 / 3).log())
    assert torch.isfinite(out.log_prob).all()
    assert (out.options >= 0).all()


def test_posterior_argmax_agrees_on_clear_segments():
    log_pi = torch.tensor([[[0.0, -6.0]] * 4 + [[-6.0, 0.0]] * 4])
    half = torch.full_like(log_pi, 0.5).log()
    fb = forward_backward(log_pi, half, half, half)
    assert most_likely_options(fb.u).tolist() == [[0] * 4 + [1] * 4]
    assert viterbi(log_pi, half, half, half).options.tolist() == [[0] * 4 + [1] * 4]
    mask = torch.tensor([[True] * 6 + [False] * 2])
    assert most_likely_options(fb.u, mask)[0, -2:].tolist() == [-1, -1]
