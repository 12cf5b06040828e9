"""Most likely option sequences: Viterbi decoding of the options' latent chain, and posterior argmax."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchrl_options.inference._semiring import chunked_forward_messages, end_factor, forward_messages, MAX, total
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
    (:func:`~torchrl_options.inference._semiring.forward_messages`, the reference forward-backward's own step), then
    backpointers. Ties prefer continuing the running option (fewer boundaries), then the lowest option index.

    Args:
        log_pi, log_term, log_cont, log_eta (Tensor): ``[B, T, K]``, as in :func:`forward_backward`.
        mask (Tensor, optional): ``[B, T]`` bool prefix mask.
        terminal (bool or Tensor): as in :func:`forward_backward`.

    Keyword Args:
        backend (str): ``"reference"`` (default): ``T`` sequential steps of O(K) work. ``"chunked"``: the same
            max-plus scan by chunks of about ``sqrt(T)`` transitions
            (:func:`~torchrl_options.inference._semiring.chunked_forward_messages`: chunk transfer matrices
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
    options = torch.full((B, T), -1, dtype=torch.long, device=log_pi.device)
    switches = torch.zeros(B, T, dtype=torch.bool, device=log_pi.device)
    switches[:, 0] = True
    for t in range(T - 1, -1, -1):
        active = t <= last  # steps past a row's end leave the row's pointer where it is
        options[:, t] = torch.where(active, h, -1)
        if t == 0:
            break
        sw = active & from_switch[:, t - 1].gather(1, h.unsqueeze(1)).squeeze(1)
        switches[:, t] = sw
        h = torch.where(sw, best_prev[:, t - 1], h)
    if backend != "reference":
        log_prob = _sequence_log_prob(options, switches, log_pi, log_term, log_cont, log_eta, mask, terminal)
        _check_finite(log_prob)
    return ViterbiOutput(options=options, switches=switches, log_prob=log_prob)


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

    Examples:
        >>> import torch
        >>> most_likely_options(torch.tensor([[[0.9, 0.1], [0.2, 0.8]]]))
        tensor([[0, 1]])
    """
    out = u.argmax(-1)
    if mask is not None:
        out = torch.where(mask, out, -1)
    return out
