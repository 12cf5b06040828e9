"""The E-step of DDO: exact forward-backward inference of the options' latent chain.

Reference: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep Options",
arXiv:1703.08294 (2017), section 4.2 and appendix A.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from torchrl_options.inference.semiring import backward_step, end_factor, forward_messages, LOG, total

__all__ = [
    "BACKENDS",
    "ForwardBackwardOutput",
    "check_forward_backward_inputs",
    "check_forward_backward_values",
    "forward_backward",
    "numba_available",
    "resolve_backend",
    "triton_available",
]

_NAMES = ("log_pi", "log_term", "log_cont", "log_eta")


@dataclass
class ForwardBackwardOutput:
    """The result of :func:`forward_backward`.

    Attributes:
        log_likelihood (Tensor): ``[B]``, ``log P(xi)`` of each trajectory, up to the dynamics terms (which
            do not depend on the options and cancel). Differentiable: its gradient is the Expectation-Gradient.
        u (Tensor): ``[B, T, K]``, ``u_t(h) = P(h_t = h | xi)``.
        v (Tensor): ``[B, T, K]``, ``v_t(h) = P(b_t = 1, h_t = h | xi)`` (option ``h`` starts at step t).
        w (Tensor): ``[B, T, K]``, ``w_t(h) = P(h_t = h, b_{t+1} = 0 | xi)`` (option ``h`` continues after t).

    ``u``, ``v`` and ``w`` are detached, zero on padding, and ``w`` is zero at each row's last valid step.
    """

    log_likelihood: Tensor
    u: Tensor
    v: Tensor
    w: Tensor


def check_forward_backward_inputs(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor | None = None,
    terminal: bool | Tensor = False,
    *,
    values: bool = True,
) -> tuple[Tensor, Tensor]:
    """Validates the inputs of :func:`forward_backward` and returns ``(mask, terminal)`` as tensors.

    ``values=False`` skips the scan of the four ``[B, T, K]`` tensors for NaN / +inf (the float32 compiled kernel
    checks the values it reads itself, and :func:`forward_backward` then calls :func:`check_forward_backward_values`
    only for the rows it reports).

    Raises:
        ValueError: naming the argument, for a wrong type, dtype, shape or device, an empty batch, a mask that is
            not a non-empty prefix of each row, or NaN / +inf in a valid entry of a log-probability.

    Examples:
        >>> import torch
        >>> x = torch.zeros(2, 3, 4)
        >>> mask, terminal = check_forward_backward_inputs(x, x, x, x)
        >>> mask.shape, terminal.shape
        (torch.Size([2, 3]), torch.Size([2]))
    """
    tensors = (log_pi, log_term, log_cont, log_eta)
    for name, x in zip(_NAMES, tensors):
        if not isinstance(x, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor of shape [B, T, K], got {type(x).__name__}.")
        if x.ndim != 3:
            raise ValueError(f"{name} must have shape [B, T, K] (3 dimensions), got shape {tuple(x.shape)}.")
        if not x.is_floating_point():
            raise ValueError(f"{name} must be a floating point tensor, got dtype {x.dtype}.")
    shape = log_pi.shape
    for name, x in zip(_NAMES[1:], tensors[1:]):
        if x.shape != shape:
            raise ValueError(
                f"{name} has shape {tuple(x.shape)} but log_pi has shape {tuple(shape)}: all four log-probability "
                "tensors must be [B, T, K] with the same B, T and K."
            )
        if x.dtype != log_pi.dtype:
            raise ValueError(f"{name} has dtype {x.dtype} but log_pi has dtype {log_pi.dtype}.")
        if x.device != log_pi.device:
            raise ValueError(f"{name} is on {x.device} but log_pi is on {log_pi.device}.")
    B, T, K = shape
    if B == 0 or T == 0 or K == 0:
        raise ValueError(
            f"log_pi has shape {tuple(shape)}: empty batch; forward_backward needs at least one trajectory (B), "
            "one step (T) and one option (K)."
        )
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool, device=log_pi.device)
    else:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise ValueError(f"mask must be a bool tensor of shape [B, T] = {(B, T)}, got {_describe(mask)}.")
        if mask.shape != (B, T):
            raise ValueError(f"mask must have shape [B, T] = {(B, T)}, got {tuple(mask.shape)}.")
        if mask.device != log_pi.device:
            try:
                mask = mask.to(log_pi.device)
            except (NotImplementedError, RuntimeError):
                raise ValueError(f"mask is on device {mask.device} but log_pi is on {log_pi.device}.") from None
        gaps = mask[:, 1:] & ~mask[:, :-1]
        if gaps.any():
            rows = gaps.any(1).nonzero().flatten().tolist()
            raise ValueError(
                f"mask must mark a prefix of each row as valid (no valid step after a padded one); rows {rows[:10]} "
                "are not prefixes."
            )
        if not mask[:, 0].all():
            rows = (~mask[:, 0]).nonzero().flatten().tolist()
            raise ValueError(f"mask: rows {rows[:10]} have no valid step; every trajectory needs at least one.")
    if isinstance(terminal, Tensor):
        if terminal.dtype != torch.bool or terminal.shape not in ((B,), ()):
            raise ValueError(f"terminal must be a bool or a bool tensor of shape [B] = [{B}], got {_describe(terminal)}.")
        terminal = terminal.to(log_pi.device).expand(B)
    elif isinstance(terminal, bool):
        terminal = torch.full((B,), terminal, dtype=torch.bool, device=log_pi.device)
    else:
        raise ValueError(f"terminal must be a bool or a bool tensor of shape [B], got {type(terminal).__name__}.")
    if values:
        check_forward_backward_values(log_pi, log_term, log_cont, log_eta, mask)
    return mask, terminal


def check_forward_backward_values(log_pi: Tensor, log_term: Tensor, log_cont: Tensor, log_eta: Tensor, mask: Tensor):
    """Raises a ``ValueError`` naming the tensor and the entry ``(b, t, k)`` if a valid entry (``mask``, ``[B, T]``
    bool) of a log-probability is NaN or +inf.

    Examples:
        >>> import torch
        >>> x = torch.zeros(1, 2, 3)
        >>> check_forward_backward_values(x, x, x, x, torch.ones(1, 2, dtype=torch.bool))
    """
    valid = mask.unsqueeze(-1)
    for name, x in zip(_NAMES, (log_pi, log_term, log_cont, log_eta)):
        bad = (torch.isnan(x) | (x == float("inf"))) & valid
        if bad.any():
            where = tuple(bad.nonzero()[0].tolist())
            raise ValueError(
                f"{name} contains NaN or +inf at (b, t, k) = {where}: log-probabilities must be finite or -inf."
            )


def _describe(x) -> str:
    if isinstance(x, Tensor):
        return f"a {x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def _raise_zero_likelihood(rows: list[int]) -> None:
    raise ValueError(
        f"trajectories {rows[:10]} have zero likelihood: at some step no option can produce the action taken "
        "(every option's log_pi, or every path through log_term/log_cont/log_eta, is -inf)."
    )


def _term_weight(mask: Tensor, terminal: Tensor) -> Tensor:
    """[B, T]: the steps whose ``log_term`` enters the likelihood."""
    T = mask.shape[1]
    last = mask.sum(1, keepdim=True) - 1
    steps = torch.arange(T, device=mask.device)
    return (steps < last) | ((steps == last) & terminal.unsqueeze(1))


def _forward_backward_reference(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor,
    terminal: Tensor,
    row_ids: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The reference: normalised log-space forward-backward, one step at a time, O(K) per step: the log semiring's
    :func:`~torchrl_options.inference.semiring.forward_step` and ``backward_step``, shared with :func:`viterbi`.

    Works on inputs whose padding was replaced by zeros. Returns ``(log_likelihood, u, v, w)``. ``row_ids`` (the
    rows' indices in the caller's batch) only serve the zero-likelihood error message.
    """
    T = log_pi.shape[1]
    last = mask.sum(1) - 1
    # After step t the option either terminates (A) or continues (C); both include pi_h(a_t | s_t).
    switch = log_pi + log_term
    stay = log_pi + log_cont
    end, last_idx = end_factor(log_pi, log_term, mask, terminal)  # [B, K]: factor of the last valid step

    # Forward: alpha_t = log phi_t normalised over h; log_z_t the per-step normalisers (their sum is log P).
    alpha, log_z, switch_in = forward_messages(LOG, switch, stay, log_eta)
    valid_next = mask[:, 1:]
    log_likelihood = total(LOG, alpha, log_z, end, last_idx, mask)
    if not torch.isfinite(log_likelihood).all():
        rows = (~torch.isfinite(log_likelihood)).nonzero().flatten()
        _raise_zero_likelihood((rows if row_ids is None else row_ids[rows]).tolist())

    # Backward: beta_t = log P(a_t, s_{t+1}, ... | s_t, h_t), normalised over h at each step.
    betas = [None] * T
    b = end - end.logsumexp(-1, keepdim=True)  # t = T - 1 is either each row's last step or padding
    betas[T - 1] = b
    for t in range(T - 2, -1, -1):
        rec, _ = backward_step(LOG, b, switch[:, t], stay[:, t], log_eta[:, t + 1])
        b = torch.where((last == t).unsqueeze(-1), end, rec)
        b = b - b.logsumexp(-1, keepdim=True)
        betas[t] = b
    beta = torch.stack(betas, 1)

    valid = mask.unsqueeze(-1)
    u = torch.softmax(alpha + beta, -1)
    u = torch.where(valid, u, 0.0)
    v = torch.zeros_like(u)
    w = torch.zeros_like(u)
    v[:, 0] = u[:, 0]
    if T > 1:
        s_in = torch.stack(switch_in, 1)  # [B, T-1, 1]
        log_sw = s_in + log_eta[:, 1:] + beta[:, 1:]  # start option h' at t+1
        log_st = alpha[:, :-1] + stay[:, :-1] + beta[:, 1:]  # keep option h from t to t+1
        norm = torch.cat([log_sw, log_st], -1).logsumexp(-1, keepdim=True)
        vn = valid_next.unsqueeze(-1)
        v[:, 1:] = torch.where(vn, (log_sw - norm).exp(), 0.0)
        w[:, :-1] = torch.where(vn, (log_st - norm).exp(), 0.0)
    return log_likelihood, u, v, w


# Chunked path: process at most this many bytes of transfer matrices ([rows, chunks, K, K] float64) at once.
_CHUNKED_MAX_BYTES = 64 * 2**20
# "auto" uses the reference below this many steps (the chunked path's fixed costs do not pay off), and above this
# many options (composing K x K chunk transfer matrices, O(T K^2) work, then costs more than the reference's T
# sequential steps of O(K) work; measured crossover on 2 CPU cores at T = 1000: K between 16 and 32).
_AUTO_MIN_STEPS = 16
_AUTO_CHUNKED_MAX_K = 24
# Largest K the Triton kernel handles (K is padded to a power of two held in registers).
_TRITON_MAX_K = 128

BACKENDS = ("auto", "reference", "chunked", "numba", "triton")
# Input dtypes the Numba kernel is compiled for.
_NUMBA_DTYPES = (torch.float32, torch.float64)


def _chunked_backend(log_pi, log_term, log_cont, log_eta, mask, terminal):
    """The chunked path of :mod:`._chunked`, by groups of rows to bound memory, with the rows it flags
    recomputed by the reference."""
    from torchrl_options.inference._chunked import choose_chunk_length, chunked_forward_backward

    B, T, K = log_pi.shape
    L = choose_chunk_length(T)
    per_row = -(-T // L) * K * K * 8
    step = max(1, _CHUNKED_MAX_BYTES // per_row)
    outs = []
    for start in range(0, B, step):
        sl = slice(start, start + step)
        outs.append(
            chunked_forward_backward(log_pi[sl], log_term[sl], log_cont[sl], log_eta[sl], mask[sl], terminal[sl], L)
        )
    ll, u, v, w, bad = (torch.cat(x, 0) for x in zip(*outs)) if len(outs) > 1 else outs[0]
    return _recompute_flagged_rows((ll, u, v, w), bad, log_pi, log_term, log_cont, log_eta, mask, terminal)


def _recompute_flagged_rows(outputs, bad, log_pi, log_term, log_cont, log_eta, mask, terminal):
    """Overwrites the rows a fast backend flags (``bad``) with the log-space reference's, which also names the rows
    of zero likelihood and raises."""
    ll, u, v, w = outputs
    if bad.any():
        rows = bad.nonzero().flatten()
        m = mask[rows]
        # the reference reads every entry: its padding must be zeros (the compiled kernels never read it)
        xs = [_zero_padding(x[rows], m) for x in (log_pi, log_term, log_cont, log_eta)]
        ref = _forward_backward_reference(*xs, m, terminal[rows], row_ids=rows)
        for out, r in zip((ll, u, v, w), ref):
            out[rows] = r
    return ll, u, v, w


def _zero_padding(x: Tensor, mask: Tensor) -> Tensor:
    """``x`` with its padding (``~mask``) replaced by zeros, so that nothing (not even NaN) leaks into the valid
    entries of a backend that reads every entry."""
    if mask.all():
        return x
    return torch.where(mask.unsqueeze(-1), x, torch.zeros((), dtype=x.dtype, device=x.device))


def _numba_backend(log_pi, log_term, log_cont, log_eta, mask, terminal, grads=False):
    """The compiled CPU kernels of :mod:`._numba_fb`, with the rows they flag recomputed by the reference (which
    also names the rows of zero likelihood and raises). Returns ``(ll, u, v, w)`` and the four gradients of
    ``sum(log P)`` (``None`` unless ``grads`` and float32 inputs). A float32 row with a NaN or +inf among its valid
    entries raises the ``ValueError`` of :func:`check_forward_backward_values`."""
    from torchrl_options.inference._numba_fb import numba_e_step

    res = numba_e_step(log_pi, log_term, log_cont, log_eta, mask, terminal, grads=grads)
    if res.clean:  # every row certified and valid (the common case): nothing to name or recompute
        return (res.log_likelihood, res.u, res.v, res.w), res.grads
    if res.invalid.any():
        # the error names the entry: scan the rows the kernel reported (the error path only)
        check_forward_backward_values(log_pi, log_term, log_cont, log_eta, mask & res.invalid.unsqueeze(1))
        # not reached unless the kernel's check sum overflowed on huge finite values: recompute those rows
        res = res._replace(bad=res.bad | res.invalid)
    out = (res.log_likelihood, res.u, res.v, res.w)
    out = _recompute_flagged_rows(out, res.bad, log_pi, log_term, log_cont, log_eta, mask, terminal)
    grads_out = res.grads
    if grads_out is not None and res.bad.any():  # the reference's rows: their gradients from their marginals
        rows = res.bad.nonzero().flatten()
        u, v, w = (x[rows] for x in out[1:])
        tw = _term_weight(mask[rows], terminal[rows]).unsqueeze(-1)
        for g, val in zip(grads_out, (u, torch.where(tw, u - w, 0.0), w, v)):
            g[rows] = val
    return out, grads_out


def _triton_backend(log_pi, log_term, log_cont, log_eta, mask, terminal):
    from torchrl_options.inference._triton_fb import triton_forward_backward

    ll, u, v, w = triton_forward_backward(log_pi, log_term, log_cont, log_eta, mask, terminal)
    if not torch.isfinite(ll).all():
        # Only a trajectory of zero likelihood does this: the reference names the rows (and raises).
        rows = (~torch.isfinite(ll)).nonzero().flatten()
        _raise_zero_likelihood(rows.tolist())
    return ll, u, v, w


_BACKENDS = {
    "reference": _forward_backward_reference,
    "chunked": _chunked_backend,
    "numba": _numba_backend,
    "triton": _triton_backend,
}


def numba_available() -> bool:
    """Whether the Numba backend can run: Numba is installed (``pip install torchrl-options[fast]``)."""
    from torchrl_options.inference._numba_fb import numba_available as _available

    return _available()


def triton_available(device: torch.device | str | None = None) -> bool:
    """Whether the Triton backend can run on ``device``: Triton imports and the device is CUDA (or Triton's
    interpreter is on, ``TRITON_INTERPRET=1``, which runs the kernel on the CPU, slowly: for tests only)."""
    from torchrl_options.inference._triton_fb import triton_importable, triton_interpret

    if not triton_importable():
        return False
    if triton_interpret():
        return True
    dev = torch.device(device) if device is not None else None
    return dev is not None and dev.type == "cuda" and torch.cuda.is_available()


def resolve_backend(backend: str, log_pi: Tensor) -> str:
    """The backend that ``forward_backward(..., backend=backend)`` runs for inputs like ``log_pi``.

    ``"auto"``: on CUDA, ``"triton"`` when Triton is available and ``K <= 128``; on the CPU, ``"numba"`` when Numba
    is installed and the dtype is float32 or float64 (fastest at every size measured by
    ``benchmarks/bench_forward_backward.py``); otherwise ``"chunked"`` when there are at least 16 steps and at most
    24 options; otherwise ``"reference"``. An explicit ``"triton"`` without CUDA and Triton, or ``"numba"`` without
    Numba, on a non-CPU tensor or another dtype, raises a ``ValueError``.

    Examples:
        >>> import torch
        >>> resolve_backend("reference", torch.zeros(2, 100, 4))
        'reference'
        >>> resolve_backend("auto", torch.zeros(2, 100, 4)) == ("numba" if numba_available() else "chunked")
        True
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}.")
    B, T, K = log_pi.shape
    if backend == "triton":
        if not triton_available(log_pi.device):
            raise ValueError(
                f"backend='triton' needs Triton and CUDA tensors (got tensors on {log_pi.device}); use 'auto'."
            )
        if K > _TRITON_MAX_K:
            raise ValueError(f"backend='triton' supports K <= {_TRITON_MAX_K} options, got K = {K}.")
        return backend
    if backend == "numba":
        if not numba_available():
            raise ValueError("backend='numba' needs Numba: pip install 'torchrl-options[fast]' (or use 'auto').")
        if log_pi.device.type != "cpu":
            raise ValueError(f"backend='numba' runs on CPU tensors, got tensors on {log_pi.device}; use 'auto'.")
        if log_pi.dtype not in _NUMBA_DTYPES:
            raise ValueError(f"backend='numba' supports float32 and float64 inputs, got {log_pi.dtype}.")
        return backend
    if backend != "auto":
        return backend
    if log_pi.device.type == "cuda" and K <= _TRITON_MAX_K and triton_available(log_pi.device):
        return "triton"
    if log_pi.device.type == "cpu" and log_pi.dtype in _NUMBA_DTYPES and numba_available():
        return "numba"
    return "chunked" if T >= _AUTO_MIN_STEPS and K <= _AUTO_CHUNKED_MAX_K else "reference"


class _ForwardBackward(torch.autograd.Function):
    """log P(xi) with the Expectation-Gradient as its backward: d/dlog_pi = u, d/dlog_eta = v, d/dlog_cont = w,
    d/dlog_term = u - w (u at a terminal row's last step)."""

    @staticmethod
    def forward(ctx, log_pi, log_term, log_cont, log_eta, mask, terminal, backend, grads):
        ctx.grads = None
        if backend == "numba":
            # the float32 kernel writes the gradients for an upstream gradient of 1 in its backward pass when one
            # will be needed (``grads``), so the gradient pass below reads nothing back
            (ll, u, v, w), ctx.grads = _numba_backend(log_pi, log_term, log_cont, log_eta, mask, terminal, grads)
        else:
            ll, u, v, w = _BACKENDS[backend](log_pi, log_term, log_cont, log_eta, mask, terminal)
        ctx.save_for_backward(u, v, w, mask, terminal)
        ctx.mark_non_differentiable(u, v, w)
        # u, v, w take no gradient: without this, autograd would fill three [B, T, K] tensors of zeros for them
        # at every backward call (about 1 ms of the numba backend's forward + gradient at (64, 1000, 8))
        ctx.set_materialize_grads(False)
        ctx.backend = backend
        return ll, u, v, w

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_ll, grad_u, grad_v, grad_w):
        if grad_ll is None:  # not materialised: no gradient reached log_likelihood
            return None, None, None, None, None, None, None, None
        grads, ctx.grads = ctx.grads, None  # used once: a second backward (retain_graph) recomputes them
        if grads is not None:
            # g * u, g * (u - w), g * w, g * v: the kernel wrote the values for g = 1 (u itself, u - w in float32,
            # ...), so scaling them gives exactly the expression below; for g = 1 they are returned as they are
            g = grad_ll.detach().to(grads[0].dtype)
            # (the test in NumPy where it can be: PyTorch calls are slow right after the kernel, see numba_e_step)
            unit = bool((g.numpy() == 1).all()) if g.device.type == "cpu" else bool((g == 1).all())
            if not unit:
                g = g.view(-1, 1, 1)
                for x in grads:
                    x.mul_(g)
            return (*grads, None, None, None, None)
        u, v, w, mask, terminal = ctx.saved_tensors
        if ctx.backend == "numba":
            from torchrl_options.inference._numba_fb import numba_expectation_gradient

            return (*numba_expectation_gradient(grad_ll, u, v, w, mask, terminal), None, None, None, None)
        term_weight = _term_weight(mask, terminal)
        if ctx.backend == "triton":
            from torchrl_options.inference._triton_fb import triton_expectation_gradient

            return (*triton_expectation_gradient(grad_ll, u, v, w, term_weight), None, None, None, None)
        g = grad_ll.view(-1, 1, 1)
        grad_term = torch.where(term_weight.unsqueeze(-1), u - w, 0.0)
        return g * u, g * grad_term, g * w, g * v, None, None, None, None


def forward_backward(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor | None = None,
    terminal: bool | Tensor = False,
    *,
    validate: bool = True,
    backend: str = "auto",
) -> ForwardBackwardOutput:
    r"""Exact posterior over the options' latent chain of demonstration trajectories (the E-step of DDO).

    The generative model (Fox et al., 2017, section 4.1): at t = 0 an option is drawn from the meta-control
    policy ``eta(h | s_0)``; each step the active option h picks ``a_t ~ pi_h(. | s_t)``; after the step it
    terminates with probability ``psi_h(s_{t+1})`` and, if it does, a new option (possibly the same one) is drawn
    from ``eta(. | s_{t+1})``. The latent variables are the options ``h_t`` and the switch indicators ``b_t``
    (``b_0 = 1``).

    The forward pass is the normalised log-space recursion of appendix A, written as a rank-one-plus-diagonal
    transition so that a step costs O(K):

    .. math::
        \phi_{t+1}(h') = \Big(\sum_h \phi_t(h)\,\pi_h(a_t|s_t)\,\psi_h(s_{t+1})\Big)\,\eta(h'|s_{t+1})
                        + \phi_t(h')\,\pi_{h'}(a_t|s_t)\,(1 - \psi_{h'}(s_{t+1})).

    The gradient of ``log_likelihood`` with respect to the four inputs is the Expectation-Gradient of section
    4.2, returned by the backward pass without differentiating through the recursion:
    ``d/dlog_pi = u``, ``d/dlog_eta = v``, ``d/dlog_cont = w`` and ``d/dlog_term = u - w`` (at a row's last valid
    step: ``u`` if ``terminal`` else 0). Training is thus ``(-out.log_likelihood).mean().backward()``.

    Everything stays finite in float32 on very long trajectories: messages are scaled every step, nothing is
    clipped and no epsilon is added; ``-inf`` entries (an option that cannot produce an action) are exact zeros.

    Args:
        log_pi (Tensor): ``[B, T, K]``, ``log pi_h(a_t | s_t)``, each option's log-probability of the action taken.
        log_term (Tensor): ``[B, T, K]``, ``log psi_h(s_{t+1})``: option h terminates after step t.
        log_cont (Tensor): ``[B, T, K]``, ``log(1 - psi_h(s_{t+1}))``.
        log_eta (Tensor): ``[B, T, K]``, ``log eta(h | s_t)``, the meta-control policy.
        mask (Tensor, optional): ``[B, T]`` bool, the valid steps, a non-empty prefix of each row. ``None``: all
            valid. Padding entries of the inputs are ignored (they may hold anything).
        terminal (bool or Tensor): ``True`` or ``[B]`` bool: the trajectory ends with its option terminating, which
            multiplies the likelihood by ``psi_h(s_T)`` (``log_term`` at the row's last valid step).

    Keyword Args:
        validate (bool): check shapes, masks and values and raise a ``ValueError`` naming the argument.
            Defaults to ``True``; turning it off saves a few device synchronisations.
        backend (str): how the recursion is computed; all give the same results (to float rounding) and the same
            gradient. ``"reference"``: one step at a time (T sequential steps of O(K) work). ``"chunked"``: the
            time axis cut into chunks of about ``sqrt(T / 2)`` steps, chunk transfer matrices composed in
            parallel, a scan across chunks, then every message recovered in parallel by the reference's own
            log-space step; rows whose chunk boundaries do not check out (possible only with extreme
            near-deterministic probabilities) are recomputed by the reference (about ``3 sqrt(T)`` sequential
            steps of O(K^2) work, computed in float64). ``"numba"``: compiled CPU kernels (need Numba, the
            ``fast`` extra; float32/float64): the time loop in machine code, scaled probability space, one
            trajectory per thread (``torch.get_num_threads()`` threads). float32 inputs run a float32 kernel on
            8-lane vectors that also writes the gradient and checks the values it reads; the rows it cannot
            certify (near-deterministic inputs) go to a float64 kernel, and the rows that one cannot certify
            (extreme inputs) to the reference. The first call of a session loads or
            compiles the kernel (seconds; see ``docs/performance.md``). ``"triton"``: a fused GPU kernel (CUDA
            and Triton), the time loop inside the kernel, one program per block of rows. ``"auto"`` (default):
            ``"triton"`` for CUDA tensors when Triton is available and K <= 128; on the CPU ``"numba"`` when
            Numba is installed, else ``"chunked"`` when T >= 16 and K <= 24 (above that, composing K x K transfer
            matrices costs more than it saves), else ``"reference"`` (see :func:`resolve_backend`).

    Returns:
        ForwardBackwardOutput: ``log_likelihood`` ``[B]`` and the detached marginals ``u``, ``v``, ``w``
        ``[B, T, K]``.

    Raises:
        ValueError: for bad inputs (see :func:`check_forward_backward_inputs`) and for a trajectory that no option
            can produce (zero likelihood).

    Examples:
        >>> import torch
        >>> from torchrl_options import forward_backward
        >>> B, T, K = 2, 5, 3
        >>> log_pi = torch.randn(B, T, K).log_softmax(-1)
        >>> psi = torch.rand(B, T, K)
        >>> log_eta = torch.full((B, T, K), 1.0 / K).log()
        >>> log_pi.requires_grad_()
        tensor(...)
        >>> out = forward_backward(log_pi, psi.log(), (1 - psi).log(), log_eta)
        >>> out.u.sum(-1)
        tensor([[1.0000, 1.0000, 1.0000, 1.0000, 1.0000],
                [1.0000, 1.0000, 1.0000, 1.0000, 1.0000]])
        >>> out.log_likelihood.sum().backward()
        >>> torch.allclose(log_pi.grad, out.u, atol=1e-6)
        True
    """
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}.")
    if validate:
        # shapes, dtypes, devices and the mask first (cheap); the values' scan after the backend is known
        mask, terminal = check_forward_backward_inputs(log_pi, log_term, log_cont, log_eta, mask, terminal, values=False)
    else:
        B, T, _ = log_pi.shape
        if mask is None:
            mask = torch.ones(B, T, dtype=torch.bool, device=log_pi.device)
        if not isinstance(terminal, Tensor):
            terminal = torch.full((B,), bool(terminal), dtype=torch.bool, device=log_pi.device)
        terminal = terminal.expand(B)
    backend = resolve_backend(backend, log_pi)
    if validate and not (backend == "numba" and log_pi.dtype == torch.float32):
        # the float32 compiled kernel checks the values it reads itself (and raises the same error)
        check_forward_backward_values(log_pi, log_term, log_cont, log_eta, mask)
    if backend != "numba":
        # Padding may hold anything (NaN included): replace it so nothing leaks into the valid entries (the
        # compiled CPU kernels read only each row's valid prefix).
        log_pi, log_term, log_cont, log_eta = (_zero_padding(x, mask) for x in (log_pi, log_term, log_cont, log_eta))
    grads = torch.is_grad_enabled() and any(x.requires_grad for x in (log_pi, log_term, log_cont, log_eta))
    ll, u, v, w = _ForwardBackward.apply(log_pi, log_term, log_cont, log_eta, mask, terminal, backend, grads)
    return ForwardBackwardOutput(log_likelihood=ll, u=u, v=v, w=w)
