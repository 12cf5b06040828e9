"""Boundary metrics on hand-made cases, against brute force, and the random baseline."""
import itertools
import math

import numpy as np
import pytest
import torch

from torchrl_options.segmentation import (
    as_boundary_lists,
    boundary_accuracy,
    boundary_metrics,
    boundary_precision_recall_f1,
    expected_random_accuracy,
    random_baseline,
    random_boundaries,
)


def test_accuracy_counts_exactly_one_reference_in_window():
    ref = [[10, 20, 22, 40]]
    # 11: one (10); 21: two (20, 22) -> miss; 30: none -> miss; 38: one (40); 42: one (40)
    assert boundary_accuracy([[11, 21, 30, 38, 42]], ref, window=2) == pytest.approx(3 / 5)
    # the window is inclusive
    assert boundary_accuracy([[12]], [[10]], window=2) == 1.0
    assert boundary_accuracy([[13]], [[10]], window=2) == 0.0


def test_accuracy_pools_trajectories_and_is_nan_without_predictions():
    assert boundary_accuracy([[5], [5, 50]], [[5], [6]], window=1) == pytest.approx(2 / 3)
    assert math.isnan(boundary_accuracy([[], []], [[3], [4]], window=1))


def test_start_of_trajectory_is_not_a_boundary():
    pred = torch.tensor([[1, 0, 0, 1, 0, 0]], dtype=torch.bool)
    ref = torch.tensor([[1, 0, 0, 0, 1, 0]], dtype=torch.bool)
    m = boundary_metrics(pred, ref, 1, lengths=[6])
    assert (m["num_predicted"], m["num_reference"]) == (1, 1)
    assert m["accuracy"] == 1.0 and m["rate"] == pytest.approx(1 / 5)
    m = boundary_metrics(pred, ref, 1, lengths=[6], include_start=True)
    assert (m["num_predicted"], m["num_reference"]) == (2, 2)


def test_padding_is_ignored():
    pred = torch.tensor([[0, 0, 1, 0, 1, 1]], dtype=torch.bool)  # the last two steps are padding
    ref = torch.tensor([[0, 0, 1, 0, 0, 0]], dtype=torch.bool)
    assert boundary_precision_recall_f1(pred, ref, 0, lengths=[4]) == (1.0, 1.0, 1.0)
    mask = torch.tensor([[1, 1, 1, 1, 0, 0]], dtype=torch.bool)
    assert boundary_precision_recall_f1(pred, ref, 0, lengths=mask) == (1.0, 1.0, 1.0)


def test_boundary_formats_agree():
    mask = torch.zeros(2, 30, dtype=torch.bool)
    mask[0, [0, 4, 17]] = True
    mask[1, [9]] = True
    lists = [[4, 17], [9]]
    assert [b.tolist() for b in as_boundary_lists(mask)] == lists
    assert [b.tolist() for b in as_boundary_lists(mask.numpy())] == lists
    assert [b.tolist() for b in as_boundary_lists(mask.tolist())] == lists
    assert [b.tolist() for b in as_boundary_lists([torch.tensor([17, 4]), np.array([9, 0])])] == lists


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="predicted"):
        boundary_accuracy([[1.5]], [[1]], 1)
    with pytest.raises(ValueError, match="reference"):
        boundary_accuracy([[1]], [[-2]], 1)
    with pytest.raises(ValueError, match="window"):
        boundary_accuracy([[1]], [[1]], -1)
    with pytest.raises(ValueError, match="trajectories"):
        boundary_accuracy([[1], [2]], [[1]], 1)


def test_precision_recall_matching_is_one_to_one():
    # both predictions are within 2 of the single reference: only one may take it
    assert boundary_precision_recall_f1([[9, 11]], [[10]], 2) == pytest.approx((0.5, 1.0, 2 / 3))
    # a greedy "closest first" pairing would match 12-13 and leave 10 and 15 apart; the maximum matching pairs both
    s = boundary_precision_recall_f1([[10, 13]], [[12, 15]], 2)
    assert s == pytest.approx((1.0, 1.0, 1.0))
    assert all(math.isnan(x) for x in boundary_precision_recall_f1([[]], [[]], 2))
    p, r, f = boundary_precision_recall_f1([[]], [[4]], 2)
    assert math.isnan(p) and r == 0.0 and f == 0.0


def _max_matching_brute(p, r, w):
    best = 0
    for k in range(min(len(p), len(r)), 0, -1):
        for ps in itertools.combinations(p, k):
            for rs in itertools.permutations(r, k):
                if all(abs(a - b) <= w for a, b in zip(ps, rs)):
                    return k
    return best


@pytest.mark.parametrize("seed", range(30))
def test_matching_is_maximum(seed):
    rng = np.random.default_rng(seed)
    p = sorted(rng.choice(np.arange(1, 25), rng.integers(0, 6), replace=False).tolist())
    r = sorted(rng.choice(np.arange(1, 25), rng.integers(0, 6), replace=False).tolist())
    w = int(rng.integers(0, 4))
    n = _max_matching_brute(p, r, w)
    s = boundary_precision_recall_f1([p], [r], w)
    if p:
        assert s.precision == pytest.approx(n / len(p))
    if r:
        assert s.recall == pytest.approx(n / len(r))


def test_random_boundaries_rate_and_range():
    b = random_boundaries([1000] * 20, 0.1, 0)
    rate = sum(x.size for x in b) / (999 * 20)
    assert abs(rate - 0.1) < 0.01
    assert all(x.min() >= 1 and x.max() <= 999 for x in b)
    assert random_boundaries([1], 1.0, 0)[0].size == 0  # a one-step trajectory has no candidate
    with pytest.raises(ValueError, match="rate"):
        random_boundaries([5], 1.5)


def test_random_baseline_matches_its_expectation():
    rng = np.random.default_rng(0)
    ref = [np.sort(rng.choice(np.arange(1, 200), 6, replace=False)) for _ in range(20)]
    expected = expected_random_accuracy(ref, [200] * 20, 2)
    base = random_baseline(ref, [200] * 20, 2, rate=0.03, num_samples=200, generator=1)
    assert base["accuracy"] == pytest.approx(expected, abs=0.02)
    assert base["expected_accuracy"] == expected
    # the F1 of random boundaries is far below a perfect segmentation
    assert base["f1"] < 0.3
    assert boundary_metrics(ref, ref, 2, lengths=[200] * 20)["f1"] == 1.0


def test_plot_segmentation_explains_itself(tmp_path):
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt
    from _figures import assert_explained, caption, legend_labels

    from torchrl_options.segmentation import plot_segmentation

    fig = plot_segmentation(torch.tensor([[0, 0, 1, 1, 2], [1, 1, 1, 0, -1]]), [[2, 4], [3]], path=tmp_path / "s.png")
    assert (tmp_path / "s.png").read_bytes()[:4] == b"\x89PNG"
    assert_explained(fig, min_caption=100)
    assert fig.axes[0].get_title() == "Segmentation of 2 trajectories into 3 options"
    assert legend_labels(fig) == ["option 0", "option 1", "option 2", "reference boundary"]
    assert "Crosses: the reference boundaries" in caption(fig)
    plt.close(fig)
