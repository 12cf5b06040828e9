"""Split-and-merge moves: escaping local optima of DDO by re-seeding a little-used option from a busy one.

Split-and-merge EM (Ueda, Nakano, Ghahramani and Hinton, "SMEM Algorithm for Mixture Models", Neural Computation
12, 2000) escapes the local optima of a mixture's likelihood where two components share one cluster while another
component is wasted: it merges the pair, splits a crowded component into the freed slot, re-runs EM and keeps the
move only if the likelihood rose. Applied to DDO (Fox, Krishnan, Stoica and Goldberg, 2017) the components are the
options: after the main fit, the parameters of a little-used (or duplicated) option, the *victim*, are overwritten
with a noisy copy of a busy option's, the *donor* (which splits the donor's steps between two near-copies and
merges the victim's into their neighbours), the model is re-trained from there, and the move is accepted only when
the training log-likelihood per step rises by more than ``min_gain``. A rejected move leaves the model as it was,
so the final likelihood is never below the main fit's.
"""
from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase

from torchrl_options.checks import check_callable, check_int, check_number, check_numbers

__all__ = ["check_split_merge_options", "copy_option", "propose_pairs", "split_merge"]

logger = logging.getLogger(__name__)

NOISE = 0.3
"""The copy's noise: ``NOISE`` times the mean absolute value of the donor's parameter slice, times N(0, 1)."""

MIN_GAIN = 1e-4
"""A move is accepted when the training log-likelihood per step rises by more than this many nats."""


def check_split_merge_options(options: TensorDictModuleBase, num_options: int) -> None:
    """Checks that every parameter of ``options`` holds one slice per option along its leading dimension.

    That is the layout of :class:`~torchrl_options.OptionsMLP` (``architecture="separate"``) and
    :class:`~torchrl_options.GaussianOptionsMLP`, where an option's parameters are the ``[k]`` slices; a shared
    trunk (``architecture="shared"``) has parameters common to all options, which a move cannot copy per option.

    Args:
        options (TensorDictModuleBase): the options module.
        num_options (int): K.

    Raises:
        ValueError: a parameter whose leading dimension is not K, or a module without parameters.

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> check_split_merge_options(OptionsMLP(2, 3, 4), 4)
        >>> check_split_merge_options(OptionsMLP(2, 3, 4, architecture="shared"), 4)
        Traceback (most recent call last):
        ...
        ValueError: split_merge copies one option's parameter slices into another's: every parameter of the options module must have the option index as its leading dimension (num_options=4), got trunk.0.weight of shape [2, 2] (architecture 'shared' is not supported; use 'separate').
    """
    if not isinstance(options, TensorDictModuleBase):
        raise TypeError(f"options must be an options module (TensorDictModuleBase), got {type(options).__name__}.")
    check_int(num_options, "num_options", minimum=1)
    named = list(options.named_parameters())
    if not named:
        raise ValueError("split_merge copies one option's parameters into another's: the options module has none.")
    for name, param in named:
        if param.dim() == 0 or param.shape[0] != num_options:
            raise ValueError(
                "split_merge copies one option's parameter slices into another's: every parameter of the options "
                f"module must have the option index as its leading dimension (num_options={num_options}), got {name} "
                f"of shape {list(param.shape)} (architecture 'shared' is not supported; use 'separate')."
            )


def copy_option(
    options: TensorDictModuleBase, victim: int, donor: int, generator: torch.Generator, noise: float = NOISE
) -> TensorDictModuleBase:
    """A copy of ``options`` whose option ``victim`` is a noisy copy of option ``donor`` (the others unchanged).

    Each parameter's ``[victim]`` slice becomes ``p[donor] + noise * mean(|p[donor]|) * N(0, 1)``.

    Args:
        options (TensorDictModuleBase): options whose parameters all have the option index as leading dimension
            (:func:`check_split_merge_options`); not modified.
        victim (int): the option overwritten.
        donor (int): the option copied.
        generator (torch.Generator): draws the noise (on the CPU).
        noise (float): relative noise scale. Defaults to :data:`NOISE`.

    Returns:
        The new module.

    Examples:
        >>> import torch
        >>> from torchrl_options import OptionsMLP
        >>> options = OptionsMLP(2, 3, 4)
        >>> new = copy_option(options, victim=0, donor=2, generator=torch.Generator().manual_seed(0), noise=0.0)
        >>> w, old = (dict(m.named_parameters())["control.params.0.weight"] for m in (new, options))
        >>> torch.equal(w[0], w[2]), torch.equal(w[1], old[1]), torch.equal(old[0], old[2])
        (True, True, False)
    """
    if not isinstance(options, TensorDictModuleBase):
        raise TypeError(f"options must be an options module (TensorDictModuleBase), got {type(options).__name__}.")
    k = _leading_size(options)
    check_int(victim, "victim", minimum=0, maximum=k - 1)  # -1 would silently overwrite the last option
    check_int(donor, "donor", minimum=0, maximum=k - 1)
    if victim == donor:
        raise ValueError(f"victim and donor must be two different options, got {victim} for both.")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}.")
    check_number(noise, "noise", lo=0.0, hi=math.inf, hi_open=True)
    new = copy.deepcopy(options)
    with torch.no_grad():
        for param in new.parameters():
            source = param[donor]
            scale = noise * float(source.abs().mean())
            draw = torch.randn(source.shape, generator=generator, dtype=source.dtype).to(source.device)
            param[victim] = source + scale * draw
    return new


def _leading_size(options: TensorDictModuleBase) -> int:
    """K, the leading size of every parameter (checked by :func:`check_split_merge_options`)."""
    sizes = {p.shape[0] for p in options.parameters() if p.dim() > 0}
    if len(sizes) != 1:
        raise ValueError(
            "copy_option needs options whose parameters all have the option index as leading dimension (see "
            f"check_split_merge_options), got leading sizes {sorted(sizes)}."
        )
    return sizes.pop()


def propose_pairs(usage: Sequence[float], duplicates: Sequence[tuple[int, int]], move: int) -> tuple[int, int]:
    """The (victim, donor) of proposal number ``move`` given the current model's usage and duplicates.

    Victims cycle through the options in a fixed order: first the less-used member of each duplicated pair (a
    wasted option), then the others in increasing usage, the most-used option last. The donor is the most-used
    option other than the victim on the first pass through the victims, the second most-used on the second pass,
    and so on.

    Args:
        usage (sequence of float): each option's share of the steps (:func:`option_diagnostics`).
        duplicates (sequence of tuple): duplicated option pairs.
        move (int): the proposal's index since the model last changed.

    Returns:
        ``(victim, donor)``.

    Examples:
        >>> propose_pairs([0.5, 0.1, 0.3, 0.1], [], 0)
        (1, 0)
        >>> propose_pairs([0.5, 0.1, 0.3, 0.1], [(0, 2)], 0)
        (2, 0)
        >>> propose_pairs([0.5, 0.1, 0.3, 0.1], [], 4)
        (3, 2)
    """
    usage = check_numbers(usage, "usage", lo=0.0, hi=1.0)
    num_options = len(usage)
    if num_options < 2:
        raise ValueError(
            f"usage must hold the usage of at least 2 options (a move copies one option into another), got {num_options}."
        )
    if isinstance(duplicates, (str, bytes)) or not isinstance(duplicates, Sequence):
        raise TypeError(f"duplicates must be a sequence of (i, j) option pairs, got {type(duplicates).__name__}.")
    for pair in duplicates:
        if (
            not isinstance(pair, Sequence) or len(pair) != 2
            or any(isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < num_options for k in pair)
        ):  # fmt: skip
            raise ValueError(f"duplicates must hold (i, j) pairs of options in [0, {num_options - 1}], got {pair!r}.")
    check_int(move, "move", minimum=0)
    by_usage = sorted(range(num_options), key=lambda k: (usage[k], k))
    first = []
    for i, j in duplicates:
        wasted = min((i, j), key=lambda k: (usage[k], k))
        if wasted not in first:
            first.append(wasted)
    victims = first + [k for k in by_usage if k not in first]
    victims = victims[: num_options - 1] if len(victims) > 1 else victims
    victim = victims[move % len(victims)]
    donors = [k for k in reversed(by_usage) if k != victim]
    donor = donors[(move // len(victims)) % len(donors)]
    return victim, donor


def split_merge(
    fit: Any,
    refit: Callable[[TensorDictModuleBase, int], Any],
    score: Callable[[Any], float],
    num_moves: int,
    generator: torch.Generator,
    *,
    noise: float = NOISE,
    min_gain: float = MIN_GAIN,
) -> tuple[Any, list[dict]]:
    """Proposes ``num_moves`` split-and-merge moves from ``fit`` and keeps those that raise the likelihood.

    Each proposal copies a donor option into a victim's slot (:func:`propose_pairs`, :func:`copy_option`), re-trains
    the model from there (``refit``) and accepts the result when ``score`` (the training log-likelihood per step)
    exceeds the current one by more than ``min_gain``; the next proposals start from the accepted model.
    :func:`~torchrl_options.discover_options` calls it with ``split_merge=n``.

    Args:
        fit: the main fit, with ``options``, ``option_usage`` and ``duplicate_options`` (a
            :class:`~torchrl_options.discovery.DiscoveryResult`).
        refit (callable): ``refit(options, seed)`` re-trains a candidate and returns a result like ``fit``.
        score (callable): ``score(result)``, the training log-likelihood per step of a result.
        num_moves (int): the proposals.
        generator (torch.Generator): draws the copies' noise and the re-fits' seeds (determinism).

    Keyword Args:
        noise (float): see :func:`copy_option`. Defaults to :data:`NOISE`.
        min_gain (float): the acceptance margin in nats per step. Defaults to :data:`MIN_GAIN`.

    Returns:
        The final result (``fit`` itself when no move was accepted) and the moves: one dict per proposal with
        ``move``, ``victim``, ``donor``, ``log_likelihood_before``, ``log_likelihood_after`` (the re-fit's) and
        ``accepted``.

    Examples:
        >>> import torch
        >>> from torchrl_options import discover_options
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(6, 20, seed=0)
        >>> result = discover_options(data, 2, num_iterations=30, seed=0, progress=False, return_info=True,
        ...                           split_merge=2, split_merge_iterations=10)
        >>> [sorted(m) for m in result.split_merge_moves][0]
        ['accepted', 'donor', 'log_likelihood_after', 'log_likelihood_before', 'move', 'victim']
        >>> ll = [m["log_likelihood_before"] for m in result.split_merge_moves]
        >>> all(b >= a for a, b in zip(ll, ll[1:]))
        True
    """
    check_callable(refit, "refit")
    check_callable(score, "score")
    check_int(num_moves, "num_moves", minimum=0)
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}.")
    check_number(noise, "noise", lo=0.0, hi=math.inf, hi_open=True)
    check_number(min_gain, "min_gain", lo=0.0, hi=math.inf, hi_open=True)
    current, current_ll = fit, score(fit)
    moves: list[dict] = []
    since_change = 0
    for move in range(num_moves):
        victim, donor = propose_pairs(current.option_usage, current.duplicate_options, since_change)
        candidate = copy_option(current.options, victim, donor, generator, noise=noise)
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator))
        result = refit(candidate, seed)
        ll = score(result)
        accepted = bool(ll > current_ll + min_gain)
        moves.append(dict(move=move, victim=victim, donor=donor, log_likelihood_before=current_ll,
                          log_likelihood_after=ll, accepted=accepted))  # fmt: skip
        logger.info("split_merge move %d: option %d <- option %d, log-likelihood per step %.5f -> %.5f (%s)",
                    move, victim, donor, current_ll, ll, "accepted" if accepted else "rejected")  # fmt: skip
        if accepted:
            current, current_ll, since_change = result, ll, 0
        else:
            since_change += 1
    return current, moves
