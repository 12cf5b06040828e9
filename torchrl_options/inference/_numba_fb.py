"""A compiled CPU forward-backward (Numba): O(K) per step, the time loop in machine code, parallel over the batch.

The reference recursion (:func:`torchrl_options.inference.forward_backward._forward_backward_reference`) takes a
dozen small PyTorch operations per time step, so on a CPU its cost is per-operation overhead, not arithmetic. Here
the whole time loop of one trajectory runs in compiled code that releases the GIL, the batch split into contiguous
blocks of rows across ``torch.get_num_threads()`` Python threads. The transition is rank one plus diagonal,
``M_t = diag(D) + E C^T`` with ``D = pi (1 - psi)`` (stay), ``C = pi psi`` (terminate) and ``E = eta_{t+1}``
(start), so a step costs O(K). Two kernels (:mod:`._numba_kernels`):

**float32 inputs: the float32 kernel** (``fb32_rows``), float32 arithmetic on explicit 8-lane vectors
(:mod:`._simd`), one pass per direction:

1. *Forward, the factors computed on the way*: per step, the shift ``m_t = max_h log pi_t(h)``, the three
   exponentials ``D = exp(log pi + log(1 - psi) - m_t)``, ``C = exp(log pi + log psi - m_t)``,
   ``E = exp(log eta_{t+1})`` (stored, with the message, in a per-step block that stays in the core's cache), then
   ``alpha_{t+1} = ((C . alpha) E + D * alpha) / z_t``; the log-likelihood is ``sum_t (m_t + log z_t)`` plus the end
   factor's, accumulated in float64. The same pass sums the entries it reads: a NaN or +inf among them makes the
   sum NaN or +inf (``-inf + inf`` is NaN), so the inputs' values are checked at no extra cost.
2. *Backward, fused with the marginals and the gradients*: ``beta_t = ((E . beta_{t+1}) C + D * beta_{t+1}) /
   z_t`` (scaled by the forward normalisers, so the chain holds no division and ``sum_h alpha_t beta_t`` stays 1),
   and at each step ``u``, ``v``, ``w`` are written, normalised by the computed ``S_t = sum_h alpha_t beta_t``, and,
   when a gradient will be needed, the four gradients of ``sum(log P)`` (``u``, ``u - w``, ``w``, ``v``: the
   Expectation-Gradient), so that the gradient pass reads nothing back.

The kernel certifies each row: every entry of every normalised message at least 1e-18 (relative to the message's
sum for ``beta``) and every step's normaliser at least 1e-10. Then whatever float32 drops (products below
1.2e-38, exponentials of log-factors more than 87 below the step's shift) is below about 1e-8 relative to any
entry it could have entered. Rows that fail (near-deterministic inputs, and every row with exact zeros, i.e.
``-inf`` log-probabilities) are recomputed by the float64 kernel.

**float64 inputs, and the float32 rows the float32 kernel flags: the float64 kernel** (``fb_rows``), float64
arithmetic inside whatever the inputs' dtype:

1. *Factors*, per transition ``t`` (step ``t`` to ``t + 1``), exponentiated once in float64 after subtracting the
   step's largest log-factor ``m_t``: ``D = exp(log_pi + log_cont - m_t)`` (stay), ``C = exp(log_pi + log_term +
   max log_eta_{t+1} - m_t)`` (terminate) and ``E = exp(log_eta_{t+1} - max log_eta_{t+1})`` (start), the
   exponentials in one flat loop over the row's ``(T - 1) * K`` entries (long enough for the compiler to vectorise
   it).
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

Both kernels read only each row's valid prefix: padding may hold anything.

Compilation: the first call per input dtype compiles the kernels (seconds, once per machine): the kernels are
cached on disk (``cache=True``) where Numba finds a writable place, in this order: ``$NUMBA_CACHE_DIR`` if set, the
package's ``__pycache__`` if writable, the user's cache directory (``~/.cache/numba``). Where none is writable the
kernels are compiled in memory in each process instead (see :mod:`._numba_kernels`).
"""
from __future__ import annotations

import logging
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["numba_available", "numba_e_step", "numba_expectation_gradient", "numba_forward_backward"]

logger = logging.getLogger(__name__)

# Below these the kernel cannot certify float64's precision and flags the row for the reference: a mathematically
# non-zero entry of a normalised message, a step's normaliser, and sum_h alpha_t(h) beta_t(h).
_FLOOR = 1e-150
_Z_FLOOR = 1e-100
_S_FLOOR = 1e-200
# The float32 kernel's certificate (see fb32_rows): what float32 drops (below 1.2e-38 per product, K + 1 products
# per entry) must stay below 1e-8 relative to the entries it enters.
def _tiny32(K: int) -> float:
    return (K + 1) * 1.6e-38 / 1e-8


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


class _OutputBuffers:
    """Recycled output memory for the kernels.

    Each call returns seven fresh ``[B, T, K]`` tensors (``u``, ``v``, ``w`` and the four gradients); from the
    C library they come as memory the operating system must map in again, page by page (at (64, 1000, 8) float32
    that tripled the kernel's time). Here each output is a NumPy array kept in a small pool and handed out through
    ``torch.from_numpy``: the tensor's storage holds a reference to the array, so an array whose only references
    are the pool's is free, and is handed out again for the next call of the same shape and dtype (already mapped
    in). At most ``max_bytes`` are kept; beyond that, outputs are plain new arrays. The memory a caller still holds
    is never reused.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._arrays: dict[tuple, list[np.ndarray]] = {}  # by (shape, dtype)
        self._bytes = 0
        self._lock = threading.Lock()

    def empty(self, shape: tuple[int, ...], dtype) -> Tensor:
        return torch.from_numpy(self.empty_array(shape, dtype))

    def empty_array(self, shape: tuple[int, ...], dtype) -> np.ndarray:
        """The array behind :meth:`empty`'s tensor (the caller wraps it with ``torch.from_numpy``; until then it
        must keep its reference)."""
        key = (shape, np.dtype(dtype))
        with self._lock:
            kept = self._arrays.setdefault(key, [])
            for arr in kept:
                if sys.getrefcount(arr) <= 3:  # the list, ``arr`` here, getrefcount's argument: nobody else
                    return arr
            arr = np.empty(shape, key[1])
            if self._bytes + arr.nbytes > self.max_bytes:  # make room: drop the free arrays of other shapes
                for arrays in self._arrays.values():
                    arrays[:] = [a for a in arrays if sys.getrefcount(a) > 3]
                self._bytes = sum(a.nbytes for arrays in self._arrays.values() for a in arrays)
            if self._bytes + arr.nbytes <= self.max_bytes:
                kept.append(arr)
                self._bytes += arr.nbytes
            return arr

    def clear(self) -> None:
        with self._lock:
            self._arrays = {}
            self._bytes = 0


# 256 MiB: the outputs of a few E-steps of 64 trajectories of 1000 steps with K up to 32 (7.3 MiB per output)
_BUFFERS = _OutputBuffers(256 * 2**20)


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
    """The compiled kernels on CPU inputs (padding is never read).

    Returns ``(log_likelihood, u, v, w, bad)`` in the inputs' dtype; ``bad`` ([B] bool) marks the rows the caller
    must recompute with the reference (their other outputs are meaningless): rows neither kernel could certify,
    and float32 rows with a NaN or +inf among their valid entries.
    """
    res = numba_e_step(log_pi, log_term, log_cont, log_eta, mask, terminal)
    return res.log_likelihood, res.u, res.v, res.w, res.bad | res.invalid


_NO_ROWS = torch.zeros(1, dtype=torch.bool)  # expanded to [B]: no row flagged (read-only)


class NumbaEStep(NamedTuple):
    """What :func:`numba_e_step` returns (see there)."""

    log_likelihood: Tensor
    u: Tensor
    v: Tensor
    w: Tensor
    grads: tuple[Tensor, Tensor, Tensor, Tensor] | None
    bad: Tensor
    invalid: Tensor
    float32_rows_recomputed: int
    clean: bool = False  # no row flagged (``bad``) or invalid: the caller has nothing to recompute or name


def numba_e_step(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor,
    terminal: Tensor,
    *,
    grads: bool = False,
) -> NumbaEStep:
    """The compiled E-step on CPU inputs (padding is never read).

    float32 inputs run the float32 kernel; the rows it cannot certify are recomputed by the float64 kernel. float64
    inputs run the float64 kernel. ``grads``: also return the four gradients of ``sum(log P)`` with respect to
    ``(log_pi, log_term, log_cont, log_eta)`` (``u``, ``u - w`` where log_term enters the likelihood else 0, ``w``,
    ``v``), written by the float32 kernel in its backward pass (``None`` for float64 inputs, whose gradient pass is
    :func:`numba_expectation_gradient`). ``bad`` marks rows the float64 kernel flagged (the caller recomputes them
    with the reference); ``invalid`` float32 rows with a NaN or +inf among the valid entries (the caller names
    them); ``float32_rows_recomputed`` counts the rows the float64 kernel took over from the float32 one.
    """
    k = _kernels()
    B, T, K = log_pi.shape
    # (NumPy for the small bookkeeping: each PyTorch call costs microseconds, tens right after a kernel has streamed
    # its arrays through the caches, and there are a dozen)
    mask_np = mask.numpy()
    lengths_np = np.full(B, T, np.int64) if mask_np.all() else mask_np.sum(1, dtype=np.int64)
    lengths = torch.from_numpy(lengths_np)
    term = terminal.to(torch.bool).contiguous()
    if log_pi.dtype != torch.float32:
        ll, u, v, w, bad = _fb64(k, log_pi, log_term, log_cont, log_eta, lengths, term)
        return NumbaEStep(ll, u, v, w, None, bad, torch.zeros(B, dtype=torch.bool), 0)
    xs = [(x.detach() if x.is_contiguous() else x.detach().contiguous()).numpy().reshape(B, T * K)
          for x in (log_pi, log_term, log_cont, log_eta)]  # fmt: skip
    arrays = [_BUFFERS.empty_array((B, T, K), np.float32) for _ in range(7 if grads else 3)]  # all written by the kernel
    outs = [torch.from_numpy(a) for a in arrays]
    u, v, w = outs[:3]
    flat = [a.reshape(B, T * K) for a in arrays]
    if not grads:
        flat += [np.empty((1, 0), np.float32)] * 4
    ll = np.empty(B)
    status = np.zeros(B, np.int8)
    args = (*xs, T, K, lengths_np, term.numpy(), ll, *flat, grads, status, np.float32(_tiny32(K)), k.EXP_CONSTANTS)
    if not _run_float32_kernel(k, args, lengths_np):  # it did not compile here: the float64 kernel instead
        ll, u, v, w, bad = _fb64(k, log_pi, log_term, log_cont, log_eta, lengths, term)
        g = None
        if grads:
            tw = _term_weight(lengths, term, T).unsqueeze(-1)
            g = (u.clone(), torch.where(tw, u - w, torch.zeros((), dtype=u.dtype)), w.clone(), v.clone())
        return NumbaEStep(ll, u, v, w, g, bad, torch.zeros(B, dtype=torch.bool), 0)
    # after the kernel the interpreter's and PyTorch's code is cold in the caches (each PyTorch call then costs
    # tens of microseconds): the common case, every row certified and valid, takes one status test
    if not status.any():
        return NumbaEStep(torch.from_numpy(ll.astype(np.float32)), u, v, w, tuple(outs[3:]) if grads else None,
                          _NO_ROWS.expand(B), _NO_ROWS.expand(B), 0, True)  # fmt: skip
    ll = torch.from_numpy(ll)
    invalid = torch.from_numpy((status & 2) != 0)
    bad = torch.zeros(B, dtype=torch.bool)
    redo_np = ((status & 1) != 0) & ((status & 2) == 0)
    n_redo = int(redo_np.sum())
    if n_redo:
        rows = torch.from_numpy(np.flatnonzero(redo_np))
        sub = [x.index_select(0, rows) for x in (log_pi, log_term, log_cont, log_eta)]
        ll_r, u_r, v_r, w_r, bad_r = _fb64(k, *sub, lengths[rows].contiguous(), term[rows].contiguous())
        ll[rows] = ll_r.double()
        for out, r in zip((u, v, w), (u_r, v_r, w_r)):
            out[rows] = r
        bad[rows] = bad_r
        if grads:
            gp, gt, gc, ge = outs[3:]
            gp[rows] = u_r
            gc[rows] = w_r
            ge[rows] = v_r
            tw = _term_weight(lengths[rows], term[rows], T).unsqueeze(-1)
            gt[rows] = torch.where(tw, u_r - w_r, torch.zeros((), dtype=u_r.dtype))
    return NumbaEStep(ll.to(torch.float32), u, v, w, tuple(outs[3:]) if grads else None, bad, invalid, n_redo)


def _term_weight(lengths: Tensor, term: Tensor, T: int) -> Tensor:
    """[B, T]: the steps whose log_term enters the likelihood (every valid step but the last, and a terminal row's
    last)."""
    steps = torch.arange(T)
    last = (lengths - 1).unsqueeze(1)
    return (steps < last) | ((steps == last) & term.unsqueeze(1))


_FLOAT32_KERNEL_OK: bool | None = None  # None until the first call compiles (or loads) it


def _run_float32_kernel(k, args, lengths) -> bool:
    """Runs the float32 kernel; ``False`` (once logged) where it cannot be compiled (an unusual Numba or target:
    its vector layer emits plain LLVM IR, so this is not expected), in which case float32 inputs take the float64
    kernel."""
    global _FLOAT32_KERNEL_OK
    import numba

    if _FLOAT32_KERNEL_OK is False or not hasattr(k, "fb32_rows"):  # (another version's kernels, in benchmarks)
        return False
    if _FLOAT32_KERNEL_OK is None:
        try:
            k.fb32_rows.compile(tuple(numba.typeof(a) for a in (*args, 0, 0)))
        except Exception as err:  # numba's compilation errors
            logger.warning("the float32 E-step kernel does not compile here (%s); using the float64 kernel", err)
            _FLOAT32_KERNEL_OK = False
            return False
        _FLOAT32_KERNEL_OK = True
    _run_rows(k.fb32_rows, args, lengths)
    return True


def _fb64(k, log_pi, log_term, log_cont, log_eta, lengths, term):
    """The float64 kernel (any input dtype it is compiled for): ``(ll, u, v, w, bad)``."""
    B, T, K = log_pi.shape
    xs = [x.detach().contiguous().numpy() for x in (log_pi, log_term, log_cont, log_eta)]
    npdt = np.float32 if log_pi.dtype == torch.float32 else np.float64
    u, v, w = (_BUFFERS.empty((B, T, K), npdt) for _ in range(3))  # every entry is written by the kernel
    ll = torch.empty(B, dtype=torch.float64)
    bad = torch.zeros(B, dtype=torch.bool)
    n = lengths.numpy()
    args = (*xs, n, term.numpy(), ll.numpy(), u.numpy(), v.numpy(), w.numpy(), bad.numpy(), _FLOOR, _Z_FLOOR, _S_FLOOR)
    _run_rows(k.fb_rows, args, n)
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
    npdt = np.float32 if u.dtype == torch.float32 else np.float64
    outs = tuple(_BUFFERS.empty((B, T, K), npdt) for _ in range(4))  # every entry is written by the kernel
    args = (g, u.numpy(), v.numpy(), w.numpy(), lengths, term, *(x.numpy() for x in outs))
    _run_rows(k.grad_rows, args, np.full(B, T))
    return outs
