"""A guard for policy-gradient losses: step-level data of an option executor must not reach them.

An env with an :class:`~torchrl_options.transforms.OptionExecutor` yields one entry per primitive step, with
``("next", "option_decision")`` telling which steps used the policy's action. A policy-gradient loss (TorchRL's
``ClipPPOLoss``, ``A2CLoss``, ...) or a GAE estimator fed those steps trains on actions that were never taken
and discounts decisions of different lengths with one ``gamma``: no error, a wrong algorithm.
:func:`guard_decision_level` makes such a loss refuse them; the decision-level batches of
:class:`~torchrl_options.data.OnPolicyDecisions` (which carry ``steps_to_next_obs``) pass.
"""
from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from torch import nn

from torchrl_options.checks import check_nested_key

__all__ = ["StepLevelDataError", "guard_decision_level", "is_step_level_option_data"]

_GUARDED = "_torchrl_options_decision_guard"


class StepLevelDataError(ValueError):
    """Step-level data of an option executor reached a loss or estimator that needs decision-level data."""


def is_step_level_option_data(data: TensorDictBase, steps_key: str = "steps_to_next_obs") -> bool:
    """Whether ``data`` is step-level data of an env with an option executor: it carries an executor's decision
    record (a key named ``option_decision`` or ``option_decision_<level>``, at the root or under ``"next"``) and no
    ``steps_key`` (which the decision-level batches carry).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> step = TensorDict({"next": {"option_decision": torch.ones(3, dtype=torch.bool)}}, [3])
        >>> is_step_level_option_data(step)
        True
        >>> is_step_level_option_data(step.set("steps_to_next_obs", torch.ones(3, dtype=torch.long)))
        False
    """
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"is_step_level_option_data expects a TensorDict, got {type(data).__name__}.")
    steps_key = check_nested_key(steps_key, "steps_key")
    if steps_key in data.keys(True):
        return False
    for key in data.keys(True, True):
        name = key if isinstance(key, str) else key[-1]
        if name == "option_decision" or name.startswith("option_decision_"):
            return True
    return False


def guard_decision_level(module: nn.Module) -> nn.Module:
    """Makes ``module`` (a TorchRL loss such as ``ClipPPOLoss``, and its value estimator if it has one) raise
    :class:`StepLevelDataError` when called on step-level data of an option executor (see
    :func:`is_step_level_option_data`). Value estimators made later by ``make_value_estimator`` are guarded
    too. Returns ``module``; guarding twice is harmless.

    Raises:
        TypeError: ``module`` is not an ``nn.Module``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor, ValueOperator
        >>> from torchrl.objectives import ClipPPOLoss
        >>> actor = ProbabilisticActor(TensorDictModule(torch.nn.Linear(2, 3), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True)
        >>> loss = guard_decision_level(ClipPPOLoss(actor, ValueOperator(torch.nn.Linear(2, 1), ["observation"])))
        >>> steps = TensorDict({"observation": torch.zeros(4, 2), "next": {"option_decision": torch.ones(4, dtype=torch.bool)}}, [4])
        >>> loss(steps)
        Traceback (most recent call last):
        ...
        torchrl_options.objectives.decision_guard.StepLevelDataError: ClipPPOLoss received step-level data of an option executor ...
    """
    if not isinstance(module, nn.Module):
        raise TypeError(f"guard_decision_level expects a loss module (torch.nn.Module), got {type(module).__name__}.")
    _guard(module)
    estimator = getattr(module, "_value_estimator", None)
    if isinstance(estimator, nn.Module):
        _guard(estimator)
    if hasattr(module, "make_value_estimator") and not getattr(module, "_guarded_make_value_estimator", False):
        make = module.make_value_estimator

        def make_value_estimator(*args: Any, **kwargs: Any):
            out = make(*args, **kwargs)
            estimator = getattr(module, "_value_estimator", None)
            if isinstance(estimator, nn.Module):
                _guard(estimator)
            return out

        module.make_value_estimator = make_value_estimator
        module._guarded_make_value_estimator = True
    return module


def _guard(module: nn.Module) -> None:
    if getattr(module, _GUARDED, False):
        return
    name = type(module).__name__

    def hook(mod: nn.Module, args: tuple, kwargs: dict) -> None:
        data = args[0] if args else kwargs.get("tensordict")
        if isinstance(data, TensorDictBase) and is_step_level_option_data(data):
            raise StepLevelDataError(
                f"{name} received step-level data of an option executor (it has an 'option_decision' entry and no "
                "'steps_to_next_obs'): on steps inside an option the policy's action was not taken, and GAE would "
                "discount decisions of different lengths with one gamma. Turn each collector batch into decisions "
                "first: `decisions = OnPolicyDecisions(gamma)(batch)` (torchrl_options.data), then compute the "
                "advantages and the loss on `decisions`."
            )

    module.register_forward_pre_hook(hook, with_kwargs=True)
    setattr(module, _GUARDED, True)
