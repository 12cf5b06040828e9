"""A fused forward-backward kernel in Triton: the time loop runs inside the kernel.

One program handles ``BLOCK_B`` batch rows; the K options of a row sit in registers (K padded to a power of two,
``KP``). The forward pass walks t = 0 .. T-1 with the reference's normalised log-space recursion and stores the
normalised forward messages ``alpha`` ([B, T, K], the only intermediate that touches memory); the backward pass
walks t = T-1 .. 0, keeps the backward message in registers and writes ``u``, ``v`` and ``w`` directly. Memory
traffic is one read of the four inputs per pass, one write and one read of ``alpha`` and one write of each marginal.

The arithmetic is the reference's (same recursion, same normalisation, log space throughout, no clipping), so -inf
entries are exact zeros and long trajectories stay finite. Triton's interpreter (``TRITON_INTERPRET=1``) runs the
same kernel on the CPU, which is how it is tested without a GPU.
"""
from __future__ import annotations

import os

import torch
from torch import Tensor

__all__ = ["triton_forward_backward", "triton_importable", "triton_interpret"]


def triton_interpret() -> bool:
    """Whether Triton's interpreter is requested (``TRITON_INTERPRET=1``)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def triton_importable() -> bool:
    """Whether ``triton`` can be imported."""
    try:
        import triton  # noqa: F401
        import triton.language  # noqa: F401
    except Exception:
        return False
    return True


_KERNEL = None


def _kernel():
    global _KERNEL
    if _KERNEL is None:
        from torchrl_options.inference._triton_kernels import _fb_kernel

        _KERNEL = _fb_kernel
    return _KERNEL


def _next_pow2(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def triton_forward_backward(
    log_pi: Tensor, log_term: Tensor, log_cont: Tensor, log_eta: Tensor, mask: Tensor, terminal: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The fused kernel on inputs whose padding was replaced by zeros. Returns ``(log_likelihood, u, v, w)``;
    a row of zero likelihood comes back with a non-finite log-likelihood (the caller raises)."""
    B, T, K = log_pi.shape
    log_pi, log_term, log_cont, log_eta = (x.contiguous() for x in (log_pi, log_term, log_cont, log_eta))
    last = mask.sum(1) - 1
    idx = last.view(B, 1, 1).expand(B, 1, K)
    end = log_pi.gather(1, idx) + torch.where(terminal.view(B, 1, 1), log_term.gather(1, idx), 0.0)
    end = end.squeeze(1).contiguous()
    last = last.to(torch.int32).contiguous()
    alpha = torch.empty_like(log_pi)
    u = torch.empty_like(log_pi)
    v = torch.empty_like(log_pi)
    w = torch.empty_like(log_pi)
    ll = torch.empty(B, dtype=log_pi.dtype, device=log_pi.device)
    KP = max(2, _next_pow2(K))
    BLOCK_B = max(1, min(16, 128 // KP, _next_pow2(B)))
    grid = (-(-B // BLOCK_B),)
    _kernel()[grid](
        log_pi, log_term, log_cont, log_eta, end, last, alpha, u, v, w, ll, B, T, K,
        BLOCK_B=BLOCK_B, KP=KP, num_warps=1 if BLOCK_B * KP <= 64 else 2,
    )
    return ll, u, v, w
