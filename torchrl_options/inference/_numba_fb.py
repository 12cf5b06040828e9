"""A compiled CPU forward-backward (Numba): scaled probability space, O(K) per step, parallel over the batch.

The reference recursion (:func:`torchrl_options.inference.forward_backward._forward_backward_reference`) takes a
dozen small PyTorch operations per time step, so on a CPU its cost is per-operation overhead, not arithmetic. Here
the whole time loop of one trajectory runs in compiled code that releases the GIL, the batch split into contiguous
blocks of rows across ``torch.get_num_threads()`` Python threads, with a row's working set (four ``[T, K]`` float64
buffers) held in the core's cache:

1. *Factors*, per transition ``t`` (step ``t`` to ``t + 1``), exponentiated once in float64 after subtracting the
   step's largest log-factor ``m_t``: ``D = exp(log_pi + log_cont - m_t)`` (stay), ``C = exp(log_pi + log_term +
   max log_eta_{t+1} - m_t)`` (terminate) and ``E = exp(log_eta_{t+1} - max log_eta_{t+1})`` (start), the
   exponentials in one flat loop over the row's ``(T - 1) * K`` entries (long enough for the compiler to vectorise
   it). The transition is rank one plus diagonal, ``M = diag(D) + E C^T``, so a step costs O(K).
2. *Forward*: ``n = (C . a) E + D * a``; ``a`` is normalised every step (its normaliser taken as
   ``(C . a) sum(E) + D . a``, so that only one reduction waits on the previous step) and the log-normalisers (plus
   the shifts ``m_t``) sum to the log-likelihood.
3. *Backward*, fused with the marginals: ``b = (E . b') C + D * b'`` normalised every step, and at each step
   ``u``, ``v``, ``w`` are written from ``a``, ``b`` and the transition's two terms, so the backward messages are
   never stored.

Float64 leaves about 700 nats of room below each step's largest term. The kernel also carries which entries are
mathematically non-zero (from the ``-inf`` pattern of the inputs) and flags a row if a finite log-factor falls
below that room, if any such entry of a normalised message falls below ``1e-150``, a step's normaliser below
``1e-100`` or ``sum_h alpha_t(h) beta_t(h)`` below ``1e-200``: past these, what float64 drops (products below
1e-308) could be a probability that later matters. Flagged rows (extreme, near-deterministic inputs only, and
rows of zero likelihood) are recomputed by the reference in log space by the caller, so the result is always the
reference's to rounding.

Compilation: the first call per input dtype compiles the kernel (a few seconds, once per machine): the kernels are
cached on disk (``cache=True``) where Numba finds a writable place, in this order: ``$NUMBA_CACHE_DIR`` if set, the
package's ``__pycache__`` if writable, the user's cache directory (``~/.cache/numba``). Where none is writable the
kernels are compiled in memory in each process instead (see :mod:`._numba_kernels`).
"""
from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import Tensor

__all__ = ["numba_available", "numba_forward_backward", "numba_expectation_gradient"]

logger = logging.getLogger(__name__)

# Below these the kernel cannot certify float64's precision and flags the row for the reference: a mathematically
# non-zero entry of a normalised message, a step's normaliser, and sum_h alpha_t(h) beta_t(h).
_FLOOR = 1e-150
_Z_FLOOR = 1e-100
_S_FLOOR = 1e-200


_NUMBA = None  # the imported module, False when unavailable, None before the first check


def numba_available() -> bool:
    """Whether Numba imports (the ``fast`` extra: ``pip install torchrl-options[fast]``)."""
    global _NUMBA
    if _NUMBA is None:
        try:
            import numba  # noqa: F401
        except Exception as err:  # ImportError, or a Numba/NumPy version mismatch
            logger.debug("numba unavailable: %s", err)
            _NUMBA = False
        else:
            _NUMBA = numba
    return _NUMBA is not False


_KERNELS = None


def _kernels():
    global _KERNELS
    if _KERNELS is None:
        if not numba_available():
            raise RuntimeError("numba is not installed: pip install 'torchrl-options[fast]'")
        from torchrl_options.inference import _numba_kernels

        _KERNELS = _numba_kernels
    return _KERNELS


def _split_rows(lengths, parts: int) -> list[tuple[int, int]]:
    """Contiguous row ranges with about equal numbers of valid steps (the work), at most ``parts`` of them."""
    B = len(lengths)
    parts = max(1, min(parts, B))
    if parts == 1:
        return [(0, B)]
    cum = np.cumsum(lengths)
    bounds = np.searchsorted(cum, cum[-1] * np.arange(1, parts) / parts, side="left") + 1
    edges = sorted({0, B, *(int(min(max(x, 1), B - 1)) for x in bounds)})
    return list(zip(edges[:-1], edges[1:]))


_POOL: ThreadPoolExecutor | None = None
_POOL_PID = -1  # the process that made _POOL (a forked child has no worker threads: it makes its own)
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


def _run_rows(fn, args, lengths) -> None:
    """``fn(*args, b0, b1)`` over the batch, split across ``torch.get_num_threads()`` threads (the kernels release
    the GIL). Rows are independent, so the result does not depend on the split."""
    global _POOL, _POOL_PID, _POOL_SIZE
    ranges = _split_rows(lengths, torch.get_num_threads())
    if len(ranges) == 1:
        fn(*args, *ranges[0])
        return
    with _POOL_LOCK:
        if _POOL is None or _POOL_PID != os.getpid() or _POOL_SIZE < len(ranges) - 1:
            if _POOL is not None and _POOL_PID == os.getpid():
                _POOL.shutdown(wait=False)
            _POOL_SIZE = len(ranges) - 1
            _POOL = ThreadPoolExecutor(max_workers=_POOL_SIZE, thread_name_prefix="torchrl_options_fb")
            _POOL_PID = os.getpid()
        pool = _POOL
    futures = [pool.submit(fn, *args, b0, b1) for b0, b1 in ranges[1:]]
    fn(*args, *ranges[0])
    for f in futures:
        f.result()


def numba_forward_backward(
    log_pi: Tensor, log_term: Tensor, log_cont: Tensor, log_eta: Tensor, mask: Tensor, terminal: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The compiled kernel on CPU inputs whose padding was replaced by zeros.

    Returns ``(log_likelihood, u, v, w, bad)`` in the inputs' dtype; ``bad`` ([B] bool) marks the rows the caller
    must recompute with the reference (their other outputs are meaningless).
    """
    k = _kernels()
    B, T, K = log_pi.shape
    xs = [x.detach().contiguous().numpy() for x in (log_pi, log_term, log_cont, log_eta)]
    lengths = mask.sum(1).to(torch.int64).contiguous().numpy()
    term = terminal.to(torch.bool).contiguous().numpy()
    u = torch.empty(B, T, K, dtype=log_pi.dtype)  # every entry is written by the kernel
    v = torch.empty_like(u)
    w = torch.empty_like(u)
    ll = torch.empty(B, dtype=torch.float64)
    bad = torch.zeros(B, dtype=torch.bool)
    args = (*xs, lengths, term, ll.numpy(), u.numpy(), v.numpy(), w.numpy(), bad.numpy(), _FLOOR, _Z_FLOOR, _S_FLOOR)
    _run_rows(k.fb_rows, args, lengths)
    return ll.to(log_pi.dtype), u, v, w, bad


def numba_expectation_gradient(
    grad_ll: Tensor, u: Tensor, v: Tensor, w: Tensor, mask: Tensor, terminal: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The gradients of ``sum(grad_ll * log P)`` with respect to ``(log_pi, log_term, log_cont, log_eta)`` in one
    pass over the marginals: ``g u``, ``g (u - w)`` on the steps whose log_term enters the likelihood (all valid
    steps but the last, and the last of a ``terminal`` row) else 0, ``g w`` and ``g v``, with ``g`` the row's
    ``grad_ll``; the values of the PyTorch expression of
    :class:`~torchrl_options.inference.forward_backward._ForwardBackward`."""
    k = _kernels()
    B, T, K = u.shape
    g = grad_ll.detach().to(u.dtype).contiguous().numpy()
    lengths = mask.sum(1).numpy()
    term = terminal.contiguous().numpy()
    outs = tuple(torch.empty_like(u) for _ in range(4))  # every entry is written by the kernel
    args = (g, u.numpy(), v.numpy(), w.numpy(), lengths, term, *(x.numpy() for x in outs))
    _run_rows(k.grad_rows, args, np.full(B, T))
    return outs
