"""Most likely option sequences: Viterbi decoding of the options' latent chain, and posterior argmax."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchrl_options.inference.forward_backward import check_forward_backward_inputs

__all__ = ["ViterbiOutput", "viterbi", "most_likely_options"]


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
) -> ViterbiOutput:
    """The most likely joint sequence of options and switches ``argmax_zeta P(zeta, xi)`` (max-product).

    Same inputs and model as :func:`~torchrl_options.forward_backward` (Fox et al., 2017, appendix A), with the
    sums replaced by maxima; O(K) per step. Ties prefer continuing the running option (fewer boundaries).

    Args:
        log_pi, log_term, log_cont, log_eta (Tensor): ``[B, T, K]``, as in :func:`forward_backward`.
        mask (Tensor, optional): ``[B, T]`` bool prefix mask.
        terminal (bool or Tensor): as in :func:`forward_backward`.

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
    """
    mask, terminal = check_forward_backward_inputs(log_pi, log_term, log_cont, log_eta, mask, terminal)
    B, T, K = log_pi.shape
    valid = mask.unsqueeze(-1)
    zero = torch.zeros((), dtype=log_pi.dtype, device=log_pi.device)
    log_pi, log_term, log_cont, log_eta = (torch.where(valid, x, zero) for x in (log_pi, log_term, log_cont, log_eta))
    last = mask.sum(1) - 1
    switch = log_pi + log_term
    stay = log_pi + log_cont

    delta = log_eta[:, 0]
    offset = torch.zeros(B, dtype=log_pi.dtype, device=log_pi.device)
    from_switch, best_prev = [], []
    for t in range(T - 1):
        m, arg = (delta + switch[:, t]).max(-1, keepdim=True)
        start = m + log_eta[:, t + 1]
        keep = delta + stay[:, t]
        sw = start > keep
        new = torch.where(sw, start, keep)
        # keep the scores bounded on long trajectories; the offsets add back to the log-probability
        top = new.max(-1, keepdim=True).values
        top = torch.where(torch.isfinite(top), top, 0.0)
        step_valid = mask[:, t + 1 : t + 2]
        delta = torch.where(step_valid, new - top, delta)
        offset = offset + torch.where(step_valid.squeeze(-1), top.squeeze(-1), 0.0)
        from_switch.append(sw)
        best_prev.append(arg)
    end = log_pi.gather(1, last.view(B, 1, 1).expand(B, 1, K)).squeeze(1)
    end = end + torch.where(terminal.unsqueeze(-1), log_term.gather(1, last.view(B, 1, 1).expand(B, 1, K)).squeeze(1), 0.0)
    final, h = (delta + end).max(-1)
    log_prob = final + offset
    if not torch.isfinite(log_prob).all():
        rows = (~torch.isfinite(log_prob)).nonzero().flatten().tolist()
        raise ValueError(f"trajectories {rows[:10]} have zero likelihood under every option sequence.")

    options = torch.full((B, T), -1, dtype=torch.long, device=log_pi.device)
    switches = torch.zeros(B, T, dtype=torch.bool, device=log_pi.device)
    rows = torch.arange(B, device=log_pi.device)
    for t in range(T - 1, -1, -1):
        active = t <= last
        options[:, t] = torch.where(active, h, -1)
        if t == 0:
            switches[:, 0] = True
            break
        sw = from_switch[t - 1][rows, h]
        prev = best_prev[t - 1].squeeze(-1)
        # steps past a row's end leave the row's pointer where it is
        step_in = active & (t <= last)
        switches[:, t] = step_in & sw
        h = torch.where(step_in, torch.where(sw, prev, h), h)
    return ViterbiOutput(options=options, switches=switches, log_prob=log_prob)


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
