"""A time-parallel (chunked) forward-backward for the options' latent chain, in plain PyTorch.

The reference recursion (:func:`torchrl_options.inference.forward_backward._forward_backward_reference`) takes T
sequential steps of a dozen small operations each, so on a CPU it is bound by per-operation overhead. Here the
time axis is cut into ``C`` chunks of ``L`` steps and the work is organised so that every sequential loop runs over
all chunks (and all batch rows) at once:

1. *Compose* (``L`` sequential steps, parallel over rows and chunks): each chunk's transfer matrix
   ``P_c = M_{cL+L-1} ... M_{cL}``, in float64 probability space with every column rescaled (and its log-scale
   carried separately). ``M_t = diag(pi (1 - psi)) + eta_{t+1} (pi psi)^T`` is rank one plus diagonal, so a step
   costs O(K^2) per chunk.
2. *Scan* (``C`` sequential steps, float64): the forward messages at the chunk starts, ``alpha_{(c+1)L} ~ P_c alpha_{cL}``,
   and the backward messages, ``beta_{cL} ~ P_c^T beta_{(c+1)L}``, in log space.
3. *Recover* (``L`` sequential steps, parallel over chunks): every per-step message, by the reference's own
   normalised log-space step (:func:`~torchrl_options.inference.semiring.forward_step` and ``backward_step`` in
   the log semiring, in the inputs' dtype) started from the chunk boundaries.
4. *Check*: each chunk's recovered message one step past its end must agree with the next boundary of the scan
   (in log space, to a tolerance set by the dtype, for entries above e^-600 of the message). Rows that fail (a transfer matrix underflowed
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

from torchrl_options.inference.semiring import backward_step, forward_step, LogSemiring

__all__ = ["chunked_forward_backward", "choose_chunk_length"]

_NEG_INF = float("-inf")
# Boundary check: entries above exp(_CHECK_FLOOR) of a normalised message must agree in log space to
# atol + rtol * |value| (the recovered side carries the rounding of L log-space steps in the inputs' dtype).
_CHECK_FLOOR = -600.0
_CHECK_TOL = {torch.float32: (1e-4, 1e-5), torch.float64: (1e-9, 1e-11)}
# Rescale the columns of the transfer matrices every _RENORM_EVERY composition steps (and at the end): float64
# leaves room for about 700 nats of decay of a column between rescalings.
_RENORM_EVERY = 4


def choose_chunk_length(T: int) -> int:
    """The chunk length L for T steps: a recovery step costs about three composition or scan steps, hence
    ``L ~ sqrt(T / 2)`` balances ``3 L`` against ``2 T / L``."""
    return max(1, min(T, int(round(math.sqrt(T / 2.0)))))


def _lse(x: Tensor, dim: int) -> Tensor:
    """logsumexp over ``dim`` (kept), -inf when all entries are -inf."""
    m = x.amax(dim, keepdim=True)
    m = torch.where(m == _NEG_INF, 0.0, m)
    return (x - m).exp_().sum(dim, keepdim=True).log_().add_(m)


class _InPlaceLogSemiring(LogSemiring):
    """The log semiring with :func:`_lse` (in place, fewer temporaries) as its sum."""

    @staticmethod
    def sum(x: Tensor, dim: int) -> Tensor:
        return _lse(x, dim)


_LOG = _InPlaceLogSemiring()


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
    dt = log_pi.dtype
    dev = log_pi.device
    cd = torch.float64
    L = choose_chunk_length(T) if chunk_length is None else max(1, min(int(chunk_length), T))
    C = -(-T // L)
    TP = C * L  # padded number of transitions (T real or virtual ones, then identities)

    # Internal layout: [time, K, B] (reductions over K run across contiguous rows of B).
    lp, lt, lc, le = (x.permute(1, 2, 0) for x in (log_pi, log_term, log_cont, log_eta))
    last = mask.sum(1) - 1  # [B]
    last_k = last.view(1, 1, B).expand(1, K, B)
    end = lp.gather(0, last_k) + torch.where(terminal, lt.gather(0, last_k), 0.0)  # [1, K, B]
    steps = torch.arange(TP, device=dev).view(TP, 1, 1)
    before, at = steps < last, steps == last  # [TP, 1, B]

    def pad(x: Tensor) -> Tensor:
        return torch.nn.functional.pad(x, (0, 0, 0, 0, 0, TP - x.shape[0])) if x.shape[0] < TP else x

    neg_inf = torch.tensor(_NEG_INF, dtype=dt, device=dev)
    unit = torch.full((K, 1), _NEG_INF, dtype=dt, device=dev)
    unit[0] = 0.0
    # Transition t maps the message at step t to the one at step t + 1 (t = 0 .. TP - 1).
    log_d = torch.where(before, pad(lp + lc), torch.where(at, neg_inf, 0.0))
    log_c = torch.where(before, pad(lp + lt), torch.where(at, end, neg_inf))
    log_e = torch.where(before, pad(le[1:]), unit)

    # --- 1. compose the chunk transfer matrices in rescaled float64 probability space ---------------------
    m_e = log_e.amax(1, keepdim=True)
    m_e = torch.where(torch.isfinite(m_e), m_e, 0.0)
    m = torch.maximum(log_d.amax(1, keepdim=True), log_c.amax(1, keepdim=True) + m_e)
    m = torch.where(torch.isfinite(m), m, 0.0).to(cd)
    m_e = m_e.to(cd)
    d = (log_d.to(cd) - m).exp_().view(C, L, K, B)
    c = (log_c.to(cd) + (m_e - m)).exp_().view(C, L, K, B)
    e = (log_e.to(cd) - m_e).exp_().view(C, L, K, B)
    # P[c, h, j, b]: transfer of chunk c from option j at its start to option h at its end.
    P = e[:, 0, :, None] * c[:, 0, None]
    P.diagonal(0, 1, 2).add_(d[:, 0].transpose(1, 2))
    tmp = torch.empty_like(P)
    row = torch.empty(C, 1, K, B, dtype=cd, device=dev)
    log_scales = []
    for i in range(1, L):
        if i % _RENORM_EVERY == 0:
            cm = P.amax(1, keepdim=True)
            cm = torch.where(cm > 0, cm, 1.0)
            P.div_(cm)
            log_scales.append(cm)
        torch.mul(P, c[:, i, :, None], out=tmp)
        torch.sum(tmp, 1, keepdim=True, out=row)  # the switching mass of each column
        P.mul_(d[:, i, :, None]).addcmul_(e[:, i, :, None], row)
    cm = P.amax(1, keepdim=True)
    cm = torch.where(cm > 0, cm, 1.0)
    P.div_(cm)
    log_scales.append(cm)
    del tmp
    col_scale = torch.stack(log_scales, 0).log_().sum(0)  # [C, 1, K(j), B]
    col_scale = col_scale.add_(m.view(C, L, 1, B).sum(1, keepdim=True)).squeeze(1)  # [C, K, B]
    log_P = P.log_()

    # --- 2. scan across chunks, float64 log space ---------------------------------------------------------
    a = le[0].to(cd)
    z = _lse(a, 0)
    a = a - z
    log_lik = z
    fwd = [a]
    for k in range(C):
        n = _lse(log_P[k] + (col_scale[k] + a).unsqueeze(0), 1).squeeze(1)
        z = _lse(n, 0)
        a = n - z
        log_lik = log_lik + z
        fwd.append(a)
    fwd = torch.stack(fwd, 0)  # [C + 1, K, B]: alpha at steps 0, L, 2L, ..., CL
    b = torch.zeros(K, B, dtype=cd, device=dev)
    bwd = [b]
    for k in range(C - 1, -1, -1):
        n = _lse(log_P[k] + b.unsqueeze(1), 0).squeeze(0) + col_scale[k]
        b = n - _lse(n, 0)
        bwd.append(b)
    bwd = torch.stack(bwd[::-1], 0)  # [C + 1, K, B]: beta at steps 0, L, ..., CL
    del log_P, P

    # --- 3. recover every message, all chunks at once, in the inputs' dtype -------------------------------
    ld4, lc4, le4 = (x.view(C, L, K, B) for x in (log_d, log_c, log_e))
    alpha = torch.empty(C, L, K, B, dtype=dt, device=dev)
    a = fwd[:C].to(dt)
    for i in range(L):
        alpha[:, i] = a
        n, _ = forward_step(_LOG, a, lc4[:, i], ld4[:, i], le4[:, i], dim=1)
        a = n - _lse(n, 1)
    bad = _mismatch(a, fwd[1:], dt)
    beta = torch.empty(C, L, K, B, dtype=dt, device=dev)
    b = bwd[1:].to(dt)
    for i in range(L - 1, -1, -1):
        n, _ = backward_step(_LOG, b, lc4[:, i], ld4[:, i], le4[:, i], dim=1)
        b = n - _lse(n, 1)
        beta[:, i] = b
    bad = bad | _mismatch(b, bwd[:C], dt) | ~torch.isfinite(log_lik.view(B))
    alpha = alpha.view(TP, K, B)[:T]
    beta = beta.view(TP, K, B)[:T]

    # --- 4. marginals, all steps at once --------------------------------------------------------------------
    valid = mask.t().unsqueeze(1)  # [T, 1, B]
    zero = torch.zeros((), dtype=dt, device=dev)
    u = torch.softmax(alpha + beta, 1)
    u = torch.where(valid, u, zero)
    v = torch.empty_like(u)
    w = torch.empty_like(u)
    v[0] = u[0]
    w[T - 1] = 0.0
    if T > 1:
        a_t, b_next = alpha[:-1], beta[1:]
        s_in = _lse(a_t + log_c[: T - 1], 1)
        log_sw = s_in + log_e[: T - 1] + b_next
        log_st = a_t + log_d[: T - 1] + b_next
        norm = torch.logaddexp(_lse(log_sw, 1), _lse(log_st, 1))
        vn = valid[1:]
        torch.where(vn, log_sw.sub_(norm).exp_(), zero, out=v[1:])
        torch.where(vn, log_st.sub_(norm).exp_(), zero, out=w[:-1])
    for x in (u, v, w):
        bad = bad | ~torch.isfinite(x.sum((0, 1)))
    u, v, w = (x.permute(2, 0, 1).contiguous() for x in (u, v, w))
    return log_lik.view(B).to(dt), u, v, w, bad


def _mismatch(recovered: Tensor, scanned: Tensor, dt: torch.dtype) -> Tensor:
    """[B] rows whose recovered ([C, K, B], dtype dt) and scanned (float64) boundary messages, normalised logs,
    disagree."""
    atol, rtol = _CHECK_TOL.get(dt, _CHECK_TOL[torch.float32])
    recovered = recovered.to(scanned.dtype)
    diff = (recovered - scanned).abs()
    top = torch.maximum(recovered, scanned)
    bad = ((diff > atol + rtol * scanned.abs()) & (top > _CHECK_FLOOR)) | torch.isnan(recovered) | torch.isnan(scanned)
    return bad.any(0).any(0)
