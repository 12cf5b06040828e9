"""Scores of a segmentation against reference boundaries, and the random-boundary baseline.

A *boundary* is a step ``t`` at which a new segment starts: the action ``a_t`` is the first one of a new option
(the convention of :func:`~torchrl_options.viterbi`'s ``switches`` and of the generators' ``true_switch``). The
start of every trajectory, ``t = 0``, is a boundary of every segmentation and is known without inference, so it
is excluded from both the predicted and the reference sets (pass ``include_start=True`` to keep it).

Boundaries are given either as one sequence of step indices per trajectory, or as a ``[B, T]`` boolean
tensor/array (``True`` where a segment starts), with ``lengths`` (or a ``[B, T]`` validity mask) telling where
each trajectory ends; steps at or beyond a trajectory's length are dropped.

The paper's score (Fox et al., 2017, section 5.3: "the fraction of option boundaries that have exactly one
human annotation in a 300 ms window around them"; 72% for DDO on surgical demonstrations, 14% for random
guessing) is :func:`boundary_accuracy`. It is a precision-like score that does not penalise missed reference
boundaries, so :func:`boundary_precision_recall_f1` adds the usual one-to-one matching scores.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

__all__ = [
    "BoundaryScores",
    "as_boundary_lists",
    "boundary_accuracy",
    "boundary_metrics",
    "boundary_precision_recall_f1",
    "expected_random_accuracy",
    "random_baseline",
    "random_boundaries",
]

Boundaries = "torch.Tensor | np.ndarray | Sequence[Sequence[int]]"


class BoundaryScores(NamedTuple):
    """Precision, recall and F1 of predicted boundaries under one-to-one matching (NaN where undefined)."""

    precision: float
    recall: float
    f1: float


def _lengths_array(lengths, n: int | None, name: str = "lengths") -> np.ndarray | None:
    if lengths is None:
        return None
    arr = np.asarray(lengths.cpu() if isinstance(lengths, torch.Tensor) else lengths)
    if arr.ndim == 2:  # a [B, T] validity mask
        arr = arr.astype(bool).sum(1)
    arr = arr.astype(np.int64).reshape(-1)
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} entries for {n} trajectories.")
    if (arr < 0).any():
        raise ValueError(f"{name} must be non-negative.")
    return arr


def as_boundary_lists(
    boundaries: Boundaries,
    lengths: torch.Tensor | np.ndarray | Sequence[int] | None = None,
    *,
    include_start: bool = False,
    name: str = "boundaries",
) -> list[np.ndarray]:
    """Normalises boundaries to one sorted array of unique step indices per trajectory.

    Args:
        boundaries: a ``[B, T]`` bool tensor/array (``True`` where a segment starts) or one sequence of step
            indices per trajectory.
        lengths: ``[B]`` valid steps per trajectory, or a ``[B, T]`` bool mask; steps ``>= length`` are dropped.

    Keyword Args:
        include_start (bool): keep ``t = 0``. Defaults to ``False``.
        name (str): the argument's name, for error messages.

    Examples:
        >>> import torch
        >>> as_boundary_lists(torch.tensor([[1, 0, 1, 0, 1], [1, 1, 0, 0, 0]]).bool(), lengths=[4, 5])
        [array([2]), array([1])]
        >>> as_boundary_lists([[5, 0, 3, 3]])
        [array([3, 5])]
    """
    if isinstance(boundaries, torch.Tensor):
        boundaries = boundaries.detach().cpu().numpy()
    if isinstance(boundaries, (str, bytes)) or not isinstance(boundaries, (np.ndarray, Sequence)):
        raise TypeError(
            f"{name} must be [B, T] booleans (a tensor or array) or a list of index lists, got {type(boundaries).__name__}."
        )
    if isinstance(boundaries, np.ndarray) and boundaries.ndim == 2 and boundaries.dtype != object:
        if boundaries.dtype != bool and not np.isin(boundaries, (0, 1)).all():
            raise ValueError(f"{name}: a [B, T] array of boundaries must be boolean (or 0/1).")
        rows = [np.flatnonzero(row.astype(bool)) for row in boundaries]
    elif isinstance(boundaries, np.ndarray) and boundaries.ndim not in (1, 2):
        raise ValueError(f"{name} must be [B, T] booleans or a list of index lists, got shape {boundaries.shape}.")
    else:
        rows = []
        for i, row in enumerate(boundaries):
            arr = np.asarray(row.cpu() if isinstance(row, torch.Tensor) else row).reshape(-1)
            if arr.dtype == bool:  # one row of a boolean mask given as a list
                arr = np.flatnonzero(arr)
            if arr.size and not np.issubdtype(arr.dtype, np.integer):
                if np.issubdtype(arr.dtype, np.floating) and np.all(arr == np.round(arr)):
                    arr = arr.astype(np.int64)
                else:
                    raise ValueError(f"{name}[{i}] must hold integer step indices, got {arr.dtype}.")
            if arr.size and arr.min() < 0:
                raise ValueError(f"{name}[{i}] holds a negative step index {int(arr.min())}.")
            rows.append(np.unique(arr.astype(np.int64)))
    lens = _lengths_array(lengths, len(rows))
    out = []
    for i, row in enumerate(rows):
        if lens is not None:
            row = row[row < lens[i]]
        if not include_start:
            row = row[row > 0]
        out.append(row.astype(np.int64))
    return out


def _pair(predicted, reference, lengths, include_start):
    pred = as_boundary_lists(predicted, lengths, include_start=include_start, name="predicted")
    ref = as_boundary_lists(reference, lengths, include_start=include_start, name="reference")
    if len(pred) != len(ref):
        raise ValueError(f"predicted has {len(pred)} trajectories but reference has {len(ref)}.")
    return pred, ref


def _check_window(window: int) -> int:
    if isinstance(window, bool) or not isinstance(window, (int, float, np.integer, np.floating)) or not np.isfinite(window):
        raise ValueError(f"window must be a non-negative integer number of steps, got {window!r}.")
    if int(window) != window or window < 0:
        raise ValueError(f"window must be a non-negative integer number of steps, got {window!r}.")
    return int(window)


def _accuracy_counts(pred: list[np.ndarray], ref: list[np.ndarray], window: int) -> tuple[int, int]:
    hits = total = 0
    for p, r in zip(pred, ref):
        total += p.size
        if p.size and r.size:
            # reference boundaries in [p - w, p + w], by binary search in the sorted reference
            count = np.searchsorted(r, p + window, side="right") - np.searchsorted(r, p - window, side="left")
            hits += int((count == 1).sum())
    return hits, total


def boundary_accuracy(
    predicted: Boundaries,
    reference: Boundaries,
    window: int,
    *,
    lengths: torch.Tensor | np.ndarray | Sequence[int] | None = None,
    include_start: bool = False,
) -> float:
    """The paper's segmentation score: the fraction of predicted boundaries with exactly one reference boundary
    within ``window`` steps (``|t_pred - t_ref| <= window``).

    Fox et al. (2017), section 5.3, with a 300 ms window at 30 Hz. Pooled over all trajectories (every predicted
    boundary counts once). A predicted boundary with two reference boundaries nearby counts as a miss, so the
    score cannot be gamed by a window wider than the segments. Missed reference boundaries do not lower it: read
    it with the recall of :func:`boundary_precision_recall_f1`.

    Args:
        predicted, reference: ``[B, T]`` booleans or one list of step indices per trajectory (see the module).
        window (int): ``w``, in steps.

    Keyword Args:
        lengths: ``[B]`` lengths or a ``[B, T]`` mask; steps beyond are ignored.
        include_start (bool): count ``t = 0`` as a boundary. Defaults to ``False``.

    Returns:
        float: in ``[0, 1]``; NaN when there is no predicted boundary.

    Examples:
        >>> # 10 is one step from 11; 30 has 29 and 31 both within 2 steps; 50 has nothing within 2 steps
        >>> boundary_accuracy([[10, 30, 50]], [[11, 29, 31, 70]], window=2)
        0.333...
        >>> boundary_accuracy([[10, 30, 50]], [[11, 29, 31, 70]], window=0)
        0.0
    """
    window = _check_window(window)
    pred, ref = _pair(predicted, reference, lengths, include_start)
    hits, total = _accuracy_counts(pred, ref, window)
    return hits / total if total else math.nan


def _matches(p: np.ndarray, r: np.ndarray, window: int) -> int:
    # Maximum one-to-one matching between sorted points where p_i and r_j may match when |p_i - r_j| <= w. Every
    # predicted point's admissible references form an interval [p_i - w, p_i + w], and these intervals are
    # ordered in both ends as p is sorted, so the left-to-right sweep matching each p_i to the earliest unmatched
    # admissible r_j is optimal (an exchange argument, as for interval scheduling).
    i = j = n = 0
    while i < p.size and j < r.size:
        if r[j] < p[i] - window:
            j += 1
        elif r[j] > p[i] + window:
            i += 1
        else:
            n += 1
            i += 1
            j += 1
    return n


def _prf_counts(pred, ref, window) -> tuple[int, int, int]:
    matched = sum(_matches(p, r, window) for p, r in zip(pred, ref))
    return matched, sum(p.size for p in pred), sum(r.size for r in ref)


def _prf(matched: int, n_pred: int, n_ref: int) -> BoundaryScores:
    precision = matched / n_pred if n_pred else math.nan
    recall = matched / n_ref if n_ref else math.nan
    if n_pred + n_ref == 0:
        f1 = math.nan
    else:
        f1 = 2 * matched / (n_pred + n_ref)
    return BoundaryScores(precision, recall, f1)


def boundary_precision_recall_f1(
    predicted: Boundaries,
    reference: Boundaries,
    window: int,
    *,
    lengths: torch.Tensor | np.ndarray | Sequence[int] | None = None,
    include_start: bool = False,
) -> BoundaryScores:
    """Precision, recall and F1 of predicted boundaries, matched one-to-one to reference boundaries.

    A predicted and a reference boundary of the same trajectory may be matched when they are at most ``window``
    steps apart; each boundary is matched at most once, and the matching has the largest possible number of
    pairs (computed exactly by a left-to-right sweep: with a window of the same width for every boundary, pairing
    each predicted boundary with the earliest unmatched reference boundary in its window is optimal). Then
    ``precision = matched / predicted``, ``recall = matched / reference`` and
    ``F1 = 2 matched / (predicted + reference)``, pooled over all trajectories.

    Args:
        predicted, reference: ``[B, T]`` booleans or one list of step indices per trajectory.
        window (int): the tolerance in steps.

    Keyword Args:
        lengths: ``[B]`` lengths or a ``[B, T]`` mask; steps beyond are ignored.
        include_start (bool): count ``t = 0`` as a boundary. Defaults to ``False``.

    Returns:
        BoundaryScores: ``(precision, recall, f1)``; precision is NaN without predicted boundaries, recall without
        reference ones.

    Examples:
        >>> # 30 can take 29 or 31, not both: two matches out of three predicted and four reference boundaries
        >>> boundary_precision_recall_f1([[10, 30, 50]], [[11, 29, 31, 70]], window=2)
        BoundaryScores(precision=0.666..., recall=0.5, f1=0.571...)
    """
    window = _check_window(window)
    pred, ref = _pair(predicted, reference, lengths, include_start)
    return _prf(*_prf_counts(pred, ref, window))


def random_boundaries(
    lengths: torch.Tensor | np.ndarray | Sequence[int],
    rate: float,
    generator: np.random.Generator | int | None = None,
    *,
    include_start: bool = False,
) -> list[np.ndarray]:
    """Random boundaries: each candidate step is a boundary independently with probability ``rate``.

    Candidate steps are ``1 .. length - 1`` (``0 .. length - 1`` with ``include_start``).

    Args:
        lengths: ``[B]`` trajectory lengths (or a ``[B, T]`` mask).
        rate (float): in ``[0, 1]``, boundaries per candidate step.
        generator: a :class:`numpy.random.Generator` or a seed.

    Examples:
        >>> [b.tolist() for b in random_boundaries([5, 3], 1.0)]
        [[1, 2, 3, 4], [1, 2]]
        >>> [b.size for b in random_boundaries([100], 0.0, 0)]
        [0]
    """
    if not 0.0 <= rate <= 1.0:
        raise ValueError(f"rate must be in [0, 1], got {rate}.")
    rng = generator if isinstance(generator, np.random.Generator) else np.random.default_rng(generator)
    lens = _lengths_array(lengths, None)
    first = 0 if include_start else 1
    out = []
    for L in lens:
        steps = np.arange(first, max(int(L), first))
        out.append(steps[rng.random(steps.size) < rate])
    return out


def _num_candidates(lens: np.ndarray, include_start: bool) -> int:
    return int(np.clip(lens - (0 if include_start else 1), 0, None).sum())


def expected_random_accuracy(
    reference: Boundaries,
    lengths: torch.Tensor | np.ndarray | Sequence[int],
    window: int,
    *,
    include_start: bool = False,
) -> float:
    """The accuracy that random boundaries get on average: the fraction of candidate steps with exactly one
    reference boundary within ``window`` steps.

    For boundaries drawn independently per step with any rate (:func:`random_boundaries`), the expected number of
    hits divided by the expected number of predicted boundaries is exactly this fraction, whatever the rate:
    the paper's "random guessing" figure.

    Examples:
        >>> expected_random_accuracy([[5]], [11], window=1)  # steps 4, 5, 6 out of 1..10
        0.3
    """
    window = _check_window(window)
    lens = _lengths_array(lengths, None)
    ref = as_boundary_lists(reference, lens, include_start=include_start, name="reference")
    first = 0 if include_start else 1
    candidates = [np.arange(first, max(int(L), first)) for L in lens]
    hits, total = _accuracy_counts(candidates, ref, window)
    return hits / total if total else math.nan


def boundary_metrics(
    predicted: Boundaries,
    reference: Boundaries,
    window: int,
    *,
    lengths: torch.Tensor | np.ndarray | Sequence[int],
    include_start: bool = False,
) -> dict[str, float]:
    """All scores of a segmentation: accuracy (the paper's), precision, recall, F1, and the boundary counts.

    Returns:
        dict with ``accuracy``, ``precision``, ``recall``, ``f1``, ``num_predicted``, ``num_reference`` and
        ``rate`` (predicted boundaries per candidate step, the rate of the matching random baseline).

    Examples:
        >>> m = boundary_metrics([[10, 30]], [[11, 31]], window=1, lengths=[41])
        >>> m["accuracy"], m["f1"], m["rate"]
        (1.0, 1.0, 0.05)
    """
    window = _check_window(window)
    pred, ref = _pair(predicted, reference, lengths, include_start)
    hits, n_pred = _accuracy_counts(pred, ref, window)
    scores = _prf(*_prf_counts(pred, ref, window))
    n_ref = sum(r.size for r in ref)
    candidates = _num_candidates(_lengths_array(lengths, len(pred)), include_start)
    return {
        "accuracy": hits / n_pred if n_pred else math.nan,
        "precision": scores.precision,
        "recall": scores.recall,
        "f1": scores.f1,
        "num_predicted": n_pred,
        "num_reference": n_ref,
        "rate": n_pred / candidates if candidates else math.nan,
    }


def random_baseline(
    reference: Boundaries,
    lengths: torch.Tensor | np.ndarray | Sequence[int],
    window: int,
    rate: float,
    *,
    num_samples: int = 100,
    generator: np.random.Generator | int | None = 0,
    include_start: bool = False,
) -> dict[str, float]:
    """The scores of random boundaries at a given rate, averaged over ``num_samples`` draws.

    Use the rate of the segmentation being judged (``boundary_metrics(...)["rate"]``) so that the baseline
    predicts as many boundaries as the method. Each draw is scored like the method (pooled over trajectories);
    the scores are averaged over the draws where they are defined. ``expected_accuracy`` is the exact
    expectation of :func:`expected_random_accuracy`.

    Returns:
        dict with ``accuracy``, ``precision``, ``recall``, ``f1`` (means over draws), ``expected_accuracy`` and
        ``rate``.

    Examples:
        >>> ref = [[20, 40, 60, 80]] * 10
        >>> base = random_baseline(ref, [100] * 10, window=2, rate=0.04, num_samples=20)
        >>> round(base["expected_accuracy"], 3), abs(base["accuracy"] - base["expected_accuracy"]) < 0.05
        (0.202, True)
    """
    window = _check_window(window)
    if num_samples < 1:
        raise ValueError(f"num_samples must be positive, got {num_samples}.")
    rng = generator if isinstance(generator, np.random.Generator) else np.random.default_rng(generator)
    lens = _lengths_array(lengths, None)
    ref = as_boundary_lists(reference, lens, include_start=include_start, name="reference")
    if len(ref) != lens.size:
        raise ValueError(f"reference has {len(ref)} trajectories but lengths has {lens.size}.")
    draws = {"accuracy": [], "precision": [], "recall": [], "f1": []}
    for _ in range(num_samples):
        pred = random_boundaries(lens, rate, rng, include_start=include_start)
        hits, n_pred = _accuracy_counts(pred, ref, window)
        scores = _prf(*_prf_counts(pred, ref, window))
        values = dict(accuracy=hits / n_pred if n_pred else math.nan, **scores._asdict())
        for k, v in values.items():
            if not math.isnan(v):
                draws[k].append(v)
    out = {k: float(np.mean(v)) if v else math.nan for k, v in draws.items()}
    out["expected_accuracy"] = expected_random_accuracy(ref, lens, window, include_start=include_start)
    out["rate"] = float(rate)
    return out
