"""A time-parallel (chunked) forward-backward for the options' latent chain, in plain PyTorch.

The reference recursion (:func:`torchrl_options.inference.forward_backward._forward_backward_reference`) takes T
sequential steps of a dozen small operations each, so on a CPU it is bound by per-operation overhead. Here the
time axis is cut into ``C`` chunks of ``L`` steps and the work is organised so that every sequential loop runs over
all chunks (and all batch rows) at once:

1. *Compose* (``L`` sequential steps, parallel over rows and chunks): each chunk's transfer matrix
   ``P_c = M_{cL+L-1} ... M_{cL}``, in float64 probability space with every column rescaled (and its log-scale
   carried separately). ``M_t = diag(pi (1 - psi)) + eta_{t+1} (pi psi)^T`` is rank one plus diagonal, so a step
   costs O(K^2) per chunk.
2. *Scan* (``C`` sequential steps): the forward messages at the chunk starts, ``alpha_{(c+1)L} ~ P_c alpha_{cL}``,
   and the backward messages, ``beta_{cL} ~ P_c^T beta_{(c+1)L}``, in log space.
3. *Recover* (``L`` sequential steps, parallel over chunks): every per-step message, by the reference's own
   normalised log-space recursion started from the chunk boundaries.
4. *Check*: each chunk's recovered message one step past its end must agree with the next boundary of the scan
   (to 1e-9 in log space, for entries above e^-600 of the message). Rows that fail (a transfer matrix underflowed
   in the rescaled probability space, which can happen with -inf entries and near-deterministic probabilities),
   and rows with a non-finite result, are reported back so that the caller recomputes them with the reference.

Sequential steps drop from ``2 T`` to about ``3 L + 2 C``; the marginals are then computed for all steps at once.
The end of each row (its last valid step, and a terminal termination) is folded into one extra "virtual"
transition, so that padded rows need no special case inside the loops:

* before the row's last step ``t``: the real transition (``d = pi (1-psi)``, ``c = pi psi``, ``e = eta_{t+1}``);
* at the last step: ``d = 0``, ``c = pi * psi^terminal`` (the end factor), ``e`` = the first unit vector, so the
  message after it is ``e_1 * (end . alpha_last)``;
* after it: the identity.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["chunked_forward_backward", "choose_chunk_length"]

_NEG_INF = float("-inf")
# Boundary check: entries above exp(_CHECK_FLOOR) of a normalised message must agree to _CHECK_TOL in log space.
_CHECK_FLOOR = -600.0
_CHECK_TOL = 1e-9
# Rescale the columns of the transfer matrices every _RENORM_EVERY composition steps (and at the end).
_RENORM_EVERY = 2


def choose_chunk_length(T: int) -> int:
    """The chunk length L for T steps: a recovery step costs about three composition or scan steps, hence
    ``L ~ sqrt(T / 2)`` balances ``3 L`` against ``2 T / L``."""
    return max(1, min(T, int(round(math.sqrt(T / 2.0)))))


def _lse(x: Tensor, dim: int, keepdim: bool = False) -> Tensor:
    return torch.logsumexp(x, dim, keepdim=keepdim)


def _normalise(x: Tensor) -> tuple[Tensor, Tensor]:
    z = _lse(x, -1, True)
    return x - z, z


def chunked_forward_backward(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor,
    terminal: Tensor,
    chunk_length: int | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Chunked forward-backward on inputs whose padding was replaced by zeros (see the module docstring).

    Returns ``(log_likelihood, u, v, w, bad)`` in the dtype of the inputs; ``bad`` is the ``[B]`` bool tensor of
    the rows that must be recomputed by the reference (their other outputs are meaningless).
    """
    B, T, K = log_pi.shape
    out_dtype = log_pi.dtype
    dev = log_pi.device
    cd = torch.float64
    L = choose_chunk_length(T) if chunk_length is None else max(1, min(int(chunk_length), T))
    C = -(-T // L)
    TP = C * L  # padded number of transitions (T real or virtual ones, then identities)

    lp, lt, lc, le = (x.to(cd) for x in (log_pi, log_term, log_cont, log_eta))
    lengths = mask.sum(1)
    last = (lengths - 1).view(B, 1, 1)
    steps = torch.arange(TP, device=dev).view(1, TP, 1)
    before, at = steps < last, steps == last

    last_idx = last.expand(B, 1, K)
    end = lp.gather(1, last_idx) + torch.where(terminal.view(B, 1, 1), lt.gather(1, last_idx), 0.0)  # [B,1,K]

    def pad(x: Tensor) -> Tensor:
        return torch.nn.functional.pad(x, (0, 0, 0, TP - x.shape[1])) if x.shape[1] < TP else x

    neg_inf = torch.tensor(_NEG_INF, dtype=cd, device=dev)
    unit = torch.full((K,), _NEG_INF, dtype=cd, device=dev)
    unit[0] = 0.0
    # Transition t maps the message at step t to the one at step t + 1 (t = 0 .. TP - 1).
    log_d = torch.where(before, pad(lp + lc), torch.where(at, neg_inf, 0.0))
    log_c = torch.where(before, pad(lp + lt), torch.where(at, end, neg_inf))
    log_e = torch.where(before, pad(le[:, 1:]), unit)

    # --- 1. compose the chunk transfer matrices in rescaled probability space -------------------------------
    m_e = log_e.amax(-1, keepdim=True)
    m_e = torch.where(torch.isfinite(m_e), m_e, 0.0)
    m = torch.maximum(log_d.amax(-1, keepdim=True), log_c.amax(-1, keepdim=True) + m_e)
    m = torch.where(torch.isfinite(m), m, 0.0)
    d = (log_d - m).exp().view(B * C, L, K)
    c = (log_c + m_e - m).exp().view(B * C, L, K)
    e = (log_e - m_e).exp().view(B * C, L, K)
    P = torch.diag_embed(d[:, 0]) + e[:, 0, :, None] * c[:, 0, None, :]  # [BC, K(out), K(in)]
    log_scales = []
    for i in range(1, L):
        if i % _RENORM_EVERY == 0:
            cm = P.amax(1, keepdim=True)
            cm = torch.where(cm > 0, cm, 1.0)
            P = P / cm
            log_scales.append(cm)
        row = torch.bmm(c[:, i, None, :], P)  # [BC, 1, K]: the switching mass of each column
        P = torch.addcmul(P * d[:, i, :, None], e[:, i, :, None], row)
    cm = P.amax(1, keepdim=True)
    cm = torch.where(cm > 0, cm, 1.0)
    P = P / cm
    log_scales.append(cm)
    col_scale = torch.stack(log_scales, 0).log().sum(0).view(B, C, K)
    col_scale = col_scale + m.view(B, C, L).sum(-1, keepdim=True)
    log_P = P.log().view(B, C, K, K)

    # --- 2. scan across chunks ---------------------------------------------------------------------------
    a, log_lik = _normalise(le[:, 0])
    log_lik = log_lik.squeeze(-1)
    fwd = [a]
    for k in range(C):
        a, z = _normalise(_lse(log_P[:, k] + (col_scale[:, k] + a).unsqueeze(1), -1))
        log_lik = log_lik + z.squeeze(-1)
        fwd.append(a)
    fwd = torch.stack(fwd, 1)  # [B, C + 1, K]: alpha at steps 0, L, 2L, ..., CL
    b = torch.zeros(B, K, dtype=cd, device=dev)
    bwd = [b]
    for k in range(C - 1, -1, -1):
        b, _ = _normalise(_lse(log_P[:, k] + b.unsqueeze(-1), 1) + col_scale[:, k])
        bwd.append(b)
    bwd = torch.stack(bwd[::-1], 1)  # [B, C + 1, K]: beta at steps 0, L, ..., CL

    # --- 3. recover every message, all chunks at once -----------------------------------------------------
    ld4, lc4, le4 = (x.view(B, C, L, K) for x in (log_d, log_c, log_e))
    alpha = torch.empty(B, C, L, K, dtype=cd, device=dev)
    a = fwd[:, :C]
    for i in range(L):
        alpha[:, :, i] = a
        s = _lse(a + lc4[:, :, i], -1, True)
        a, _ = _normalise(torch.logaddexp(s + le4[:, :, i], a + ld4[:, :, i]))
    bad = _mismatch(a, fwd[:, 1:])
    beta = torch.empty(B, C, L, K, dtype=cd, device=dev)
    b = bwd[:, 1:]
    for i in range(L - 1, -1, -1):
        g = _lse(b + le4[:, :, i], -1, True)
        b, _ = _normalise(torch.logaddexp(lc4[:, :, i] + g, ld4[:, :, i] + b))
        beta[:, :, i] = b
    bad = bad | _mismatch(b, bwd[:, :C]) | ~torch.isfinite(log_lik)
    alpha = alpha.view(B, TP, K)[:, :T]
    beta = beta.view(B, TP, K)[:, :T]

    # --- 4. marginals -------------------------------------------------------------------------------------
    valid = mask.unsqueeze(-1)
    u = torch.softmax(alpha + beta, -1)
    u = torch.where(valid, u, 0.0)
    v = torch.zeros_like(u)
    w = torch.zeros_like(u)
    v[:, 0] = u[:, 0]
    if T > 1:
        a_t, b_next = alpha[:, :-1], beta[:, 1:]
        s_in = _lse(a_t + log_c[:, : T - 1], -1, True)
        log_sw = s_in + log_e[:, : T - 1] + b_next
        log_st = a_t + log_d[:, : T - 1] + b_next
        norm = torch.logaddexp(_lse(log_sw, -1, True), _lse(log_st, -1, True))
        vn = mask[:, 1:].unsqueeze(-1)
        v[:, 1:] = torch.where(vn, (log_sw - norm).exp(), 0.0)
        w[:, :-1] = torch.where(vn, (log_st - norm).exp(), 0.0)
    bad = bad | ~torch.isfinite(u).all(-1).all(-1) | ~torch.isfinite(v).all(-1).all(-1) | ~torch.isfinite(w).all(-1).all(-1)
    return log_lik.to(out_dtype), u.to(out_dtype), v.to(out_dtype), w.to(out_dtype), bad


def _mismatch(recovered: Tensor, scanned: Tensor) -> Tensor:
    """[B] rows whose recovered and scanned boundary messages ([B, C, K], normalised logs) disagree."""
    diff = (recovered - scanned).abs()
    top = torch.maximum(recovered, scanned)
    bad = ((diff > _CHECK_TOL) & (top > _CHECK_FLOOR)) | torch.isnan(recovered) | torch.isnan(scanned)
    return bad.flatten(1).any(1)
