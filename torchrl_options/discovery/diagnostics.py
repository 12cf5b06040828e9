"""Signs that a discovery run may be stuck: unused options, duplicated options, restarts that disagree.

The likelihood of DDO (Fox et al., 2017, section 4) has local optima in which two options merge into one or one
option is never used. A user who cannot see the ground truth cannot tell such a run from a good one by its
likelihood alone; these label-free checks, computed on the demonstrations themselves, can.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from torchrl_options.checks import check_number, check_numbers
from torchrl_options.inference import forward_backward

__all__ = ["OptionDiagnostics", "option_diagnostics", "options_in_use", "restart_disagreement", "UNUSED_SHARE"]

logger = logging.getLogger(__name__)

UNUSED_SHARE = 0.1
"""An option active on less than ``UNUSED_SHARE / K`` of the demonstrations' steps is reported unused (the default
``min_usage`` of :func:`option_diagnostics`)."""


def options_in_use(usage: Sequence[float]) -> int:
    """How many of K options are in use: active on at least ``UNUSED_SHARE / K`` of the steps, by their usage shares
    (:attr:`DiscoveryResult.option_usage <torchrl_options.discovery.DiscoveryResult>`, :class:`OptionDiagnostics`'s
    ``usage``). The complement of :func:`option_diagnostics`'s ``unused`` with its default ``min_usage``.

    Raises:
        TypeError: ``usage`` is not a sequence of numbers.
        ValueError: a share is NaN or outside ``[0, 1]``.

    Examples:
        >>> options_in_use([0.6, 0.38, 0.02])
        2
        >>> options_in_use([])
        0
    """
    usage = check_numbers(usage, "usage", lo=0.0, hi=1.0)
    return sum(u >= UNUSED_SHARE / len(usage) for u in usage)


@dataclass
class OptionDiagnostics:
    """Label-free diagnostics of discovered options on the demonstrations.

    Attributes:
        usage (list of float): per option, the posterior share of valid steps it is active at (sums to 1).
        duplicates (list of tuple): pairs ``(i, j)`` of options whose control and termination agree on the
            demonstrations (mean absolute difference of the log-probabilities of the demonstrated actions below
            ``policy_tol`` nats and of the termination probabilities below ``termination_tol``).
        unused (list of int): options active at less than ``min_usage`` of the steps.
        warnings (list of str): one sentence per problem found, also logged as warnings by
            :func:`~torchrl_options.discover_options`.
        log_likelihood_per_step (float): the exact log-likelihood of the demonstrations under the options, per
            valid step (the forward pass the usage comes from).
    """

    usage: list[float]
    duplicates: list[tuple[int, int]] = field(default_factory=list)
    unused: list[int] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    log_likelihood_per_step: float = math.nan


def option_diagnostics(
    log_probs: Mapping[str, torch.Tensor],
    *,
    min_usage: float | None = None,
    policy_tol: float = 0.05,
    termination_tol: float = 0.05,
) -> OptionDiagnostics:
    """Usage and duplicates of K options, from their E-step inputs on the demonstrations.

    Args:
        log_probs (mapping): ``log_pi``, ``log_term``, ``log_cont``, ``log_eta`` ``[B, T, K]`` and ``mask``
            ``[B, T]``, as returned by :meth:`~torchrl_options.DDOLoss.log_probabilities`.

    Keyword Args:
        min_usage (float, optional): an option active at less than this share of the steps is reported unused.
            Defaults to ``UNUSED_SHARE / K`` (``0.1 / K``).
        policy_tol (float): see :class:`OptionDiagnostics`. Defaults to 0.05 nats.
        termination_tol (float): see :class:`OptionDiagnostics`. Defaults to 0.05.

    Returns:
        An :class:`OptionDiagnostics`.

    Examples:
        >>> import torch
        >>> B, T, K = 2, 5, 3
        >>> log_pi = torch.log(torch.tensor([0.9, 0.9, 0.1])).expand(B, T, K)
        >>> log_term = torch.full((B, T, K), -2.0)
        >>> lp = dict(log_pi=log_pi, log_term=log_term, log_cont=torch.log1p(-log_term.exp()),
        ...           log_eta=torch.full((B, T, K), -torch.log(torch.tensor(3.0)).item()),
        ...           mask=torch.ones(B, T, dtype=torch.bool))
        >>> d = option_diagnostics(lp)
        >>> d.duplicates, d.unused
        ([(0, 1)], [2])
    """
    if not isinstance(log_probs, Mapping):
        raise TypeError(f"log_probs must be a mapping of tensors (DDOLoss.log_probabilities), got {type(log_probs).__name__}.")
    missing = [k for k in ("log_pi", "log_term", "log_cont", "log_eta", "mask") if k not in log_probs]
    if missing:
        raise ValueError(f"log_probs lacks {missing} (expected the output of DDOLoss.log_probabilities).")
    check_number(min_usage, "min_usage", lo=0.0, hi=1.0, allow_none=True)
    check_number(policy_tol, "policy_tol", lo=0.0, hi=math.inf, hi_open=True)
    check_number(termination_tol, "termination_tol", lo=0.0, hi=1.0)
    mask = log_probs["mask"].bool()
    log_pi = log_probs["log_pi"].detach()
    K = log_pi.shape[-1]
    if min_usage is None:
        min_usage = UNUSED_SHARE / K
    with torch.no_grad():
        fb = forward_backward(
            log_pi, log_probs["log_term"].detach(), log_probs["log_cont"].detach(), log_probs["log_eta"].detach(),
            mask, log_probs.get("terminal", False),
        )  # fmt: skip
        u = fb.u[mask].double()  # [N, K]
        log_likelihood_per_step = float(fb.log_likelihood.double().sum() / mask.sum().clamp_min(1))
        usage = (u.sum(0) / u.sum().clamp_min(1e-30)).tolist()
        lp = log_pi[mask].double().clamp_min(-30.0)  # [N, K]
        term = log_probs["log_term"].detach()[mask].double().exp()
        policy_gap = (lp[:, :, None] - lp[:, None, :]).abs().mean(0)
        term_gap = (term[:, :, None] - term[:, None, :]).abs().mean(0)
    duplicates = [
        (i, j)
        for i in range(K)
        for j in range(i + 1, K)
        if policy_gap[i, j] < policy_tol and term_gap[i, j] < termination_tol
    ]
    unused = [h for h in range(K) if usage[h] < min_usage]
    warnings = []
    if unused:
        warnings.append(
            f"option(s) {unused} are active at less than {min_usage:.3g} of the steps (usage "
            f"{[round(usage[h], 4) for h in unused]}): the run may be stuck in a local optimum with fewer options "
            "than asked, or the demonstrations hold fewer skills; try more restarts or fewer options."
        )
    if duplicates:
        warnings.append(
            f"option pairs {duplicates} act and terminate alike on the demonstrations (duplicates): the run may be "
            "stuck in a local optimum; try more restarts or fewer options."
        )
    return OptionDiagnostics(usage=usage, duplicates=duplicates, unused=unused, warnings=warnings,
                             log_likelihood_per_step=log_likelihood_per_step)


def restart_disagreement(log_likelihoods: Sequence[float], *, tol: float = 0.02) -> str | None:
    """A warning when most starts ended far below the best one (the best may be a local optimum too).

    Args:
        log_likelihoods (sequence of float): each start's log-likelihood per step.

    Keyword Args:
        tol (float): starts within ``tol`` nats per step of the best count as reaching it. Defaults to 0.02.

    Returns:
        ``None`` when at least half the starts (and at least two) reach the best, else a one-sentence warning.

    Examples:
        >>> restart_disagreement([-1.0, -1.01, -1.3, -1.2]) is None
        True
        >>> print(restart_disagreement([-1.0, -1.5, -1.3, -1.2]))  # doctest: +ELLIPSIS
        only 1 of 4 starts reached the best log-likelihood per step ...
    """
    check_numbers(log_likelihoods, "log_likelihoods", allow_nan=True)  # NaN (a failed start) is left out
    check_number(tol, "tol", lo=0.0, hi=math.inf, hi_open=True)
    lls = [x for x in log_likelihoods if x == x]
    if len(lls) < 2:
        return None
    best = max(lls)
    reached = sum(x >= best - tol for x in lls)
    if reached >= max(2, (len(lls) + 1) // 2):
        return None
    return (
        f"only {reached} of {len(lls)} starts reached the best log-likelihood per step ({best:.4f}; the others "
        f"{sorted(round(x, 4) for x in lls)}): the likelihood has several optima here and the best found may not be "
        "the global one; try more restarts (restarts=...) or longer ones (restart_iterations=...)."
    )
