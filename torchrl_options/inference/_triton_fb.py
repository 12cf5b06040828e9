"""A fused forward-backward kernel in Triton: the time loop runs inside the kernel.

One program handles ``BLOCK_B`` batch rows; the K options of a row sit in registers (K padded to a power of two,
``KP``). The forward pass walks t = 0 .. T-1 with the reference's normalised log-space recursion and stores the
normalised forward messages ``alpha`` ([B, T, K], the only intermediate that touches memory); the backward pass
walks t = T-1 .. 0, keeps the backward message in registers and writes ``u``, ``v`` and ``w`` directly. Memory
traffic is one read of the four inputs per pass, one write and one read of ``alpha`` and one write of each marginal.

The arithmetic is the reference's (same recursion, same normalisation, log space throughout, no clipping), so -inf
entries are exact zeros and long trajectories stay finite. Triton's interpreter (``TRITON_INTERPRET=1``) runs the
same kernel on the CPU, which is how it is tested without a GPU.

The kernel keeps its own copy of the step of :mod:`.semiring` (the one scan that the reference forward-backward,
Viterbi and the chunked backend share): it is machine code for the log semiring only, as is the Numba kernel.
"""
from __future__ import annotations

import os

import torch
from torch import Tensor

__all__ = ["triton_expectation_gradient", "triton_forward_backward", "triton_importable", "triton_interpret"]


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


def _kernel():
    from torchrl_options.inference._triton_kernels import _fb_kernel

    return _fb_kernel


def _sm_count(device: torch.device) -> int:
    if device.type != "cuda":
        return 1  # the interpreter: any launch shape is as good
    return torch.cuda.get_device_properties(device).multi_processor_count


def _next_pow2(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def triton_forward_backward(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor,
    terminal: Tensor,
    *,
    block_b: int | None = None,
    num_warps: int | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The fused kernel on inputs whose padding was replaced by zeros. Returns ``(log_likelihood, u, v, w)``;
    a row of zero likelihood comes back with a non-finite log-likelihood (the caller raises).

    ``block_b`` (rows per program, a power of two) and ``num_warps`` override the launch shape chosen from K and B
    (``benchmarks/bench_triton_fb.py`` compares them)."""
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
    if block_b is None:
        # About 128 (row, option) cells per warp; fewer rows per program (down to one warp's worth of cells) when
        # that leaves the GPU with under two programs per multiprocessor. Measured on an H100 (bench_triton_fb.py):
        # (4096, 1000, 16) best at 8 rows x 1 warp, (64, 1000, 8) at 2-4 rows x 1 warp.
        block_b = max(1, min(32, 128 // KP, _next_pow2(B)))
        floor = max(1, 32 // KP)
        while block_b > floor and -(-B // block_b) < 2 * _sm_count(log_pi.device):
            block_b //= 2
    BLOCK_B = block_b
    if BLOCK_B < 1 or BLOCK_B & (BLOCK_B - 1):
        raise ValueError(f"block_b must be a power of two, got {BLOCK_B}.")
    if num_warps is None:
        num_warps = max(1, min(8, BLOCK_B * KP // 128))
    grid = (-(-B // BLOCK_B),)
    _kernel()[grid](
        log_pi, log_term, log_cont, log_eta, end, last, alpha, u, v, w, ll, B, T, K,
        BLOCK_B=BLOCK_B, KP=KP, num_warps=num_warps,
    )
    return ll, u, v, w


def triton_expectation_gradient(
    grad_ll: Tensor, u: Tensor, v: Tensor, w: Tensor, term_weight: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The gradients of ``sum(grad_ll * log P)`` with respect to ``(log_pi, log_term, log_cont, log_eta)`` in one
    pass over the marginals: ``g u``, ``g (u - w)`` where ``term_weight``, ``g w`` and ``g v``, with ``g`` the
    row's ``grad_ll``. The same values as the PyTorch expression, in 7 tensor passes instead of about 13."""
    from torchrl_options.inference._triton_kernels import _grad_kernel

    B, T, K = u.shape
    u, v, w = u.contiguous(), v.contiguous(), w.contiguous()
    g = grad_ll.to(u.dtype).contiguous()
    tw = term_weight.contiguous().view(torch.uint8)
    outs = tuple(torch.empty_like(u) for _ in range(4))
    N = B * T * K
    BLOCK = 1024
    _grad_kernel[(-(-N // BLOCK),)](u, v, w, tw, g, *outs, N, T * K, K, BLOCK=BLOCK, num_warps=4)
    return outs
