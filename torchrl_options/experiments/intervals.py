"""Intervals of a mean over seeds that hold their coverage at the few seeds RL experiments run, and verdicts.

Every interval the package reports (summaries, Atari tables, the bands of ``curves.png``) comes from
:func:`mean_interval`: a Student-t interval of the mean over seeds. Comparisons of two conditions run on the same
seeds use it on the per-seed differences (:func:`paired_difference_interval`), and :func:`interval_verdict` words
the result as "ahead", "behind" or "no evidence either way".

Why not a percentile bootstrap: resampling n seeds cannot see more spread than those n seeds show, so at small n its
intervals are too narrow. Simulated, 95% percentile-bootstrap intervals of the mean covered the true mean of
normal data 75% of the time at n = 3, 83% at n = 5, 89% at n = 8 and 92% at n = 15
(``python benchmarks/bench_intervals.py`` prints the table); the Student-t interval covers 95% at every n on normal
data.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

__all__ = ["interval_verdict", "mean_interval", "paired_difference_interval", "t_intervals", "t_quantile"]

#: the three verdicts of :func:`interval_verdict`
AHEAD, BEHIND, NO_EVIDENCE = "ahead", "behind", "no evidence either way"

#: how :func:`mean_interval` computes its interval, for tables and plots to name it
METHOD = "Student-t interval of the mean over seeds"


def _t_two_sided_mass(t: float, df: int) -> float:
    """P(|T| <= t) for Student's t with an integer number of degrees of freedom ``df`` (exact, closed form).

    With theta = arctan(t / sqrt(df)): for odd df, (2 / pi) (theta + sin(theta) cos(theta) S) where S sums
    ``prod_{i=1..k} (2i) / (2i + 1) cos(theta)^(2k)`` for k = 0 .. (df - 3) / 2; for even df,
    sin(theta) sum_{k=0}^{(df - 2) / 2} prod_{i=1..k} (2i - 1) / (2i) cos(theta)^(2k) (Abramowitz and Stegun 26.7.3).
    """
    theta = math.atan(t / math.sqrt(df))
    c2 = math.cos(theta) ** 2
    if df % 2:
        if df == 1:
            return 2 * theta / math.pi
        total, term = 1.0, 1.0
        for k in range(1, (df - 3) // 2 + 1):
            term *= c2 * (2 * k) / (2 * k + 1)
            total += term
        return 2 / math.pi * (theta + math.sin(theta) * math.cos(theta) * total)
    total, term = 1.0, 1.0
    for k in range(1, (df - 2) // 2 + 1):
        term *= c2 * (2 * k - 1) / (2 * k)
        total += term
    return math.sin(theta) * total


@functools.lru_cache(maxsize=1024, typed=True)
def t_quantile(confidence: float, df: int) -> float:
    """The ``t`` with P(|T| <= t) = ``confidence`` for Student's t with ``df`` degrees of freedom.

    That is the ``(1 + confidence) / 2`` quantile, the half-width of a two-sided interval in standard errors.
    Computed from the exact distribution function by bisection (to 1e-12), so it needs no scipy.

    Args:
        confidence (float): in (0, 1).
        df (int): degrees of freedom, at least 1.

    Examples:
        >>> round(t_quantile(0.95, 2), 4), round(t_quantile(0.95, 14), 4), round(t_quantile(0.99, 1), 3)
        (4.3027, 2.1448, 63.657)
    """
    confidence = _check_confidence(confidence)
    if isinstance(df, bool) or not isinstance(df, (int, np.integer)) or df < 1:
        raise ValueError(f"df must be an integer >= 1, got {df!r}.")
    df = int(df)
    lo, hi = 0.0, 1.0
    while _t_two_sided_mass(hi, df) < confidence:
        hi *= 2
    while hi - lo > 1e-12 * max(hi, 1.0):
        mid = 0.5 * (lo + hi)
        if _t_two_sided_mass(mid, df) < confidence:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _check_confidence(confidence: float) -> float:
    if isinstance(confidence, bool) or not isinstance(confidence, (int, float, np.floating)):
        raise TypeError(f"confidence must be a float in (0, 1), got {type(confidence).__name__} {confidence!r}.")
    if not 0.0 < float(confidence) < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}.")
    return float(confidence)


def _as_values(values, name: str) -> np.ndarray:
    """``values`` as a finite 1-D float array with at least one entry, or a clear error naming ``name``."""
    if isinstance(values, (str, bytes)):
        raise TypeError(f"{name} must be a sequence of numbers, got {type(values).__name__} {values!r}.")
    try:
        x = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be a sequence of numbers, got {values!r} ({err}).") from None
    if x.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional (one value per seed), got shape {tuple(x.shape)}.")
    if x.size == 0:
        raise ValueError(f"{name} needs at least one value, got none.")
    if not np.isfinite(x).all():
        raise ValueError(f"{name} must be finite, got {x.tolist()!r}.")
    return x


def t_intervals(x: np.ndarray, confidence: float = 0.95, axis: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mean_interval` along ``axis`` of an array (e.g. a learning curve per seed), vectorised.

    Returns the arrays ``(mean, low, high)``; with one value along ``axis``, ``low`` and ``high`` are -inf and inf.
    The caller checks the values (:func:`mean_interval` does, for one sample).

    Examples:
        >>> mean, low, high = t_intervals(np.array([[0.0, 1.0], [1.0, 1.0], [2.0, 1.0]]), axis=0)
        >>> mean.tolist(), np.round(low, 3).tolist(), high[1].item()
        ([1.0, 1.0], [-1.484, 1.0], 1.0)
    """
    x = np.asarray(x, dtype=float)
    confidence = _check_confidence(confidence)
    n = x.shape[axis]
    mean = x.mean(axis)
    if n < 2:
        return mean, np.full_like(mean, -np.inf), np.full_like(mean, np.inf)
    half = t_quantile(confidence, n - 1) * x.std(axis, ddof=1) / math.sqrt(n)
    return mean, mean - half, mean + half


def mean_interval(values: Sequence[float] | np.ndarray, confidence: float = 0.95) -> tuple[float, float, float]:
    """The mean of ``values`` (one per seed) and a Student-t confidence interval of it: ``(mean, low, high)``.

    The interval is ``mean -/+ t * s / sqrt(n)``, with ``s`` the sample standard deviation (n - 1 in the
    denominator) and ``t`` the ``(1 + confidence) / 2`` quantile of Student's t with n - 1 degrees of freedom. Its
    coverage is exact on normal data at every n. Measured by simulation (``benchmarks/bench_intervals.py
    --samples 20000``), nominal 95% intervals covered the true mean 94.7-95.2% of the time on normal data at n = 3,
    5, 8 and 15, and 91.7-92.6% on moderately skewed data (lognormal, sigma 0.5), where the percentile bootstrap
    this replaces covered 74.9% (n = 3) to 91.8% (n = 15) on normal data and 71.6-89.6% on lognormal data.
    Heavily skewed data need more seeds for any interval.

    With a single value there is no spread to go by: the interval is (-inf, inf) and any comparison it backs says
    "no evidence either way". Equal values give a zero-width interval.

    Args:
        values (sequence of float): one finite value per seed (e.g. a seed's mean return over its last episodes).
        confidence (float): the nominal coverage, in (0, 1). Defaults to 0.95.

    Returns:
        ``(mean, low, high)`` as floats.

    Raises:
        ValueError: no values, values that are not finite or not one-dimensional, a confidence outside (0, 1).
        TypeError: values that are not numbers.

    Examples:
        >>> mean, low, high = mean_interval([1.0, 2.0, 3.0, 4.0])
        >>> mean, round(low, 3), round(high, 3)
        (2.5, 0.446, 4.554)
        >>> mean_interval([3.0])
        (3.0, -inf, inf)
    """
    x = _as_values(values, "values")
    mean, low, high = t_intervals(x, confidence)
    return float(mean), float(low), float(high)


def paired_difference_interval(
    values: Sequence[float] | np.ndarray, baseline: Sequence[float] | np.ndarray, confidence: float = 0.95
) -> tuple[float, float, float]:
    """Mean and Student-t interval of ``values - baseline``, entry by entry (the same seeds in the same order).

    Pairing by seed removes what the seeds share (the same environment seeds, the same phase-1 agent), so the
    interval of the difference is usually much narrower than the two intervals side by side would suggest.

    Args:
        values (sequence of float): per seed, the condition's figure.
        baseline (sequence of float): per seed, the baseline's figure, same length and seed order.
        confidence (float): the nominal coverage, in (0, 1).

    Examples:
        >>> m, low, high = paired_difference_interval([1.1, 2.2, 3.1], [1.0, 2.0, 3.0])
        >>> round(m, 3), round(low, 3), round(high, 3), interval_verdict((m, low, high))
        (0.133, -0.01, 0.277, 'no evidence either way')
    """
    x = _as_values(values, "values")
    y = _as_values(baseline, "baseline")
    if x.shape != y.shape:
        raise ValueError(
            f"values and baseline must hold one value per seed for the same seeds, got {x.size} and {y.size} values."
        )
    return mean_interval(x - y, confidence)


def interval_verdict(interval: tuple[float, float, float], reference: float = 0.0) -> str:
    """``"ahead"`` when the interval ``(mean, low, high)`` lies above ``reference``, ``"behind"`` when below,
    ``"no evidence either way"`` when it contains it.

    Examples:
        >>> interval_verdict((0.2, 0.1, 0.3)), interval_verdict((-0.2, -0.3, -0.1)), interval_verdict((0.1, -0.1, 0.3))
        ('ahead', 'behind', 'no evidence either way')
    """
    if len(interval) != 3:
        raise ValueError(f"interval must be (mean, low, high), got {interval!r}.")
    _, low, high = (float(v) for v in interval)
    if low > reference:
        return AHEAD
    if high < reference:
        return BEHIND
    return NO_EVIDENCE
