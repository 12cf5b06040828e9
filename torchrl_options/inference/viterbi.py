"""Most likely option sequences: Viterbi decoding of the options' latent chain, and posterior argmax."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchrl_options.checks import check_same_device, check_tensor
from torchrl_options.inference.semiring import chunked_forward_messages, end_factor, forward_messages, MAX, total
from torchrl_options.inference.forward_backward import check_forward_backward_inputs

__all__ = ["VITERBI_BACKENDS", "ViterbiOutput", "viterbi", "most_likely_options"]

VITERBI_BACKENDS = ("reference", "chunked")


@dataclass
class ViterbiOutput:
    """The result of :func:`viterbi`.

    Attributes:
        options (Tensor): ``[B, T]`` long, the option active at each step, ``-1`` on padding.
        switches (Tensor): ``[B, T]`` bool, ``b_t``: an option starts at step t (always at t = 0; a new option may
            be the same one again). False on padding.
        log_prob (Tensor): ``[B]``, the joint log-probability of the decoded latent sequence and the trajectory.
    """

    options: Tensor
    switches: Tensor
    log_prob: Tensor


def viterbi(
    log_pi: Tensor,
    log_term: Tensor,
    log_cont: Tensor,
    log_eta: Tensor,
    mask: Tensor | None = None,
    terminal: bool | Tensor = False,
    *,
    backend: str = "reference",
) -> ViterbiOutput:
    """The most likely joint sequence of options and switches ``argmax_zeta P(zeta, xi)`` (max-product).

    Same inputs and model as :func:`~torchrl_options.forward_backward` (Fox et al., 2017, appendix A), with the
    sums replaced by maxima; O(K) per step: the max-plus semiring's scan
    (:func:`~torchrl_options.inference.semiring.forward_messages`, the reference forward-backward's own step), then
    backpointers. Ties prefer continuing the running option (fewer boundaries), then the lowest option index.

    Args:
        log_pi, log_term, log_cont, log_eta (Tensor): ``[B, T, K]``, as in :func:`forward_backward`.
        mask (Tensor, optional): ``[B, T]`` bool prefix mask.
        terminal (bool or Tensor): as in :func:`forward_backward`.

    Keyword Args:
        backend (str): ``"reference"`` (default): ``T`` sequential steps of O(K) work. ``"chunked"``: the same
            max-plus scan by chunks of about ``sqrt(T)`` transitions
            (:func:`~torchrl_options.inference.semiring.chunked_forward_messages`: chunk transfer matrices
            composed in parallel, a scan across chunks, every message recovered in parallel), about ``3 sqrt(T)``
            sequential steps of O(K^2) work: faster on long trajectories with few options. The same sequence and
            log-probability up to float rounding (an exact tie between two sequences may then break the other
            way); the log-probability is the decoded sequence's own.

    Returns:
        ViterbiOutput: the options ``[B, T]``, the switch indicators ``[B, T]`` and the joint log-probability.

    Examples:
        >>> import torch
        >>> from torchrl_options.inference import viterbi
        >>> # option 0 explains the first three actions, option 1 the last three
        >>> log_pi = torch.tensor([[[0.0, -5.0]] * 3 + [[-5.0, 0.0]] * 3])
        >>> half = torch.full_like(log_pi, 0.5).log()
        >>> out = viterbi(log_pi, half, half, half)
        >>> out.options
        tensor([[0, 0, 0, 1, 1, 1]])
        >>> out.switches.nonzero()[:, 1]
        tensor([0, 3])
        >>> torch.equal(viterbi(log_pi, half, half, half, backend="chunked").options, out.options)
        True
    """
    if backend not in VITERBI_BACKENDS:
        raise ValueError(f"backend must be one of {VITERBI_BACKENDS}, got {backend!r}.")
    mask, terminal = check_forward_backward_inputs(log_pi, log_term, log_cont, log_eta, mask, terminal)
    B, T, K = log_pi.shape
    valid = mask.unsqueeze(-1)
    zero = torch.zeros((), dtype=log_pi.dtype, device=log_pi.device)
    log_pi, log_term, log_cont, log_eta = (torch.where(valid, x, zero) for x in (log_pi, log_term, log_cont, log_eta))
    switch = log_pi + log_term
    stay = log_pi + log_cont
    end, last_idx = end_factor(log_pi, log_term, mask, terminal)
    if backend == "reference":
        delta, log_z, switch_in = forward_messages(MAX, switch, stay, log_eta)
        log_prob = total(MAX, delta, log_z, end, last_idx, mask)
        _check_finite(log_prob)
    else:
        delta, switch_in = chunked_forward_messages(MAX, switch, stay, log_eta, round(math.sqrt(T)))
        switch_in = switch_in.unbind(1)

    # the scan's choices, recomputed from its messages for all steps at once (the same operations on the same
    # values): the best option to switch from before step t + 1, and whether each option at t + 1 was started there
    if T > 1:
        best_prev = (delta[:, :-1] + switch[:, :-1]).argmax(-1)  # [B, T - 1]
        from_switch = torch.stack(switch_in, 1) + log_eta[:, 1:] > delta[:, :-1] + stay[:, :-1]  # [B, T - 1, K]
    last = mask.sum(1) - 1
    h = (delta.gather(1, last_idx).squeeze(1) + end).argmax(-1)
    if backend == "reference" or T == 1:
        options, switches = _backtrack(best_prev if T > 1 else None, from_switch if T > 1 else None, last, h)
    else:
        options, switches = _backtrack_chunked(best_prev, from_switch, last, h, round(math.sqrt(T)))
    if backend != "reference":
        log_prob = _sequence_log_prob(options, switches, log_pi, log_term, log_cont, log_eta, mask, terminal)
        _check_finite(log_prob)
    return ViterbiOutput(options=options, switches=switches, log_prob=log_prob)


def _backtrack(best_prev: Tensor | None, from_switch: Tensor | None, last: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """Follows the backpointers from the option ``h`` ``[B]`` at each row's ``last`` step: ``(options, switches)``."""
    B, T = last.shape[0], 1 if best_prev is None else best_prev.shape[1] + 1
    options = torch.full((B, T), -1, dtype=torch.long, device=h.device)
    switches = torch.zeros(B, T, dtype=torch.bool, device=h.device)
    switches[:, 0] = True
    for t in range(T - 1, -1, -1):
        active = t <= last  # steps past a row's end leave the row's pointer where it is
        options[:, t] = torch.where(active, h, -1)
        if t == 0:
            break
        sw = active & from_switch[:, t - 1].gather(1, h.unsqueeze(1)).squeeze(1)
        switches[:, t] = sw
        h = torch.where(sw, best_prev[:, t - 1], h)
    return options, switches


def _backtrack_chunked(best_prev: Tensor, from_switch: Tensor, last: Tensor, h: Tensor, L: int) -> tuple[Tensor, Tensor]:
    """:func:`_backtrack` by chunks of ``L`` transitions: each chunk's pointer map (option at its end to option at
    its start) composed for all chunks at once, a scan across chunks, then every step recovered in parallel."""
    B, T1, K = from_switch.shape  # T1 = T - 1 transitions; transition t points from step t + 1 back to step t
    L = max(1, min(L, T1))
    C = -(-T1 // L)
    steps = torch.arange(C * L, device=h.device).view(1, C * L, 1)
    ident = torch.arange(K, device=h.device).view(1, 1, K)
    pad = (0, 0, 0, C * L - T1)
    live = steps < last.view(B, 1, 1)  # past a row's end the pointer map is the identity
    sw = torch.nn.functional.pad(from_switch, pad) & live  # [B, C L, K]
    f = torch.where(sw, torch.nn.functional.pad(best_prev, pad[2:]).unsqueeze(-1), ident)
    f, sw = f.view(B, C, L, K), sw.view(B, C, L, K)
    G = ident.expand(B, C, K)
    for i in range(L - 1, -1, -1):
        G = f[:, :, i].gather(-1, G)
    ends = [h]  # the option at the end of each chunk, from the last chunk back
    for c in range(C - 1, 0, -1):
        ends.append(G[:, c].gather(-1, ends[-1].unsqueeze(-1)).squeeze(-1))
    g = torch.stack(ends[::-1], 1).unsqueeze(-1)  # [B, C, 1]
    options = torch.empty(B, C, L + 1, dtype=torch.long, device=h.device)
    switches = torch.empty(B, C, L, dtype=torch.bool, device=h.device)
    options[:, :, L] = g.squeeze(-1)
    for i in range(L - 1, -1, -1):
        switches[:, :, i] = sw[:, :, i].gather(-1, g).squeeze(-1)
        g = f[:, :, i].gather(-1, g)
        options[:, :, i] = g.squeeze(-1)
    # step c L + i is options[:, c, i]; the end of the last chunk, step C L, is options[:, -1, L]
    opts = torch.cat([options[:, :, :L].reshape(B, C * L), options[:, -1, L:]], 1)[:, : T1 + 1]
    valid = torch.arange(T1 + 1, device=h.device) <= last.unsqueeze(1)
    opts = torch.where(valid, opts, -1)
    switch = torch.cat([torch.ones(B, 1, dtype=torch.bool, device=h.device), switches.reshape(B, C * L)[:, :T1]], 1)
    return opts, switch & valid


def _check_finite(log_prob: Tensor) -> None:
    if not torch.isfinite(log_prob).all():
        rows = (~torch.isfinite(log_prob)).nonzero().flatten().tolist()
        raise ValueError(f"trajectories {rows[:10]} have zero likelihood under every option sequence.")


def _sequence_log_prob(options, switches, log_pi, log_term, log_cont, log_eta, mask, terminal) -> Tensor:
    """``[B]``: ``log P(zeta, xi)`` of the latent sequences ``(options, switches)`` (inputs with zeroed padding)."""
    h = options.clamp(min=0).unsqueeze(-1)
    at = lambda x: x.gather(-1, h).squeeze(-1)  # noqa: E731
    prev = torch.cat([h[:, :1], h[:, :-1]], 1)
    leave = torch.where(switches, log_term.roll(1, 1).gather(-1, prev).squeeze(-1) + at(log_eta),
                        log_cont.roll(1, 1).gather(-1, prev).squeeze(-1))  # fmt: skip
    leave[:, 0] = at(log_eta)[:, 0]
    last = (mask.sum(1) - 1).unsqueeze(1)
    end = torch.where(terminal, at(log_term).gather(1, last).squeeze(1), 0.0)
    return torch.where(mask, at(log_pi) + leave, 0.0).sum(1) + end


def most_likely_options(u: Tensor, mask: Tensor | None = None) -> Tensor:
    """The posterior argmax ``argmax_h u_t(h)`` per step, ``-1`` on padding.

    Args:
        u (Tensor): ``[B, T, K]`` posterior marginals (from :func:`forward_backward`).
        mask (Tensor, optional): ``[B, T]`` bool.

    Raises:
        ValueError: ``u`` is not a ``[B, T, K]`` floating point tensor with ``K >= 1`` or holds NaN at a valid step;
            ``mask`` is not a ``[B, T]`` bool tensor on ``u``'s device (``TypeError`` for a non-tensor).

    Examples:
        >>> import torch
        >>> most_likely_options(torch.tensor([[[0.9, 0.1], [0.2, 0.8]]]))
        tensor([[0, 1]])
    """
    check_tensor(u, "u", ndim=3, dtype="floating", owner="most_likely_options")
    B, T, K = u.shape
    if K == 0:
        raise ValueError("most_likely_options: u must hold K >= 1 options in its last dimension, got shape [B, T, 0].")
    if mask is not None:
        check_tensor(mask, "mask", shape=(B, T), dtype="bool", owner="most_likely_options")
        check_same_device({"u": u, "mask": mask}, "most_likely_options")
    bad = torch.isnan(u).any(-1)
    if mask is not None:
        bad = bad & mask
    if bad.any():
        b, t = bad.nonzero()[0].tolist()
        raise ValueError(f"most_likely_options: u holds NaN at (b, t) = ({b}, {t}); the marginals must be numbers.")
    out = u.argmax(-1)
    if mask is not None:
        out = torch.where(mask, out, -1)
    return out
