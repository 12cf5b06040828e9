"""experiments.intervals: the Student-t interval of a mean, its coverage at small n, paired differences, verdicts."""
import math

import numpy as np
import pytest

import torchrl_options.experiments as experiments
from torchrl_options.experiments import interval_verdict, mean_interval, paired_difference_interval
from torchrl_options.experiments.intervals import t_intervals, t_quantile

SAMPLES = 10_000  # per case: the coverage's standard error is about 0.002


def _coverage(intervals, data: str, n: int, rng) -> float:
    """Share of SAMPLES simulated samples of n values whose interval (vectorised ``intervals``) holds the mean."""
    if data == "normal":
        x, true_mean = rng.normal(2.0, 3.0, (SAMPLES, n)), 2.0
    else:  # moderately skewed
        x, true_mean = rng.lognormal(0.0, 0.5, (SAMPLES, n)), math.exp(0.5**2 / 2)
    _, low, high = intervals(x)
    return float(((low <= true_mean) & (true_mean <= high)).mean())


def _t(x):
    return t_intervals(x, 0.95, axis=1)


def _z(x):  # the normal-quantile interval: too narrow at small n, as the old percentile bootstrap was
    half = 1.959964 * x.std(1, ddof=1) / np.sqrt(x.shape[1])
    return x.mean(1), x.mean(1) - half, x.mean(1) + half


@pytest.mark.parametrize("n", [3, 5, 8, 15])
def test_coverage_at_small_n(n):
    rng = np.random.default_rng(n)
    normal = _coverage(_t, "normal", n, rng)
    assert normal >= 0.93, f"normal data, n={n}: coverage {normal:.3f}"
    assert normal <= 0.97  # not covering by being needlessly wide either
    skewed = _coverage(_t, "lognormal", n, rng)
    if n >= 5:
        assert skewed >= 0.90, f"lognormal data, n={n}: coverage {skewed:.3f}"
    # the same check catches an interval that is too narrow at small n
    if n <= 5:
        assert _coverage(_z, "normal", n, np.random.default_rng(n)) < 0.93


def test_vectorised_intervals_are_the_public_function():
    x = np.random.default_rng(0).normal(size=(4, 6))
    mean, low, high = t_intervals(x, 0.9, axis=1)
    for i in range(4):
        assert mean_interval(x[i], 0.9) == pytest.approx((mean[i], low[i], high[i]), rel=1e-12)


def test_t_quantile_against_tables():
    # two-sided 95% and 99% critical values of Student's t (standard tables)
    for df, q in [(1, 12.7062), (2, 4.3027), (3, 3.1824), (4, 2.7764), (7, 2.3646), (14, 2.1448), (30, 2.0423)]:
        assert t_quantile(0.95, df) == pytest.approx(q, abs=1e-4)
    assert t_quantile(0.99, 9) == pytest.approx(3.2498, abs=1e-4)
    assert t_quantile(0.95, 5000) == pytest.approx(1.96044, abs=1e-4)  # tends to the normal quantile, 1.95996
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="df must be an integer >= 1"):
            t_quantile(0.95, bad)


def test_mean_interval_by_hand():
    x = [0.2, 0.5, 0.3, 0.6]
    mean, low, high = mean_interval(x)
    half = 3.182446 * np.std(x, ddof=1) / 2  # t(0.975, 3) * s / sqrt(4)
    assert (mean, low, high) == pytest.approx((0.4, 0.4 - half, 0.4 + half), rel=1e-6)
    assert mean_interval([1.0, 1.0, 1.0]) == (1.0, 1.0, 1.0)
    assert mean_interval([5.0]) == (5.0, -math.inf, math.inf)  # one seed: no evidence of anything
    wider = mean_interval(x, confidence=0.99)
    assert wider[1] < low and wider[2] > high


def test_mean_interval_errors_name_the_argument():
    for bad, err, match in [
        ([], ValueError, "values needs at least one value"),
        ([1.0, float("nan")], ValueError, "values must be finite"),
        ([[1.0, 2.0]], ValueError, "values must be one-dimensional"),
        (["a", "b"], TypeError, "values must be a sequence of numbers"),
        ("12", TypeError, "values must be a sequence of numbers"),
    ]:
        with pytest.raises(err, match=match):
            mean_interval(bad)
    for bad in (0.0, 1.0, 95):
        with pytest.raises(ValueError, match="confidence must be in \\(0, 1\\)"):
            mean_interval([1.0, 2.0], confidence=bad)
    with pytest.raises(TypeError, match="confidence must be a float"):
        mean_interval([1.0, 2.0], confidence="0.95")


def test_paired_difference_interval_uses_the_per_seed_differences():
    base = np.array([0.1, 0.5, 0.9, 0.3])
    options = base + np.array([0.11, 0.09, 0.1, 0.1])  # a small, consistent gain on every seed
    diff = paired_difference_interval(options, base)
    assert diff == pytest.approx(mean_interval(options - base))
    assert interval_verdict(diff) == "ahead"
    # unpaired, the two intervals overlap widely: the pairing is what shows the gain
    assert mean_interval(options)[1] < mean_interval(base)[2]
    assert interval_verdict(paired_difference_interval(base, options)) == "behind"
    with pytest.raises(ValueError, match="values and baseline must hold one value per seed .* 3 and 4"):
        paired_difference_interval([1.0, 2.0, 3.0], base)


def test_interval_verdict():
    assert interval_verdict((0.3, 0.1, 0.5)) == "ahead"
    assert interval_verdict((-0.3, -0.5, -0.1)) == "behind"
    assert interval_verdict((0.3, -0.1, 0.5)) == "no evidence either way"
    assert interval_verdict((0.3, 0.0, 0.5)) == "no evidence either way"  # touching 0 is not above it
    assert interval_verdict((1.0, -math.inf, math.inf)) == "no evidence either way"
    assert interval_verdict((0.6, 0.55, 0.7), reference=0.5) == "ahead"
    with pytest.raises(ValueError, match="interval must be \\(mean, low, high\\)"):
        interval_verdict((0.1, 0.2))


def test_one_interval_function_in_the_package():
    assert experiments.mean_interval is mean_interval
    assert not hasattr(experiments, "bootstrap_ci")
    import torchrl_options.experiments.results as results

    assert not hasattr(results, "bootstrap_ci")


def test_against_scipy_when_installed():
    stats = pytest.importorskip("scipy.stats")
    for confidence in (0.8, 0.95, 0.99):
        for df in (1, 2, 3, 7, 14, 50, 500):
            assert t_quantile(confidence, df) == pytest.approx(stats.t.ppf((1 + confidence) / 2, df), abs=1e-8)
    x = np.random.default_rng(1).normal(size=5)
    low, high = stats.t.interval(0.95, 4, loc=x.mean(), scale=stats.sem(x))
    assert mean_interval(x)[1:] == pytest.approx((low, high), abs=1e-10)
