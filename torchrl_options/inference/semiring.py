"""One semiring-parameterised recursion for the options' latent chain (Fox et al., 2017, appendix A).

The options-HMM step is rank one plus diagonal: every option feeds one "switch" mass, which the meta-control
policy redistributes, and each option also continues on its own,

.. math::
    \\alpha_{t+1}(h') = \\Big(\\bigoplus_h \\alpha_t(h) \\otimes \\mathrm{sw}_t(h)\\Big) \\otimes \\eta_{t+1}(h')
                       \\oplus \\alpha_t(h') \\otimes \\mathrm{st}_t(h'),

with ``sw = log pi + log psi`` and ``st = log pi + log(1 - psi)``. In the log semiring (``oplus`` = log-sum-exp,
``otimes`` = ``+``) the scan's total is ``log P(xi)`` and its gradient with respect to the inputs is the
posterior marginals (``d/dlog_pi = u``, ``d/dlog_eta = v``, ``d/dlog_cont = w``), as in pytorch-struct; in the
max-plus semiring (``oplus`` = max) the total is the Viterbi score and its gradient is the indicator of the best
latent sequence. :func:`forward_step` and :func:`backward_step` are the one step that the reference
forward-backward (:mod:`.forward_backward`), Viterbi (:mod:`.viterbi`) and the chunked backend's recovery
(:mod:`._chunked`) run; the hierarchical recursion
(:mod:`torchrl_options.hierarchy.inference`) takes its semiring (:data:`LOG` or :data:`SAFE_LOG`) as an argument
too, its marginals by autograd. The compiled kernels (:mod:`._numba_kernels`, :mod:`._triton_kernels`) are machine code
for the log semiring only and keep their own copy of the step.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["LOG", "MAX", "SAFE_LOG", "Semiring", "backward_step", "chunked_forward_messages", "end_factor", "forward_messages", "forward_step", "scan_score", "total"]


class Semiring:
    """The ``oplus`` of a semiring on log-scores (``otimes`` is ``+`` in both): :attr:`LOG` and :attr:`MAX`.

    Examples:
        >>> import torch
        >>> x = torch.tensor([[0.0, 0.0]])
        >>> LOG.sum(x, -1), MAX.sum(x, -1)
        (tensor([[0.6931]]), tensor([[0.]]))
    """

    name = "semiring"

    @staticmethod
    def sum(x: Tensor, dim: int) -> Tensor:
        """``oplus`` over ``dim`` (kept)."""
        raise NotImplementedError

    @staticmethod
    def plus(x: Tensor, y: Tensor) -> Tensor:
        """``x oplus y``."""
        raise NotImplementedError

    def reduce(self, x: Tensor, dim: int) -> Tensor:
        """``oplus`` over ``dim`` (removed)."""
        return self.sum(x, dim).squeeze(dim)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class LogSemiring(Semiring):
    """Log-sum-exp and ``+``: sums over latent sequences (the likelihood, marginals by its gradient)."""

    name = "log"

    @staticmethod
    def sum(x: Tensor, dim: int) -> Tensor:
        return x.logsumexp(dim, keepdim=True)

    @staticmethod
    def plus(x: Tensor, y: Tensor) -> Tensor:
        return torch.logaddexp(x, y)

    def reduce(self, x: Tensor, dim: int) -> Tensor:
        return x.logsumexp(dim)


class SafeLogSemiring(LogSemiring):
    """:class:`LogSemiring` whose sum's gradient stays finite (zero) on groups that are all ``-inf``.

    ``torch.logsumexp`` back-propagates ``exp(-inf - (-inf)) = NaN`` there; such groups (states that nothing can
    reach) only appear when some log-probabilities are exactly ``-inf``. Slower: for such inputs only.

    Examples:
        >>> import torch
        >>> x = torch.full((1, 2), -float("inf"), requires_grad=True)
        >>> SAFE_LOG.reduce(x, -1).sum().backward()
        >>> x.grad
        tensor([[0., 0.]])
    """

    name = "safe_log"

    @staticmethod
    def sum(x: Tensor, dim: int) -> Tensor:
        m = x.detach().amax(dim, keepdim=True)
        m = torch.where(torch.isfinite(m), m, torch.zeros((), dtype=x.dtype, device=x.device))
        s = (x - m).exp().sum(dim, keepdim=True)
        pos = s > 0
        out = m + torch.where(pos, s, torch.ones((), dtype=s.dtype, device=s.device)).log()
        return torch.where(pos, out, torch.full((), -float("inf"), dtype=x.dtype, device=x.device))

    def reduce(self, x: Tensor, dim: int) -> Tensor:
        return self.sum(x, dim).squeeze(dim)


class MaxSemiring(Semiring):
    """Max and ``+``: the best latent sequence. Ties go to the first index of a ``sum`` and to ``y`` in
    ``plus(x, y)`` (the gradient follows the same choice), so that the recursion's ``plus(switch, keep)`` prefers
    continuing the running option."""

    name = "max"

    @staticmethod
    def sum(x: Tensor, dim: int) -> Tensor:
        return x.max(dim, keepdim=True).values

    @staticmethod
    def plus(x: Tensor, y: Tensor) -> Tensor:
        return torch.where(x > y, x, y)


LOG = LogSemiring()
SAFE_LOG = SafeLogSemiring()
MAX = MaxSemiring()


def forward_step(
    sr: Semiring, a: Tensor, switch: Tensor, stay: Tensor, eta_next: Tensor, dim: int = -1
) -> tuple[Tensor, Tensor]:
    """One forward step ``[..., K] -> [..., K]`` (unnormalised) and the switch mass ``[..., 1]`` that feeds it
    (options along ``dim``).

    Examples:
        >>> import torch
        >>> a = torch.zeros(1, 2).log_softmax(-1)  # uniform over two options
        >>> half = torch.full((1, 2), 0.5).log()
        >>> n, s = forward_step(LOG, a, half, half, half)
        >>> n.exp()  # pi = 1: stay 1/2 + switch 1/2 * eta 1/2
        tensor([[0.5000, 0.5000]])
    """
    s = sr.sum(a + switch, dim)
    return sr.plus(s + eta_next, a + stay), s


def backward_step(
    sr: Semiring, b: Tensor, switch: Tensor, stay: Tensor, eta_next: Tensor, dim: int = -1
) -> tuple[Tensor, Tensor]:
    """One backward step (the transpose of :func:`forward_step`) and the start mass ``[..., 1]`` it uses.

    Examples:
        >>> import torch
        >>> half = torch.full((1, 2), 0.5).log()
        >>> n, g = backward_step(MAX, torch.zeros(1, 2), half, half, half)
        >>> n.exp()
        tensor([[0.5000, 0.5000]])
    """
    g = sr.sum(eta_next + b, dim)
    return sr.plus(switch + g, stay + b), g


def _const(x: Tensor) -> Tensor:
    """``x`` as a constant for autograd (detached only when it needs it: the reference runs without a graph)."""
    return x.detach() if x.requires_grad else x


def forward_messages(sr: Semiring, switch: Tensor, stay: Tensor, log_eta: Tensor) -> tuple[Tensor, Tensor, list[Tensor]]:
    """The forward recursion over ``[B, T, K]`` inputs (padding already zeroed), normalised by ``oplus`` at every
    step: the messages ``[B, T, K]``, the normalisers ``[B, T]`` and the switch masses of steps ``1 .. T - 1``.

    Steps past a row's end are computed like the others (on the zeroed padding); the caller reads each row up to
    its last valid step. The normalisers are constants for autograd: they shift every latent sequence alike, so the
    gradient of the total stays the marginals (log) or the best sequence's indicator (max).
    """
    T = switch.shape[1]
    a = log_eta[:, 0]
    z = sr.sum(_const(a), -1)
    a = a - z
    alphas, log_zs, switch_in = [a], [z], []
    for t in range(T - 1):
        n, s = forward_step(sr, a, switch[:, t], stay[:, t], log_eta[:, t + 1])
        z = sr.sum(_const(n), -1)
        a = n - z
        alphas.append(a)
        log_zs.append(z)
        switch_in.append(s)
    return torch.stack(alphas, 1), torch.cat(log_zs, 1), switch_in


def end_factor(log_pi: Tensor, log_term: Tensor, mask: Tensor, terminal: Tensor) -> tuple[Tensor, Tensor]:
    """``(end, last_idx)``: the factor ``[B, K]`` of each row's last valid step (``log pi``, plus ``log psi`` for a
    terminal row) and the ``[B, 1, K]`` index of that step."""
    B, _, K = log_pi.shape
    last_idx = (mask.sum(1) - 1).view(B, 1, 1).expand(B, 1, K)
    end_term = torch.where(terminal.unsqueeze(-1), log_term.gather(1, last_idx).squeeze(1), 0.0)
    return log_pi.gather(1, last_idx).squeeze(1) + end_term, last_idx


def total(sr: Semiring, alpha: Tensor, log_z: Tensor, end: Tensor, last_idx: Tensor, mask: Tensor) -> Tensor:
    """``[B]``: the ``oplus`` over all latent sequences of each row, from :func:`forward_messages`' outputs."""
    log_z = torch.cat([log_z[:, :1], torch.where(mask[:, 1:], log_z[:, 1:], 0.0)], 1)
    return log_z.sum(1) + sr.sum(alpha.gather(1, last_idx).squeeze(1) + end, -1).squeeze(-1)


def scan_score(
    sr: Semiring, log_pi: Tensor, log_term: Tensor, log_cont: Tensor, log_eta: Tensor, mask: Tensor, terminal: Tensor
) -> Tensor:
    """``[B]``: ``log P(xi)`` (:data:`LOG`) or ``max_zeta log P(zeta, xi)`` (:data:`MAX`) of ``[B, T, K]`` inputs
    whose padding was zeroed, differentiable: its gradient is the posterior marginals (log) or the indicator of the
    best latent sequence (max).

    Examples:
        >>> import torch
        >>> B, T, K = 1, 4, 2
        >>> log_pi = torch.randn(B, T, K).log_softmax(-1).requires_grad_()
        >>> psi = torch.full((B, T, K), 0.3)
        >>> args = (log_pi, psi.log(), (1 - psi).log(), torch.full((B, T, K), 0.5).log(),
        ...         torch.ones(B, T, dtype=torch.bool), torch.zeros(B, dtype=torch.bool))
        >>> best = scan_score(MAX, *args)
        >>> path = torch.autograd.grad(best.sum(), log_pi)[0]  # one option per step
        >>> path.sum(-1)
        tensor([[1., 1., 1., 1.]])
    """
    alpha, log_z, _ = forward_messages(sr, log_pi + log_term, log_pi + log_cont, log_eta)
    end, last_idx = end_factor(log_pi, log_term, mask, terminal)
    return total(sr, alpha, log_z, end, last_idx, mask)


def chunked_forward_messages(
    sr: Semiring, switch: Tensor, stay: Tensor, log_eta: Tensor, chunk_length: int
) -> tuple[Tensor, Tensor]:
    """:func:`forward_messages` by chunks, for any semiring: the messages ``[B, T, K]`` (each normalised by
    ``oplus``, up to float rounding the same as :func:`forward_messages`') and the switch masses ``[B, T - 1, 1]``.

    The ``T - 1`` transitions are cut into ``C`` chunks of ``L = chunk_length``; each chunk's transfer matrix (the
    semiring product of its ``L`` steps, in float64 log space) is composed for all chunks at once by
    :func:`forward_step` with the start option as a batch dimension (``L`` sequential steps), a scan across chunks
    gives the messages at the chunk starts (``C`` steps), and :func:`forward_step` recovers every message from them,
    all chunks at once (``L`` steps): about ``2 L + C`` sequential steps instead of ``T``, each of O(K^2) work for
    the composition.

    Examples:
        >>> import torch
        >>> x = torch.randn(2, 30, 3, dtype=torch.float64).log_softmax(-1)
        >>> ref, _, ref_s = forward_messages(MAX, x, x - 1, x - 2)
        >>> alpha, s = chunked_forward_messages(MAX, x, x - 1, x - 2, chunk_length=4)
        >>> torch.allclose(alpha, ref), torch.allclose(s, torch.stack(ref_s, 1))
        (True, True)
    """
    B, T, K = switch.shape
    L = max(1, min(int(chunk_length), max(T - 1, 1)))
    C = -(-(T - 1) // L) if T > 1 else 1
    TP = C * L

    def chunks(x: Tensor) -> Tensor:  # transitions 0 .. T - 2, zero-padded to C L, as [B, C, L, K]
        return torch.nn.functional.pad(x, (0, 0, 0, TP - x.shape[1])).view(B, C, L, K)

    sw, st, en = chunks(switch[:, : T - 1]), chunks(stay[:, : T - 1]), chunks(log_eta[:, 1:])
    cd = torch.float64
    # P[b, c, h, j]: the semiring weight of reaching option h after chunk c from option j at its start
    P = torch.full((K, K), float("-inf"), dtype=cd, device=switch.device).fill_diagonal_(0.0).expand(B, C, K, K)
    for i in range(L):
        P, _ = forward_step(sr, P, *(x[:, :, i, :, None].to(cd) for x in (sw, st, en)), dim=-2)
    a = log_eta[:, 0].to(cd)
    a = a - sr.sum(_const(a), -1)
    starts = [a]
    for c in range(C - 1):
        n = sr.reduce(P[:, c] + a.unsqueeze(-2), -1)
        a = n - sr.sum(_const(n), -1)
        starts.append(a)
    a = torch.stack(starts, 1).to(switch.dtype)  # [B, C, K]: the messages at steps 0, L, 2L, ...
    alphas, switch_in = [], []
    for i in range(L):
        alphas.append(a)
        n, s = forward_step(sr, a, sw[:, :, i], st[:, :, i], en[:, :, i])
        a = n - sr.sum(_const(n), -1)
        switch_in.append(s)
    alphas.append(a)
    alpha = torch.stack(alphas[:L], 2).view(B, TP, K)
    alpha = torch.cat([alpha, alphas[L][:, -1:]], 1)[:, :T]  # the last chunk's end is step C L
    return alpha, torch.stack(switch_in, 2).view(B, TP, 1)[:, : T - 1]
