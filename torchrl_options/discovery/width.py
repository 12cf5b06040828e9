"""Choosing the width of the options' networks by held-out likelihood (``discover_options(num_cells="auto")``).

DDO (Fox et al., 2017) fits the options by maximum likelihood, and a wider network always fits the demonstrations at
least as well: on small data sets it reaches a likelihood above the truth's with other labels (over-fitting the
segmentation), while a narrow one cannot represent options that need capacity. Which width is right depends on the
data, so it is chosen on the data: each candidate width is fitted on a random share of the trajectories and scored
by the log-likelihood per step of the trajectories held out, a label-free criterion.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_int
from torchrl_options.objectives import DDOLoss

__all__ = ["AUTO_WIDTHS", "HOLDOUT_FRACTION", "held_out_log_likelihood", "select_width", "split_trajectories"]

logger = logging.getLogger(__name__)

AUTO_WIDTHS: tuple[int, ...] = (4, 8)
"""The hidden-layer widths ``num_cells="auto"`` chooses among."""

HOLDOUT_FRACTION: float = 0.2
"""The share of trajectories ``num_cells="auto"`` holds out to score each width."""

_MASK = ("collector", "mask")


def split_trajectories(
    data: TensorDictBase, fraction: float, generator: torch.Generator
) -> tuple[TensorDictBase, TensorDictBase]:
    """Splits a ``[B, T]`` trajectory batch into ``(train, held_out)`` rows at random.

    Args:
        data (TensorDictBase): ``[B, T]`` trajectories (one row per trajectory).
        fraction (float): the share of rows held out, in ``(0, 1)``; at least one row is held out and one kept.
        generator (torch.Generator): the random split's generator.

    Returns:
        ``(train, held_out)``, two ``[B', T]`` tensordicts.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.randn(10, 5, 2)}, [10, 5])
        >>> train, held_out = split_trajectories(data, 0.2, torch.Generator().manual_seed(0))
        >>> train.batch_size, held_out.batch_size
        (torch.Size([8, 5]), torch.Size([2, 5]))
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction!r}.")
    rows = data.batch_size[0]
    if rows < 2:
        raise ValueError(f"splitting trajectories needs at least 2 of them, got {rows}.")
    held = min(max(1, round(fraction * rows)), rows - 1)
    perm = torch.randperm(rows, generator=generator).to(data.device)
    return data[perm[held:]], data[perm[:held]]


def held_out_log_likelihood(
    options: TensorDictModuleBase,
    meta_control: TensorDictModuleBase | None,
    data: TensorDictBase,
    *,
    action_space: str = "categorical",
    action_key: NestedKey = "action",
) -> float:
    """The log-likelihood per valid step of ``data`` under the options (the exact forward pass of :class:`DDOLoss`).

    Args:
        options, meta_control: the fitted modules (``meta_control=None``: uniform).
        data (TensorDictBase): ``[B, T]`` trajectories with ``("collector", "mask")``.

    Keyword Args:
        action_space (str): ``"categorical"`` or ``"continuous"``.
        action_key (NestedKey): the action entry.

    Returns:
        The log-likelihood per step (a float).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP
        >>> obs = torch.randn(4, 7, 2)
        >>> data = TensorDict({"observation": obs[:, :-1], "action": torch.randint(3, (4, 6)),
        ...                    "next": {"observation": obs[:, 1:]}}, [4, 6])
        >>> ll = held_out_log_likelihood(OptionsMLP(2, 3, 2), None, data)
        >>> ll < 0
        True
    """
    loss = DDOLoss(options, meta_control, action_space=action_space)
    loss.set_keys(action=action_key)
    with torch.no_grad():
        return float(loss(data)["log_likelihood_per_step"])


def select_width(
    fit: Callable[[TensorDictBase, int], object],
    data: TensorDictBase,
    *,
    widths: Sequence[int] = AUTO_WIDTHS,
    fraction: float = HOLDOUT_FRACTION,
    generator: torch.Generator,
    action_space: str = "categorical",
    action_key: NestedKey = "action",
) -> tuple[int, object, dict[int, float]]:
    """Fits each width on the same training share and keeps the one with the best held-out likelihood.

    Args:
        fit (callable): ``fit(train, width)`` returns a :class:`~torchrl_options.discovery.DiscoveryResult`.
        data (TensorDictBase): ``[B, T]`` trajectories with ``("collector", "mask")``.

    Keyword Args:
        widths (sequence of int): the candidate widths. Defaults to :data:`AUTO_WIDTHS`.
        fraction (float): the share of trajectories held out. Defaults to :data:`HOLDOUT_FRACTION`.
        generator (torch.Generator): the split's generator.
        action_space, action_key: as in :func:`held_out_log_likelihood`.

    Returns:
        ``(width, result, scores)``: the chosen width, its fit on the training share, and every width's held-out
        log-likelihood per step (ties go to the narrower width).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.discovery import discover_options
        >>> obs = torch.randn(10, 9, 2)
        >>> data = TensorDict({"observation": obs[:, :-1], "action": (obs[:, :-1, 0] > 0).long(),
        ...                    "next": {"observation": obs[:, 1:]},
        ...                    ("collector", "mask"): torch.ones(10, 8, dtype=torch.bool)}, [10, 8])
        >>> fit = lambda d, w: discover_options(d, 2, num_cells=w, num_iterations=5, progress=False, return_info=True)
        >>> width, result, scores = select_width(fit, data, generator=torch.Generator().manual_seed(0))
        >>> width in scores, sorted(scores)
        (True, [4, 8])
    """
    widths = list(widths)
    if not widths:
        raise ValueError("widths must be a non-empty sequence of positive ints, got [].")
    for w in widths:
        check_int(w, "widths", minimum=1)
    train, held_out = split_trajectories(data, fraction, generator)
    scores, fits = {}, {}
    for width in widths:
        result = fit(train, width)
        scores[width] = held_out_log_likelihood(
            result.options, result.meta_control, held_out, action_space=action_space, action_key=action_key
        )
        fits[width] = result
    best = max(widths, key=lambda w: (scores[w], -w))
    logger.info(
        "num_cells='auto': held-out log-likelihood per step %s; width %d kept",
        ", ".join(f"{w} units {s:.4f}" for w, s in scores.items()), best,
    )  # fmt: skip
    return best, fits[best], scores
