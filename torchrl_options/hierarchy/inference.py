"""Exact inference for a level of options over fixed lower levels (call-and-return), linear in T.

Reference: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep Options",
arXiv:1703.08294 (2017), sections 3.4 and 4.3 and appendix A.

The model. Levels are numbered ``1 .. D`` bottom-up; level ``D`` is the one being discovered and levels
``1 .. D-1`` are fixed. A level-``j`` option chooses among the augmented action space of size
``N_j = A + K_1 + ... + K_{j-1}``: index ``a < A`` is a primitive action and index ``A + K_1 + ... + K_{i-1} + k``
invokes option ``k`` of level ``i < j`` (the layout of nested :class:`~torchrl_options.transforms.OptionExecutor`
spaces). The state at step ``t`` is a *call stack*: the active level-``D`` option, the child it invoked, that
child's child, ... down to the option that chose the primitive action ``a_t``. After the step the primitive
returns; an option whose child returned terminates with ``psi(s_{t+1})`` (returning to its caller) or picks a
new child with its control policy at ``s_{t+1}``; when the level-``D`` option terminates the meta-control
``eta(. | s_{t+1})`` picks the next one (``b_0 = 1``: it also picks the first). So an option never terminates
while a child it invoked is running.

The forward recursion is exact and costs O(S) per step, with S the number of stack shapes (``K_2 (1 + K_1)`` for
two levels): pop masses flow up the stack (sums over children), push masses flow down (products along paths).
Messages are normalised in log space every step. The gradient of the log-likelihood, by autograd, is the
Expectation-Gradient (posterior expected counts of every choice and termination event), and the posterior
marginals are gradients with respect to zero biases on the stack states.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import itertools
import logging
import math

import torch
from torch import Tensor

from torchrl_options.checks import check_int
from torchrl_options.inference.semiring import LOG, SAFE_LOG

__all__ = [
    "BACKENDS",
    "HierarchyPosterior",
    "hierarchical_forward_backward",
    "stack_shapes",
]


logger = logging.getLogger(__name__)

BACKENDS = ("auto", "dense", "structured", "chunked")


@dataclass
class HierarchyPosterior:
    """The result of :func:`hierarchical_forward_backward`.

    Lists are indexed by level, bottom-up (``[0]`` is level 1, ``[-1]`` the top level D).

    Attributes:
        log_likelihood (Tensor): ``[B]``, ``log P(xi)`` up to the dynamics terms. Differentiable when the inputs
            are; its gradient is the Expectation-Gradient.
        u (list of Tensor, optional): ``[B, T, K_j]``, ``P(option k of level j is on the call stack at step t | xi)``.
            At the top level the rows sum to 1; below, the missing mass is the probability that no level-``j``
            option runs at that step (a higher option chose a primitive or a lower-level option directly).
        v (list of Tensor, optional): ``[B, T, K_j]``, ``P(option k of level j is invoked at step t | xi)``.
        emitter (Tensor, optional): ``[B, T, D]``, ``P(the primitive a_t was chosen by a level-j option | xi)``.

    Marginals are detached, ``None`` unless asked for, and zero on padding.
    """

    log_likelihood: Tensor
    u: list[Tensor] | None = None
    v: list[Tensor] | None = None
    emitter: Tensor | None = None

    def most_likely(self, level: int) -> Tensor:
        """``[B, T]``: the most likely option of ``level`` (1-based) at each step, ``-1`` on padding."""
        if self.u is None:
            raise ValueError("most_likely needs the marginals: call hierarchical_forward_backward(..., marginals=True).")
        u = self.u[level - 1]
        return torch.where(u.sum(-1) > 0, u.argmax(-1), -1)


def stack_shapes(num_levels: int) -> list[tuple[int, ...]]:
    """The call-stack shapes of a hierarchy of ``num_levels`` levels: tuples of 0-based levels from the top down,
    strictly decreasing, starting with the top level. Sorted by length (callers before callees).

    Examples:
        >>> stack_shapes(3)
        [(2,), (2, 0), (2, 1), (2, 1, 0)]
    """
    check_int(num_levels, "num_levels", minimum=1)
    top = num_levels - 1
    shapes = [(top,)]
    frontier = [(top,)]
    while frontier:
        nxt = [s + (i,) for s in frontier for i in range(s[-1])]
        shapes += nxt
        frontier = nxt
    return sorted(shapes, key=lambda s: (len(s), s))


def _check_inputs(action, log_pi, log_term, log_cont, log_eta, mask, terminal):
    if not isinstance(log_pi, Sequence) or isinstance(log_pi, Tensor) or len(log_pi) == 0:
        raise ValueError("log_pi must be a non-empty list of [B, T, K_j, N_j] tensors, one per level (bottom-up).")
    D = len(log_pi)
    for name, seq in (("log_term", log_term), ("log_cont", log_cont)):
        if not isinstance(seq, Sequence) or isinstance(seq, Tensor) or len(seq) != D:
            raise ValueError(f"{name} must be a list of {D} [B, T, K_j] tensors (one per level, like log_pi).")
    x0 = log_pi[0]
    if not isinstance(x0, Tensor) or x0.ndim != 4 or not x0.is_floating_point():
        raise ValueError(f"log_pi[0] must be a floating point [B, T, K_1, A] tensor, got {_describe(x0)}.")
    B, T, _, A = x0.shape
    if B == 0 or T == 0 or A == 0:
        raise ValueError(f"log_pi[0] has shape {tuple(x0.shape)}: empty batch, trajectory or action space.")
    sizes = []
    n = A
    for j in range(D):
        x = log_pi[j]
        if not isinstance(x, Tensor) or x.ndim != 4 or x.shape[:2] != (B, T) or x.shape[2] == 0:
            raise ValueError(f"log_pi[{j}] (level {j + 1}) must be a [B, T, K_{j + 1}, N] tensor with [B, T] = "
                             f"{[B, T]}, got {_describe(x)}.")
        if x.shape[3] != n:
            parts = " + ".join(["A"] + [f"K_{i + 1}" for i in range(j)])
            values = " + ".join(str(v) for v in [A] + sizes)
            raise ValueError(
                f"log_pi[{j}] (level {j + 1}) has {x.shape[3]} actions in its last dimension, but a level-{j + 1} "
                f"option chooses among {parts} = {values} = {n} (primitive actions and the options of the lower "
                "levels)."
            )
        if x.dtype != x0.dtype or x.device != x0.device:
            raise ValueError(f"log_pi[{j}] has dtype/device {x.dtype}/{x.device}, log_pi[0] {x0.dtype}/{x0.device}.")
        K = x.shape[2]
        for name, seq in (("log_term", log_term), ("log_cont", log_cont)):
            y = seq[j]
            if not isinstance(y, Tensor) or y.shape != (B, T, K) or y.dtype != x0.dtype:
                raise ValueError(
                    f"{name}[{j}] (level {j + 1}) must be a {x0.dtype} tensor of shape [B, T, K_{j + 1}] = "
                    f"{[B, T, K]}, got {_describe(y)}."
                )
        sizes.append(K)
        n += K
    if not isinstance(log_eta, Tensor) or log_eta.shape != (B, T, sizes[-1]) or log_eta.dtype != x0.dtype:
        raise ValueError(
            f"log_eta must be a {x0.dtype} tensor of shape [B, T, K_D] = {[B, T, sizes[-1]]} (the meta-control "
            f"over the top level's options), got {_describe(log_eta)}."
        )
    if not isinstance(action, Tensor) or action.shape != (B, T) or action.is_floating_point():
        raise ValueError(f"action must be an integer tensor of shape [B, T] = {[B, T]}, got {_describe(action)}.")
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool, device=x0.device)
    else:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.shape != (B, T):
            raise ValueError(f"mask must be a bool tensor of shape [B, T] = {[B, T]}, got {_describe(mask)}.")
        if not mask[:, 0].all() or (mask[:, 1:] & ~mask[:, :-1]).any():
            raise ValueError("mask must mark a non-empty prefix of each row as valid (padding at the end only).")
        mask = mask.to(x0.device)
    bad = ((action < 0) | (action >= A)) & mask
    if bad.any():
        raise ValueError(
            f"action holds {int(action[bad][0])}, outside the primitive actions [0, {A}) (A from log_pi[0]): "
            "demonstrations must record primitive actions."
        )
    if isinstance(terminal, bool):
        terminal = torch.full((B,), terminal, dtype=torch.bool, device=x0.device)
    elif isinstance(terminal, Tensor) and terminal.dtype == torch.bool and terminal.shape in ((), (B,)):
        terminal = terminal.to(x0.device).expand(B)
    else:
        raise ValueError(f"terminal must be a bool or a bool tensor of shape [B] = [{B}], got {_describe(terminal)}.")
    valid = mask.view(B, T, 1)
    for name, seq in (("log_pi", log_pi), ("log_term", log_term), ("log_cont", log_cont), ("log_eta", [log_eta])):
        for j, y in enumerate(seq):
            v = valid.view(B, T, *([1] * (y.ndim - 2)))
            if ((torch.isnan(y) | (y == float("inf"))) & v).any():
                raise ValueError(f"{name}[{j}] contains NaN or +inf at a valid step: log-probabilities must be finite or -inf.")
    return A, sizes, mask, terminal


def _describe(x) -> str:
    if isinstance(x, Tensor):
        return f"a {x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def hierarchical_forward_backward(
    action: Tensor,
    log_pi: Sequence[Tensor],
    log_term: Sequence[Tensor],
    log_cont: Sequence[Tensor],
    log_eta: Tensor,
    mask: Tensor | None = None,
    terminal: bool | Tensor = False,
    *,
    marginals: bool = False,
    validate: bool = True,
    backend: str = "auto",
) -> HierarchyPosterior:
    r"""Exact log-likelihood (and posterior marginals) of demonstrations under a hierarchy of options.

    The top level ``D`` is driven by the meta-control ``eta``; the levels below run call-and-return (see the
    module docstring; Fox et al., 2017, sections 3.4 and 4.3). With one level this is the model of
    :func:`~torchrl_options.forward_backward` and gives the same likelihood.

    Per step the forward message is a distribution over call stacks (``(h_D, c_1, c_2, ...)``, the top option
    and the chain of options below it, the last of which chose ``a_t``). Its update is a pop pass,

    .. math::
        M(n) = \alpha_t(n) + \sum_{c \text{ child of } n} \psi_c(s_{t+1}) M(c),

    the mass returned to the option at the bottom of stack ``n`` (its primitive returned, or its child option
    terminated), then a push pass,

    .. math::
        P(n) = (1 - \psi_n(s_{t+1})) M(n) + P(\text{parent}(n))\,\pi_{\text{parent}(n)}(n | s_{t+1}),

    with ``P(root) = sum_h psi_h M(h)`` spread by ``eta(h | s_{t+1})``, and
    ``alpha_{t+1}(n) = P(n) pi_n(a_{t+1} | s_{t+1})``. Both passes are sums over the tree of stack shapes: O(S)
    per step, T sequential steps. Everything is in normalised log space; the gradient comes from autograd
    (the Expectation-Gradient identity holds for any exact forward pass).

    Args:
        action (Tensor): ``[B, T]`` long, the primitive actions taken, in ``[0, A)``.
        log_pi (list of Tensor): per level, bottom-up, ``[B, T, K_j, N_j]``: ``log pi_h(c | s_t)`` of each level-j
            option over its augmented action space ``N_j = A + K_1 + ... + K_{j-1}`` (``N_1 = A``).
        log_term (list of Tensor): per level, ``[B, T, K_j]``: ``log psi_h(s_{t+1})``.
        log_cont (list of Tensor): per level, ``[B, T, K_j]``: ``log(1 - psi_h(s_{t+1}))``.
        log_eta (Tensor): ``[B, T, K_D]``: ``log eta(h | s_t)`` over the top level's options.
        mask (Tensor, optional): ``[B, T]`` bool, a non-empty prefix of each row. Padding may hold anything.
        terminal (bool or Tensor): ``[B]``: the trajectory ends with its top option terminating (which needs
            every option on the stack to terminate at ``s_T``).

    Keyword Args:
        marginals (bool): also return ``u``, ``v`` and ``emitter`` (one extra backward pass through the
            recursion). Defaults to ``False``.
        validate (bool): check the inputs and raise a ``ValueError`` naming the argument. Defaults to ``True``.
        backend (str): ``"dense"``: the S x S transition matrices of all steps built at once (O(S^2 D) memory per
            step), then one log-space matrix-vector product per step: few, larger operations, the faster on
            small hierarchies. ``"structured"``: the pop/push passes over the tree of stack shapes, O(S) per step
            in more, smaller operations, the faster on larger batches. ``"chunked"``: the dense matrices
            multiplied time-parallel (chunks of about ``sqrt(T)`` steps composed at once, then a scan over the
            chunks, in float64 with rescaling): about ``2 sqrt(T)`` sequential steps instead of ``T``, the
            fastest on long trajectories of small batches. ``"auto"`` (default): chunked from 48 steps when
            ``B T S^2 (D + 1) <= 2^24``; otherwise dense when ``B S^2 (D + 1) <= 2^13``, else structured.
            All are exact and give the same results (chunked recomputes with the structured recursion any row
            whose float64 products underflow to a zero likelihood).

    Returns:
        HierarchyPosterior

    Raises:
        ValueError: for inconsistent shapes (``log_pi[j]``'s last dimension must be ``A + K_1 + ... + K_{j-1}``),
            bad masks or actions, or a trajectory of zero likelihood.

    Examples:
        >>> import torch
        >>> B, T, A, K1, K2 = 2, 6, 3, 2, 2
        >>> lp = lambda *s: torch.randn(*s).log_softmax(-1)
        >>> ls = lambda *s: torch.nn.functional.logsigmoid(torch.randn(*s))
        >>> action = torch.randint(A, (B, T))
        >>> out = hierarchical_forward_backward(
        ...     action, [lp(B, T, K1, A), lp(B, T, K2, A + K1)], [ls(B, T, K1), ls(B, T, K2)],
        ...     [ls(B, T, K1), ls(B, T, K2)], lp(B, T, K2), marginals=True)
        >>> out.log_likelihood.shape, out.u[1].shape, out.emitter.shape
        (torch.Size([2]), torch.Size([2, 6, 2]), torch.Size([2, 6, 2]))
        >>> torch.allclose(out.u[1].sum(-1), torch.ones(B, T))
        True
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}.")
    if validate:
        A, sizes, mask, terminal = _check_inputs(action, log_pi, log_term, log_cont, log_eta, mask, terminal)
    else:
        A = log_pi[0].shape[-1]
        sizes = [x.shape[2] for x in log_pi]
        B, T = action.shape
        if mask is None:
            mask = torch.ones(B, T, dtype=torch.bool, device=action.device)
        if isinstance(terminal, bool):
            terminal = torch.full((B,), terminal, dtype=torch.bool, device=action.device)
        terminal = terminal.expand(B)
    if not marginals:
        ll = _forward(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, None, None, backend)
        _check_finite(ll)
        return HierarchyPosterior(ll)

    shapes = stack_shapes(len(sizes))
    B, T = action.shape
    dtype, device = log_eta.dtype, log_eta.device
    with torch.enable_grad():
        node_bias = {s: torch.zeros(B, T, *[sizes[i] for i in s], dtype=dtype, device=device, requires_grad=True)
                     for s in shapes}
        start_bias = {s: torch.zeros_like(node_bias[s], requires_grad=True) for s in shapes}
        ll = _forward(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, node_bias, start_bias,
                      backend)
        _check_finite(ll)
        leaves = [node_bias[s] for s in shapes] + [start_bias[s] for s in shapes]
        grads = torch.autograd.grad(ll.sum(), leaves, retain_graph=ll.requires_grad)
    node = dict(zip(shapes, grads[: len(shapes)]))
    start = dict(zip(shapes, grads[len(shapes):]))
    D = len(sizes)
    u = [torch.zeros(B, T, K, dtype=dtype, device=device) for K in sizes]
    v = [torch.zeros(B, T, K, dtype=dtype, device=device) for K in sizes]
    emitter = torch.zeros(B, T, D, dtype=dtype, device=device)
    for s in shapes:
        g = node[s]
        for pos, level in enumerate(s):
            other = [2 + p for p in range(len(s)) if p != pos]
            u[level] += g.sum(other) if other else g
        last = 2 + len(s) - 1
        v[s[-1]] += start[s].sum(list(range(2, last))) if last > 2 else start[s]
        emitter[:, :, s[-1]] += g.flatten(2).sum(-1)
    if not any(x.requires_grad for x in [*log_pi, *log_term, *log_cont, log_eta]):
        ll = ll.detach()
    return HierarchyPosterior(ll, [x.detach() for x in u], [x.detach() for x in v], emitter.detach())


def _check_finite(ll: Tensor) -> None:
    if not torch.isfinite(ll).all():
        rows = (~torch.isfinite(ll)).nonzero().flatten().tolist()
        raise ValueError(
            f"trajectories {rows[:10]} have zero likelihood: at some step no call stack of the hierarchy can "
            "produce the action taken."
        )


def _nodes(sizes: list[int]) -> list[tuple[tuple[int, int], ...]]:
    """Every call stack, as ((level, option), ...) from the top, in the order of the flattened stack shapes."""
    nodes = []
    for s in stack_shapes(len(sizes)):
        for idx in itertools.product(*[range(sizes[lv]) for lv in s]):
            nodes.append(tuple(zip(s, idx)))
    return nodes


# "auto" picks the dense recursion for small batches (per-step work below this many elements), where its fewer
# operations per step win, as long as its transition tensor stays below _DENSE_MAX_ELEMENTS.
_DENSE_MAX_STEP_ELEMENTS = 2**13
_DENSE_MAX_ELEMENTS = 2**25
# Bounds of the chunked product (see _forward_chunked): e^-200 * 1e-200 and 1e-100 * 1e-200 stay normal float64.
_FACTOR_RANGE = 100.0
_TINY_MATRIX = 1e-200
_TINY_MESSAGE = 1e-100
# ... and the chunked product of the dense matrices from this many steps (fewer sequential steps, same memory)
_CHUNKED_MIN_STEPS = 48
# its float64 step matrices are memory-bound: past about 2^24 elements the structured recursion is faster on a CPU
_CHUNKED_MAX_ELEMENTS = 2**24


def _forward(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, node_bias, start_bias, backend):
    B, T = action.shape

    # Padding may hold anything: zeros keep NaN out of the forward pass and of its gradient.
    def clean(x: Tensor) -> Tensor:
        return torch.where(mask.view(B, T, *([1] * (x.ndim - 2))), x, torch.zeros((), dtype=x.dtype, device=x.device))

    log_pi = [clean(x) for x in log_pi]
    log_term = [clean(x) for x in log_term]
    log_cont = [clean(x) for x in log_cont]
    log_eta = clean(log_eta)
    # the recursion's semiring: -inf entries (impossible choices) need the NaN-free log-sum-exp; finite inputs take
    # the fused one
    inputs = [*log_pi, *log_term, *log_cont, log_eta]
    sr = LOG if all(bool(torch.isfinite(x).all()) for x in inputs) else SAFE_LOG
    if backend == "auto":
        S, D = len(_nodes(sizes)), len(sizes)
        step = B * S * S * (D + 1)
        if T >= _CHUNKED_MIN_STEPS and step * T <= _CHUNKED_MAX_ELEMENTS:
            backend = "chunked"
        elif step <= _DENSE_MAX_STEP_ELEMENTS and step * T <= _DENSE_MAX_ELEMENTS:
            backend = "dense"
        else:
            backend = "structured"
    args = (A, sizes)
    if backend != "chunked":
        run = _forward_dense if backend == "dense" else _forward_structured
        return run(action, log_pi, log_term, log_cont, log_eta, mask, terminal, *args, node_bias, start_bias, sr)
    ll = _forward_chunked(action, log_pi, log_term, log_cont, log_eta, mask, terminal, *args, node_bias, start_bias,
                          sr)  # fmt: skip
    bad = ~torch.isfinite(ll)
    if bool(bad.any()):  # underflow in the float64 transfer matrices (or a zero likelihood): the exact recursion
        rows = bad.nonzero().squeeze(-1)
        logger.debug("chunked forward: %d of %d trajectories recomputed by the structured recursion", len(rows), B)
        pick = lambda x: x[rows]  # noqa: E731
        picked = [None if b is None else {k: pick(v) for k, v in b.items()} for b in (node_bias, start_bias)]
        redo = _forward_structured(
            pick(action), [pick(x) for x in log_pi], [pick(x) for x in log_term], [pick(x) for x in log_cont],
            pick(log_eta), pick(mask), pick(terminal), *args, *picked, sr,
        )  # fmt: skip
        ll = ll.index_put((rows,), redo)
    return ll


def _dense_transitions(action, log_pi, log_term, log_cont, log_eta, mask, A, sizes, node_bias, start_bias, sr,
                       factors=False):  # fmt: skip
    """The S x S log transition matrices of all steps at once: ``(log alpha_0 [B, S], trans [B, T - 1, S, S] or
    None, root_end [B, T, S])``, with ``alpha_{t+1}(n') = sum_n alpha_t(n) exp(trans[t, n, n'])`` and
    ``root_end[t, n]`` the log-probability that every option of stack ``n`` terminates at ``s_{t+1}``.

    The transition from stack n (after step t) to stack n' (at step t+1) goes through the deepest option q still
    running: the options of n below q terminate, q continues (or q is the root: everything terminated), and
    the options of n' below q are invoked. q ranges over the common callers of n and n' (and the root), at most
    D + 1 of them; pop and push costs are suffix sums along the stacks.
    """
    B, T = action.shape
    D = len(sizes)
    nodes = _nodes(sizes)
    S = len(nodes)
    dtype, device = log_eta.dtype, log_eta.device
    level_start = [sum(sizes[:lv]) for lv in range(D)]  # level lv's options in a [sum K] concatenation
    widths = [x.shape[-1] for x in log_pi]
    pi_start = [sum(sizes[i] * widths[i] for i in range(lv)) + sizes[-1] for lv in range(D)]
    offsets = [A + sum(sizes[:i]) for i in range(D)]
    index = {n: i for i, n in enumerate(nodes)}
    bottom, called, depth = [], [], []
    anc = torch.full((S, D), S, dtype=torch.long)
    for i, n in enumerate(nodes):
        lv, o = n[-1]
        bottom.append(level_start[lv] + o)
        if len(n) == 1:
            called.append(o)  # log_eta
        else:
            plv, po = n[-2]
            called.append(pi_start[plv] + po * widths[plv] + offsets[lv] + o)
        depth.append(len(n) - 1)
        for k in range(len(n)):
            anc[i, k] = index[n[: k + 1]]
    # deepest common caller of every pair, -1 when they only share the root
    common = torch.full((S, S), -1, dtype=torch.long)
    for i, n in enumerate(nodes):
        for j, m in enumerate(nodes):
            k = 0
            while k < min(len(n), len(m)) and n[k] == m[k]:
                k += 1
            common[i, j] = k - 1
    depth = torch.tensor(depth)
    levels = torch.arange(D + 1)
    # through q at depth i (i = D: the root) is possible when i <= common depth
    through = (levels[None, None] <= common[..., None]) | (levels == D)[None, None]
    log_through = torch.where(through, 0.0, -float("inf")).to(dtype=dtype, device=device)
    valid_depth = ((levels[None] <= depth[:, None]) | (levels == D)[None]).to(device)  # [S, D + 1]
    anc, bottom, called = anc.to(device), torch.tensor(bottom, device=device), torch.tensor(called, device=device)

    idx = torch.where(mask, action, 0).long()
    emit_levels = [lp.gather(-1, idx.view(B, T, 1, 1).expand(B, T, lp.shape[2], 1)).squeeze(-1) for lp in log_pi]
    emit = torch.cat(emit_levels, -1)[..., bottom]
    term = torch.cat(list(log_term), -1)[..., bottom]
    cont = torch.cat(list(log_cont), -1)[..., bottom]
    call = torch.cat([log_eta] + [lp.flatten(2) for lp in log_pi], -1)[..., called]
    if node_bias is not None:
        emit = emit + torch.cat([node_bias[s].flatten(2) for s in stack_shapes(D)], -1)
        call = call + torch.cat([start_bias[s].flatten(2) for s in stack_shapes(D)], -1)

    zero = torch.zeros(B, T, 1, dtype=dtype, device=device)

    def along_stack(x: Tensor) -> Tensor:
        """[B, T, S] per stack bottom -> [B, T, S, D]: the value at each depth of each stack (0 past its end)."""
        return torch.cat([x, zero], -1)[..., anc]

    def suffix(x: Tensor) -> Tensor:
        """[B, T, S, D] -> [B, T, S, D + 1]: sums over depths >= i (no subtraction: -inf stays exact)."""
        rc = x.flip(-1).cumsum(-1).flip(-1)
        return torch.cat([rc, torch.zeros_like(rc[..., :1])], -1)

    term_sfx = suffix(along_stack(term))
    call_sfx = suffix(along_stack(call))
    cont_at = torch.cat([along_stack(cont), zero.unsqueeze(-1).expand(B, T, S, 1)], -1)
    # pop: terminations below q (depth i) and q's continuation; the root (i = D) sees every option terminate
    pop = torch.cat([term_sfx[..., 1:D + 1] + cont_at[..., :D], term_sfx[..., :1]], -1)
    # push: invocations below q; from the root, the meta-control's choice and every invocation
    push = torch.cat([call_sfx[..., 1:D + 1], call_sfx[..., :1]], -1)
    pop = torch.where(valid_depth, pop, 0.0)
    push = torch.where(valid_depth, push, 0.0)
    if factors:  # the pieces, for a product in probability space: trans = lse_q(pop_q + push'_q + through_q)
        return push[:, 0, :, D] + emit[:, 0], (pop[:, :-1], push[:, 1:] + emit[:, 1:, :, None], through.to(device)), \
            pop[..., D]  # fmt: skip
    trans = None
    if T > 1:
        trans = pop[:, :-1, :, None, :] + push[:, 1:, None, :, :] + log_through
        trans = sr.reduce(trans, -1) + emit[:, 1:, None, :]  # [B, T - 1, S, S]
    # the first message, the transitions, and the end factor (every option on the stack terminates at s_{t+1})
    return push[:, 0, :, D] + emit[:, 0], trans, pop[..., D]


def _forward_dense(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, node_bias, start_bias, sr):
    """The dense transitions (:func:`_dense_transitions`), then one log-space matrix-vector product per step."""
    B, T = action.shape
    alpha, trans, root_end = _dense_transitions(
        action, log_pi, log_term, log_cont, log_eta, mask, A, sizes, node_bias, start_bias, sr
    )
    # per-step views by unbind: indexing [:, t] would make autograd allocate a full-size gradient per step
    trans = trans.unbind(1) if T > 1 else ()
    # Padded steps run on the zeroed inputs (finite) and are dropped below: no per-step masking needed.
    z = sr.reduce(alpha, -1)
    alpha = alpha - z.unsqueeze(-1)
    alphas, log_zs = [alpha], [z]
    for t in range(T - 1):
        new = sr.reduce(alpha.unsqueeze(-1) + trans[t], 1)
        z = sr.reduce(new, -1)
        alpha = new - z.unsqueeze(-1)
        alphas.append(alpha)
        log_zs.append(z)
    return _total(mask, terminal, torch.stack(log_zs, 1), lambda last: sr.reduce(
        _at(torch.stack(alphas, 1), last) + _at(root_end, last), -1), sr)


def _chunk_length(steps: int) -> int:
    """``L ~ sqrt(steps)`` balances the ``L`` composition steps against the ``steps / L`` scan steps."""
    return max(1, min(steps, int(round(math.sqrt(steps)))))


def _forward_chunked(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, node_bias, start_bias,
                     sr, chunk_length=None):  # fmt: skip
    """Time-parallel (chunked) product of the dense transition matrices, in float64 probability space.

    The ``T - 1`` transitions are cut into ``C`` chunks of ``L`` steps. *Compose* (``L`` sequential batched matrix
    products, parallel over rows and chunks): each chunk's transfer matrix, its rows rescaled to a maximum of 1 at
    every step (the log-scales carried apart). *Scan* (``C`` sequential vector-matrix products): the message at
    every chunk boundary, rescaled to a maximum of 1. Sequential steps drop from ``T`` to about ``2 sqrt(T)``.
    Transitions past a row's last valid step are the identity, so the final message is the one at that step.
    Every rescaling factor is a detached constant: the value is exact and autograd differentiates the rest.

    No product may flush a positive entry to zero (float64 has about 700 nats of range). The factors of the step
    matrices stay within ``_FACTOR_RANGE`` nats of their step's largest, the transfer-matrix entries above
    ``_TINY_MATRIX`` and the weighted messages above ``_TINY_MESSAGE`` (relative to their row's largest), or the
    trajectory is marked NaN and :func:`_forward` recomputes it with :func:`_forward_structured`. With those
    bounds every term of every product is a normal float64, so the zero pattern is exact and the result is that
    of the exact recursion up to rounding.
    """
    B, T = action.shape
    log_alpha, (pop, push, through), root_end = _dense_transitions(
        action, log_pi, log_term, log_cont, log_eta, mask, A, sizes, node_bias, start_bias, sr, factors=True
    )
    cd = torch.float64
    last = mask.sum(1) - 1

    def shift_of(x: Tensor, dims) -> Tensor:
        m = x.detach().amax(dims, keepdim=True)
        return torch.where(torch.isfinite(m), m, torch.zeros((), dtype=m.dtype, device=m.device))

    def rescale(x: Tensor) -> tuple[Tensor, Tensor]:
        """x / (its last dimension's max, detached), and the log of that max (1 where the max is 0)."""
        r = x.detach().amax(-1, keepdim=True)
        r = torch.where(r > 0, r, torch.ones((), dtype=cd, device=r.device))
        return x / r, r.log().squeeze(-1)

    m0 = shift_of(log_alpha, -1)
    a, log_r = rescale((log_alpha - m0).to(cd).exp())
    log_scale = m0.squeeze(-1).to(cd) + log_r  # [B]: log alpha = log_scale + log a
    if T > 1:
        steps = T - 1
        L = _chunk_length(steps) if chunk_length is None else max(1, min(int(chunk_length), steps))
        C = -(-steps // L)
        S = pop.shape[2]
        valid = torch.arange(steps, device=action.device)[None] < last[:, None]  # transition t -> t + 1 is used
        # E_t = exp(trans_t - m_t) = sum_q through_q * outer(exp(pop_q - m_pop), exp(push_q - m_push)), in float64:
        # cheaper than the log-space tensor. A factor more than _FACTOR_RANGE nats below its step's largest could
        # flush a product to zero: its row is recomputed exactly.
        m_pop, m_push = shift_of(pop, (-2, -1)), shift_of(push, (-2, -1))
        pop, push = pop - m_pop, push - m_push
        with torch.no_grad():
            far = ((pop < -_FACTOR_RANGE) & (pop > -math.inf)).flatten(1).any(-1)
            far = far | ((push < -_FACTOR_RANGE) & (push > -math.inf)).flatten(1).any(-1)
        pop, push = pop.to(cd).exp(), push.to(cd).exp()
        through = through.to(cd)
        E = sum(through[..., q] * (pop[..., :, None, q] * push[..., None, :, q]) for q in range(through.shape[-1]))
        m = (m_pop + m_push).view(B, steps)
        eye = torch.eye(S, dtype=cd, device=E.device)
        E = torch.where(valid[..., None, None], E, eye)
        m = torch.where(valid, m.to(cd), 0.0)
        if C * L > steps:
            E = torch.cat([E, eye.expand(B, C * L - steps, S, S)], 1)
            m = torch.cat([m, m.new_zeros(B, C * L - steps)], 1)
        E = E.view(B, C, L, S, S).unbind(2)
        log_chunk = m.view(B, C, L).sum(-1)  # [B, C]
        # compose: Q_c = E_{cL} ... E_{cL+L-1} = diag(exp(row_scale)) Q
        Q, row_scale = rescale(E[0])
        lost = far | _below(Q, _TINY_MATRIX)
        for j in range(1, L):
            Q, log_r = rescale(Q @ E[j])
            row_scale = row_scale + log_r
            lost = lost | _below(Q, _TINY_MATRIX)
        # scan over the chunk boundaries
        Q, row_scale, log_chunk = Q.unbind(1), row_scale.unbind(1), log_chunk.unbind(1)
        for c in range(C):
            log_a = torch.where(a.detach() > 0, a.detach(), 1.0).log()
            shift = torch.where(a.detach() > 0, log_a + row_scale[c], -math.inf).amax(-1, keepdim=True)
            shift = torch.where(torch.isfinite(shift), shift, 0.0)
            w = a * (row_scale[c] - shift).clamp(max=700.0).exp()
            lost = lost | _below(w, _TINY_MESSAGE, a.detach() > 0)
            a, log_r = rescale((w.unsqueeze(-2) @ Q[c]).squeeze(-2))
            log_scale = log_scale + shift.squeeze(-1) + log_r + log_chunk[c]
    # the end: terminal rows need every option on the stack to terminate at s_T
    end = torch.where(terminal[:, None], _at(root_end, last), 0.0).to(cd)
    me = shift_of(end, -1)
    total = (a * (end - me).exp()).sum(-1)
    log_total = torch.where(total > 0, total, 1.0).log()  # no 0/0 in the backward of a zero-likelihood row
    log_total = torch.where(total > 0, log_total, -math.inf)
    ll = (log_scale + me.squeeze(-1) + log_total).to(log_alpha.dtype)
    if T > 1:  # rows with (nearly) lost mass are marked non-finite, to be recomputed exactly
        ll = torch.where(lost, torch.full((), math.nan, dtype=ll.dtype, device=ll.device), ll)
    return ll


def _below(x: Tensor, tiny: float, positive: Tensor | None = None) -> Tensor:
    """Per batch row: does ``x`` hold an entry below ``tiny`` where it is positive in exact arithmetic
    (``positive``, default ``x > 0``)? Detached."""
    with torch.no_grad():
        positive = x > 0 if positive is None else positive
        return (positive & (x < tiny)).flatten(1).any(-1)


def _at(x: Tensor, last: Tensor) -> Tensor:
    """``x[b, last[b]]`` for ``x`` of shape ``[B, T, ...]``."""
    index = last.view(-1, 1, *([1] * (x.ndim - 2))).expand(-1, 1, *x.shape[2:])
    return x.gather(1, index).squeeze(1)


def _total(mask: Tensor, terminal: Tensor, log_z: Tensor, root_at, sr) -> Tensor:
    """log P: the per-step normalisers over each row's valid steps, times, for terminal rows, the probability
    that every option on the stack terminates at ``s_T`` (``root_at(last)``; the normalised message sums to 1)."""
    last = mask.sum(1) - 1
    total = torch.where(mask, log_z, 0.0).sum(1)
    return total + torch.where(terminal, root_at(last), 0.0)


def _forward_structured(action, log_pi, log_term, log_cont, log_eta, mask, terminal, A, sizes, node_bias, start_bias, sr):
    """The recursion over the tree of stack shapes, O(S) per step (more, smaller operations per step)."""
    B, T = action.shape
    D = len(sizes)
    shapes = stack_shapes(D)
    offsets = [A + sum(sizes[:i]) for i in range(D)]  # where level i's options start in an augmented space

    def view(x: Tensor, depth: int) -> Tensor:
        # [B, T, ...trailing] -> [B, T, 1 x depth, ...trailing]: broadcast over the callers on the stack
        return x.view(B, T, *([1] * depth), *x.shape[2:])

    # Everything that does not depend on the message, for all steps at once.
    idx = torch.where(mask, action, 0).long()
    emit, term, cont, call = {}, {}, {}, {}
    for s in shapes:
        lv, depth = s[-1], len(s) - 1
        lp = log_pi[lv]
        e = lp.gather(-1, idx.view(B, T, 1, 1).expand(B, T, lp.shape[2], 1)).squeeze(-1)
        emit[s] = view(e, depth)
        term[s] = view(log_term[lv], depth)
        cont[s] = view(log_cont[lv], depth)
        if depth:
            caller = s[-2]
            c = log_pi[caller][..., offsets[lv] : offsets[lv] + sizes[lv]]  # [B, T, K_caller, K_lv]
            call[s] = view(c, depth - 1)
    # per-step views by unbind: indexing [:, t] would make autograd allocate a full-size gradient per step
    emit, term, cont, call = ({s: x.unbind(1) for s, x in d.items()} for d in (emit, term, cont, call))
    eta = log_eta.unbind(1)
    node_bias = None if node_bias is None else {s: x.unbind(1) for s, x in node_bias.items()}
    start_bias = None if start_bias is None else {s: x.unbind(1) for s, x in start_bias.items()}
    children = {s: [c for c in shapes if len(c) == len(s) + 1 and c[:-1] == s] for s in shapes}
    top = shapes[0]
    last = mask.sum(1) - 1
    steps = range(T)

    def step_bias(bias, s, t):
        return 0.0 if bias is None else bias[s][t]

    def push(t: int, root: Tensor | None, resume: dict | None) -> dict:
        """alpha_t (unnormalised) from the mass returned to the root and the resumed options."""
        alpha, chooser = {}, {}
        for s in shapes:
            if len(s) == 1:
                entry = eta[t] if root is None else root.unsqueeze(-1) + eta[t]
            else:
                entry = chooser[s[:-1]].unsqueeze(-1) + call[s][t]
            entry = entry + step_bias(start_bias, s, t)
            p = entry if resume is None else _lse([resume[s], entry])
            chooser[s] = p
            alpha[s] = p + emit[s][t] + step_bias(node_bias, s, t)
        return alpha

    def pop(t: int, alpha: dict) -> tuple[Tensor, dict]:
        """After step t: the mass reaching the root (top option terminated) and each option's resume mass."""
        ret, resume = {}, {}
        for s in reversed(shapes):
            parts = [alpha[s]] + [sr.reduce(ret[c], -1) for c in children[s]]
            m = _lse(parts)
            ret[s] = m + term[s][t]
            resume[s] = m + cont[s][t]
        return sr.reduce(ret[top], -1), resume

    def _lse(xs: list[Tensor]) -> Tensor:
        return xs[0] if len(xs) == 1 else sr.reduce(torch.stack(xs, 0), 0)

    def normalise(alpha: dict) -> tuple[dict, Tensor]:
        z = sr.reduce(torch.cat([a.reshape(B, -1) for a in alpha.values()], -1), -1)
        return {s: a - z.view(B, *([1] * (a.ndim - 1))) for s, a in alpha.items()}, z

    alpha, z = normalise(push(0, None, None))
    roots, log_zs = [], [z]
    for t in steps:
        root, resume = pop(t, alpha)
        roots.append(root)
        if t == T - 1:
            break
        alpha, z = normalise(push(t + 1, root, resume))
        log_zs.append(z)
    return _total(mask, terminal, torch.stack(log_zs, 1), lambda last: _at(torch.stack(roots, 1), last), sr)
