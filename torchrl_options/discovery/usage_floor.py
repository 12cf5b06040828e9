"""A floor on every option's usage during discovery: posterior regularisation of DDO's E-step.

Maximum likelihood is indifferent between one option that copies a demonstrator and several that share its steps,
and Expectation-Gradient drifts to the first: the option that explains a step slightly better gets more of the
posterior, so more of the gradient, and the others go unused (the collapse :func:`~torchrl_options.discovery.
diagnostics.option_diagnostics` warns about). Posterior regularisation (Ganchev, Graca, Gillenwater, Taskar,
"Posterior Regularization for Structured Latent Variable Models", JMLR 2010) constrains the E-step instead of the
model: the posterior ``p(z | x)`` of DDO's option sequence ``z`` (Fox, Krishnan, Stoica, Goldberg, "Multi-Level
Discovery of Deep Options", 2017, section 4) is replaced by its KL projection

.. math::
    q^* = \\arg\\min_q KL(q \\| p(z|x)) \\quad \\text{s.t.} \\quad E_q[n_h] \\ge c\\, n / K \\text{ for every } h,

with ``n_h`` the steps spent in option ``h``, ``n`` the valid steps and ``c`` the floor as a share of the uniform
usage. Its solution is ``q*(z) ~ p(z | x) exp(sum_t lambda_{h_t})`` with dual variables ``lambda >= 0``: the E-step
with ``lambda_h`` added to option ``h``'s action log-probabilities at every step, the same forward-backward pass.
The M-step then maximises ``E_{q*}[log p(x, z)]`` (its gradient is that of ``log Z_lambda``, the biased pass's
normaliser, since ``lambda`` does not depend on the parameters), which is EM on the penalised objective
``log p(x) - KL(q* || p(z|x)) = log Z_lambda - lambda . E_{q*}[n]``. The dual is climbed one projected gradient
step per E-step (:meth:`UsageFloor.update`), so it follows the parameters as they move.
"""
from __future__ import annotations

import torch

from torchrl_options.checks import check_int, check_number, check_positive_number

__all__ = ["UsageFloor", "USAGE_DUAL_STEP", "check_usage_floor"]

USAGE_DUAL_STEP = 1.0
"""The dual step of :class:`UsageFloor` (nats of bias per unit of relative usage shortfall, per E-step)."""


class UsageFloor:
    """The dual variables of a floor on every option's posterior usage (posterior regularisation of DDO's E-step).

    Args:
        num_options (int): K.
        floor (float): the least usage of every option, as a share of the uniform usage ``1 / K``, in ``(0, 1)``:
            0.5 asks every option to be active on at least half of ``1 / K`` of the steps.

    Keyword Args:
        step (float): the dual step, nats per unit of relative shortfall. Defaults to :data:`USAGE_DUAL_STEP`.
        device: where the dual variables live (the batch's device).

    Attributes:
        bias (Tensor): ``[K]``, ``lambda >= 0``, added to each option's action log-probabilities in the E-step.

    Examples:
        >>> import torch
        >>> floor = UsageFloor(2, 0.5)
        >>> floor.update(torch.tensor([0.9, 0.1]))  # option 1 at 0.2 of its uniform share, below 0.5
        >>> floor.bias
        tensor([0.0000, 0.3000])
        >>> floor.update(torch.tensor([0.6, 0.4]))  # above the floor: the bias shrinks, never below 0
        >>> floor.bias
        tensor([0., 0.])
    """

    def __init__(self, num_options: int, floor: float, *, step: float = USAGE_DUAL_STEP, device=None) -> None:
        check_int(num_options, "num_options", minimum=1)
        check_usage_floor(floor, "floor")
        if floor is None:
            raise TypeError("UsageFloor: floor must be a number in (0, 1), got None.")
        check_positive_number(step, "step")
        self.num_options, self.floor, self.step = num_options, float(floor), float(step)
        self.bias = torch.zeros(num_options, device=device)

    def update(self, usage: torch.Tensor) -> None:
        """One projected dual step from the E-step's usage shares ``usage`` ``[K]`` (summing to 1)."""
        if not isinstance(usage, torch.Tensor):
            raise TypeError(f"UsageFloor.update: usage must be a [K={self.num_options}] tensor, got {type(usage).__name__}.")
        if usage.shape != (self.num_options,):
            raise ValueError(f"UsageFloor.update: usage must be a [K={self.num_options}] tensor, got {tuple(usage.shape)}.")
        if not bool(torch.isfinite(usage).all()):
            raise ValueError(f"UsageFloor.update: usage must be finite, got {usage.tolist()}.")
        relative = usage.detach().to(self.bias) * self.num_options
        self.bias = (self.bias + self.step * (self.floor - relative)).clamp_min(0.0)

    def biased(self, log_pi: torch.Tensor) -> torch.Tensor:
        """``log_pi`` ``[..., K]`` with each option's dual variable added (the projected E-step's input)."""
        return log_pi + self.bias.to(log_pi)

    def penalty(self, u: torch.Tensor) -> torch.Tensor:
        """``lambda . E_q[n]`` from the projected posterior's marginals ``u`` ``[B, T, K]``: what the biased pass's
        log-normaliser holds beyond the penalised objective."""
        return (u.sum((0, 1)) * self.bias.to(u)).sum()


def check_usage_floor(floor, name: str = "usage_floor") -> None:
    """``floor`` is ``None`` or a number in ``(0, 1)`` (a share of the uniform usage ``1 / K``); errors name it
    ``name``.

    Examples:
        >>> check_usage_floor(0.5)
        >>> check_usage_floor(1.0)
        Traceback (most recent call last):
        ...
        ValueError: usage_floor must be a share of the uniform usage 1/K in (0, 1), got 1.0.
    """
    check_number(floor, name, allow_none=True)
    if floor is not None and not 0.0 < floor < 1.0:
        raise ValueError(f"{name} must be a share of the uniform usage 1/K in (0, 1), got {floor!r}.")
