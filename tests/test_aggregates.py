"""experiments.aggregates: IQM, probability of improvement, performance profiles and the stratified bootstrap,
against brute force and hand-computed figures."""
import itertools

import numpy as np
import pytest

from torchrl_options.experiments import (
    aggregate_scores,
    aggregates_markdown,
    interquartile_mean,
    performance_profile,
    plot_aggregates,
    probability_of_improvement,
    stratified_bootstrap_interval,
)
from torchrl_options.experiments.aggregates import _iqm, _poi, min_max_normalize


def test_interquartile_mean_by_hand():
    x = np.array([[1.0, 7.0], [3.0, 5.0], [100.0, -50.0], [4.0, 6.0]])  # 8 scores: 2 trimmed from each end
    assert interquartile_mean(x) == pytest.approx(np.mean([3.0, 4.0, 5.0, 6.0]))
    assert interquartile_mean([1.0, 2.0, 3.0]) == 2.0  # int(0.75) = 0 trimmed: the mean
    y = np.arange(10.0)  # scipy.stats.trim_mean(y, 0.25) drops 2 from each end
    assert interquartile_mean(y) == pytest.approx(np.mean(y[2:8]))
    batched = np.stack([x, 2 * x])
    assert _iqm(batched).tolist() == pytest.approx([4.5, 9.0])


def test_probability_of_improvement_against_brute_force():
    rng = np.random.default_rng(0)
    x = rng.integers(0, 4, (5, 3)).astype(float)  # small integers: ties happen
    y = rng.integers(0, 4, (4, 3)).astype(float)
    per_task = []
    for t in range(3):
        wins = sum((a > b) + 0.5 * (a == b) for a, b in itertools.product(x[:, t], y[:, t]))
        per_task.append(wins / (5 * 4))
    assert probability_of_improvement(x, y) == pytest.approx(np.mean(per_task))
    assert probability_of_improvement(x, y) + probability_of_improvement(y, x) == pytest.approx(1.0)
    assert probability_of_improvement(x, x) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="same tasks, got 3 and 2 columns"):
        probability_of_improvement(x, y[:, :2])


def test_performance_profile_weighs_tasks_equally():
    # task 0: 2 runs (0.1, 0.9); task 1: 2 runs (0.6, 0.6)
    x = np.array([[0.1, 0.6], [0.9, 0.6]])
    taus = [0.0, 0.5, 0.7, 1.0]
    assert performance_profile(x, taus).tolist() == pytest.approx([1.0, 0.75, 0.25, 0.0])
    with pytest.raises(ValueError, match="thresholds must be a non-empty 1-D array"):
        performance_profile(x, [])


def test_stratified_bootstrap_resamples_within_tasks():
    x = np.array([[0.0, 10.0], [1.0, 11.0], [2.0, 12.0]])  # each task's values are its own
    seen = []

    def record(m):
        seen.append(m)
        return m.mean((-2, -1))

    point, low, high = stratified_bootstrap_interval(record, x, num_resamples=300, seed=1)
    assert point == pytest.approx(x.mean())
    draws = np.concatenate(seen[1:])  # seen[0] is the point estimate
    assert draws.shape == (300, 3, 2)
    assert set(np.unique(draws[..., 0])) <= {0.0, 1.0, 2.0} and set(np.unique(draws[..., 1])) <= {10.0, 11.0, 12.0}
    # the columns are resampled independently (not the same rows in both tasks)
    assert (draws[..., 1] - draws[..., 0] != 10.0).any()
    # reproducible with the seed; narrower with more runs; a point with one run per task
    assert stratified_bootstrap_interval(_iqm, x, num_resamples=300, seed=1)[1:] == \
        stratified_bootstrap_interval(_iqm, x, num_resamples=300, seed=1)[1:]
    rng = np.random.default_rng(0)
    few, many = rng.normal(size=(4, 3)), rng.normal(size=(64, 3))
    w_few = np.subtract(*stratified_bootstrap_interval(_iqm, few)[2:0:-1])
    w_many = np.subtract(*stratified_bootstrap_interval(_iqm, many)[2:0:-1])
    assert w_many < w_few
    one = stratified_bootstrap_interval(_iqm, [[1.0, 2.0]], num_resamples=100)
    assert one == (1.5, 1.5, 1.5)


def test_stratified_bootstrap_errors():
    with pytest.raises(ValueError, match="num_resamples must be an integer >= 100"):
        stratified_bootstrap_interval(_iqm, [[1.0]], num_resamples=10)
    with pytest.raises(ValueError, match="confidence must be in"):
        stratified_bootstrap_interval(_iqm, [[1.0]], confidence=1.5)
    with pytest.raises(ValueError, match="scores\\[0\\] must hold finite scores"):
        stratified_bootstrap_interval(_iqm, [[1.0, float("inf")]])
    with pytest.raises(ValueError, match="non-empty array of scores"):
        stratified_bootstrap_interval(_iqm, np.zeros((0, 3)))


def test_min_max_normalize():
    norm, low, high = min_max_normalize({"A": [[0.0, 5.0], [10.0, 5.0]], "B": [[5.0, 5.0]]})
    assert norm["A"].tolist() == [[0.0, 0.0], [1.0, 0.0]] and norm["B"].tolist() == [[0.5, 0.0]]
    assert low.tolist() == [0.0, 5.0] and high.tolist() == [10.0, 5.0]  # a constant task maps to 0
    with pytest.raises(ValueError, match="same tasks"):
        min_max_normalize({"A": [[0.0, 1.0]], "B": [[0.0]]})


def test_aggregate_scores_verdicts_and_markdown():
    rng = np.random.default_rng(0)
    scale = np.array([1.0, 100.0, 10.0])  # tasks on different scales: normalised per task
    base = rng.normal(0.0, 1.0, (8, 3)) * scale
    scores = {"A": base, "H1": base + 2 * scale, "H1w": rng.normal(0.0, 1.0, (8, 3)) * scale, "A0": base - 2 * scale}
    pairs = [("H1", "A"), ("A0", "A"), ("H1w", "A")]
    agg = aggregate_scores(scores, pairs, tasks=["Pong", "Seaquest", "Gopher"], num_resamples=500)
    assert agg.verdict(("H1", "A")) == "ahead" and agg.verdict(("A0", "A")) == "behind"
    assert agg.verdict(("H1w", "A")) == "no evidence either way"
    assert agg.iqm["H1"][0] > agg.iqm["A"][0] > agg.iqm["A0"][0]
    for m, lo, hi in agg.iqm.values():
        assert lo <= m <= hi and 0.0 <= lo and hi <= 1.0
    prof, lo, hi = agg.profiles["H1"]
    assert prof.shape == agg.thresholds.shape and (np.diff(prof) <= 0).all() and (lo <= prof + 1e-12).all()
    text = aggregates_markdown(agg)
    assert "3 tasks (Pong, Seaquest, Gopher)" in text and "stratified percentile bootstrap" in text
    h1 = next(line for line in text.splitlines() if line.startswith("| H1 vs A |"))
    assert h1.endswith("| ahead | 8 vs 8 |")
    p, lo, hi = agg.improvement[("H1", "A")]
    assert h1.startswith(f"| H1 vs A | {p:.2f} [{lo:.2f}, {hi:.2f}] |") and lo > 0.5
    assert "| H1w vs A |" in text and "no evidence either way" in text
    with pytest.raises(ValueError, match="pairs must be \\(algorithm, baseline\\) among"):
        aggregate_scores(scores, [("H2", "A")])
    with pytest.raises(ValueError, match="tasks must name the 3 columns"):
        aggregate_scores(scores, pairs, tasks=["Pong"])
    with pytest.raises(ValueError, match="same tasks, got these numbers of columns: \\{'A': 2, 'B': 1\\}"):
        aggregate_scores({"A": [[0.0, 1.0]], "B": [[0.0]]}, [], normalize=False)
    given = aggregate_scores({"A": [[0.2, 0.4], [0.6, 0.8]]}, [], normalize=False, num_resamples=100)
    assert given.iqm["A"][0] == pytest.approx(0.5) and given.normalization == "as given"


def test_against_rliable_when_installed():
    rly = pytest.importorskip("rliable.metrics")
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(6, 4)), rng.normal(0.3, 1.0, (6, 4))
    assert interquartile_mean(x) == pytest.approx(rly.aggregate_iqm(x))
    assert probability_of_improvement(x, y) == pytest.approx(rly.probability_of_improvement(x, y))


def test_plot_aggregates_names_its_intervals(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from _figures import assert_explained, caption

    rng = np.random.default_rng(0)
    agg = aggregate_scores({"A": rng.normal(size=(3, 2)), "H1": rng.normal(size=(3, 2))}, [("H1", "A")],
                           tasks=["Pong", "Seaquest"], num_resamples=200)
    fig = plot_aggregates(agg, tmp_path / "aggregates.png", title="Atari RAM")
    assert (tmp_path / "aggregates.png").read_bytes()[:4] == b"\x89PNG"
    assert_explained(fig)
    assert "stratified percentile bootstrap over runs (Agarwal et al. 2021) (200 resamples)" in caption(fig)
    suptitle = fig.subfigs[0].get_suptitle()
    assert "stratified percentile bootstrap" in suptitle and "Pong, Seaquest" in suptitle
    assert [ax.get_title() for ax in fig.axes] == ["IQM, 95% CI", "Probability of improvement, 95% CI",
                                                  "Performance profiles, 95% bands"]
    assert any("runs/task" in t.get_text() for t in fig.axes[0].get_yticklabels())
