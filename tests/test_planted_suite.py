"""testing/planted_suite.py: relabelling accuracy, planted generators and their Bayes ceilings, discovery on them."""
import itertools
import math

import pytest
import torch

from torchrl_options import DDOLoss, discover_options
from torchrl_options.testing import (
    best_matching_accuracy,
    planted_gaussian_demonstrations,
    PLANTED_SUITE,
    posterior_accuracy,
)
from torchrl_options.testing.planted_suite import corridor_options, planted_tabular_demonstrations, tabular_log_probabilities


def _brute_force(pred, truth, k):
    best = 0
    for perm in itertools.permutations(range(k)):
        best = max(best, int((torch.tensor(perm)[pred] == truth).sum()))
    return best / truth.numel()


@pytest.mark.parametrize("seed", range(5))
def test_best_matching_accuracy_equals_brute_force_over_permutations(seed):
    g = torch.Generator().manual_seed(seed)
    k = 2 + seed % 4
    truth = torch.randint(k, (60,), generator=g)
    pred = torch.where(torch.rand(60, generator=g) < 0.6, (truth + seed) % k, torch.randint(k, (60,), generator=g))
    assert best_matching_accuracy(pred, truth) == pytest.approx(_brute_force(pred, truth, k))


def test_best_matching_accuracy_respects_the_mask_and_refuses_an_empty_one():
    truth = torch.tensor([0, 0, 1, 1])
    pred = torch.tensor([1, 1, 0, 1])
    mask = torch.tensor([True, True, True, False])
    assert best_matching_accuracy(pred, truth, mask) == 1.0
    with pytest.raises(ValueError, match="no valid step"):
        best_matching_accuracy(pred, truth, torch.zeros(4, dtype=torch.bool))


def test_tabular_demonstrations_follow_the_planted_model_and_are_padded():
    spec = corridor_options(6, noise=0.2)
    data = planted_tabular_demonstrations(
        spec["policy"], spec["termination"], spec["next_state"], spec["features"], num_trajectories=16,
        lengths=(5, 12), seed=0,
    )  # fmt: skip
    mask = data["collector", "mask"]
    lengths = mask.sum(1)
    assert data.batch_size == torch.Size([16, 12]) and lengths.min() >= 5 and lengths.max() <= 12
    assert (mask[:, :-1] >= mask[:, 1:]).all()  # padding only at the end
    truth = tabular_log_probabilities(data, spec["policy"], spec["termination"])
    # every demonstrated action has positive probability under the option that took it
    taken = truth["log_pi"].gather(-1, data["true_option"].unsqueeze(-1)).squeeze(-1)
    assert torch.isfinite(taken[mask]).all()
    # the truth's posterior labels the steps far better than chance
    ceiling, ll = posterior_accuracy(truth, data["true_option"])
    assert ceiling > 0.8 and math.isfinite(ll) and ll < 0


def test_gaussian_demonstrations_ceiling_is_high_and_likelihood_finite():
    data, truth = planted_gaussian_demonstrations(16, (20, 30), seed=1)
    assert data["action"].is_floating_point() and data["action"].shape[-1] == 2
    ceiling, ll = posterior_accuracy(truth, data["true_option"])
    assert ceiling > 0.95 and math.isfinite(ll)
    # true_switch marks where an option starts: the first step, and every change of option (a termination may also
    # redraw the same option, so not every switch changes it)
    option, switch = data["true_option"], data["true_switch"]
    assert switch.dtype == torch.bool and switch[:, 0].all()
    changed = option[:, 1:] != option[:, :-1]
    assert not (changed & ~switch[:, 1:]).any()
    assert (switch[:, 1:] & ~changed).any()
    # a termination happens at the state reached: the truth's termination probability there is the planted one
    term = truth["log_term"].exp().gather(-1, option[..., None]).squeeze(-1)
    assert term[:, :-1][switch[:, 1:]].mean() > term[:, :-1][~switch[:, 1:]].mean() + 0.3


def test_suite_problems_are_reproducible_and_varied():
    names = [p.name for p in PLANTED_SUITE]
    assert len(set(names)) == len(names) >= 6
    assert {p.action_space for p in PLANTED_SUITE} == {"categorical", "continuous"}
    assert min(p.num_options for p in PLANTED_SUITE) == 2 and max(p.num_options for p in PLANTED_SUITE) == 8
    problem = PLANTED_SUITE[0]
    a, _ = problem.make(3)
    b, _ = problem.make(3)
    assert (a == b).all()


def _problem(name):
    return next(p for p in PLANTED_SUITE if p.name == name)


@pytest.mark.parametrize("name, seed, rows", [("corridor-2", 1, 64), ("landmarks-3", 0, 96), ("landmarks-8", 1, 256)])
def test_defaults_reach_the_bayes_ceiling_on_small_suite_members(name, seed, rows):
    """discover_options with nothing but K and the seed set: within 3 points of the truth's own posterior."""
    problem = _problem(name)
    data, truth = problem.make(seed)
    data, truth = data[:rows], {k: v[:rows] for k, v in truth.items()}  # fewer trajectories: a fast test
    ceiling, truth_ll = problem.ceiling(data, truth)
    result = discover_options(data, problem.num_options, seed=seed, progress=False, return_info=True)
    with torch.no_grad():
        acc, ll = posterior_accuracy(DDOLoss(result.options).log_probabilities(data), data["true_option"])
    assert acc >= ceiling - 0.03, (acc, ceiling)
    assert ll >= truth_ll - 5e-3, (ll, truth_ll)
    assert len(result.restart_log_likelihoods) > 1  # several starts are part of the default
    assert not result.duplicate_options and len(result.option_usage) == problem.num_options


def test_defaults_reach_the_truths_likelihood_on_a_small_gaussian_member():
    """Continuous options with the defaults: labels at the ceiling and a likelihood at or above the truth's minus 1e-3
    nats per step (with a termination of one tanh layer, ``termination_cells=8``, this run ends 0.016 below it)."""
    problem = _problem("gaussian-3")
    data, truth = problem.make(0)
    data, truth = data[:64], {k: v[:64] for k, v in truth.items()}  # at 24 trajectories one layer over-fits past it
    ceiling, truth_ll = problem.ceiling(data, truth)
    result = discover_options(data, problem.num_options, action_space="continuous", seed=0, progress=False,
                              return_info=True)  # fmt: skip
    assert result.options.config["termination_cells"] == [16, 16]
    with torch.no_grad():
        lp = DDOLoss(result.options, action_space="continuous").log_probabilities(data)
    acc, ll = posterior_accuracy(lp, data["true_option"])
    assert acc >= ceiling - 0.02, (acc, ceiling)
    assert ll >= truth_ll - 1e-3, (ll, truth_ll)


@pytest.mark.slow
@pytest.mark.parametrize("problem", PLANTED_SUITE, ids=lambda p: p.name)
@pytest.mark.parametrize("seed", range(3))
def test_defaults_reach_the_bayes_ceiling_on_the_whole_suite(problem, seed):
    data, truth = problem.make(seed)
    ceiling, truth_ll = problem.ceiling(data, truth)
    result = discover_options(
        data, problem.num_options, action_space=problem.action_space, seed=seed, progress=False, return_info=True
    )
    with torch.no_grad():
        lp = DDOLoss(result.options, result.meta_control, action_space=problem.action_space).log_probabilities(data)
    acc, ll = posterior_accuracy(lp, data["true_option"])
    # within 2 points of the ceiling, or (not identifiable at this data size) a likelihood at or above the truth's
    assert acc >= ceiling - 0.02 or ll >= truth_ll, (acc, ceiling, ll, truth_ll)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_discover_hierarchy_defaults_on_the_two_level_member(seed):
    """The suite's two-level member (``two-level-4x4`` of ``benchmarks/bench_planted_suite.py``): 64 trajectories of
    a planted 4-over-4 hierarchy, ``discover_hierarchy`` with its defaults. Level 2's labels within 2 points of the
    truth's own posterior, or (not identifiable at this data size) a likelihood at or above the truth's."""
    from torchrl_options.hierarchy import discover_hierarchy, hierarchical_forward_backward, HierarchicalDDOLoss
    from torchrl_options.testing import planted_two_level_demonstrations, planted_two_level_log_probabilities

    data = planted_two_level_demonstrations(64, 60, seed=seed)
    truth = hierarchical_forward_backward(**planted_two_level_log_probabilities(data), marginals=True)
    ceiling = best_matching_accuracy(truth.most_likely(2), data["true_option_2"])
    truth_ll = truth.log_likelihood.sum().item() / data.numel()
    hierarchy = discover_hierarchy(data, [4, 4], seed=seed, progress=False)
    loss = HierarchicalDDOLoss(hierarchy.options(2), hierarchy.levels[:1], num_actions=4)
    with torch.no_grad():
        acc = best_matching_accuracy(loss.posterior(data).most_likely(2), data["true_option_2"])
        ll = loss(data)["log_likelihood_per_step"].item()
    assert math.isfinite(ll) and ceiling > 0.9
    assert acc >= ceiling - 0.02 or ll >= truth_ll, (acc, ceiling, ll, truth_ll)


def _suite_rows(name):
    """The rows of a kept ``results/planted_suite/<name>.csv`` (one per problem and seed)."""
    import csv
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "results" / "planted_suite" / f"{name}.csv"
    with open(path, newline="") as f:
        return [dict(r, seed=int(r["seed"]), **{k: float(r[k]) for k in ("ceiling", "accuracy", "ll", "truth_ll")})
                for r in csv.DictReader(f)]  # fmt: skip


def suite_table_row(problem, rows):
    """The planted-suite page's table row of ``problem``: seeds, ceiling, mean and worst labels, worst gap,
    likelihood vs the truth's, seeds near the ceiling and seeds at or above the truth's likelihood."""
    runs = [r for r in rows if r["problem"] == problem]
    n = len(runs)
    mean = lambda k: sum(r[k] for r in runs) / n  # noqa: E731
    dll = [r["ll"] - r["truth_ll"] for r in runs]
    near = sum(r["ceiling"] - r["accuracy"] <= 0.02 and r["ll"] >= r["truth_ll"] - 1e-3 for r in runs)
    above = sum(r["ll"] >= r["truth_ll"] for r in runs)
    return (f"| {problem} | {n} | {mean('ceiling'):.3f} | {mean('accuracy'):.3f} | "
            f"{min(r['accuracy'] for r in runs):.3f} | {100 * max(r['ceiling'] - r['accuracy'] for r in runs):.1f} | "
            f"{sum(dll) / n:+.4f} (worst {min(dll):+.4f}) | {near}/{n} | {above}/{n} |")  # fmt: skip


def test_kept_suite_figures_are_quoted():
    """The tables on docs/experiments/planted_suite.md are recomputed from the kept results/planted_suite/*.csv: the
    defaults', the random starts', segment starts with the width chosen on held-out data, the two-level problem."""
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "experiments" / "planted_suite.md").read_text()
    for name in ("defaults", "defaults_2026-12-05", "random_starts"):
        rows = _suite_rows(name)
        problems = list(dict.fromkeys(r["problem"] for r in rows))
        two_level = {"two-level-4x4"} if name == "defaults" else set()
        assert set(problems) == {p.name for p in PLANTED_SUITE} | two_level
        for problem in problems:
            assert sum(r["problem"] == problem for r in rows) == 10, (name, problem)
            row = suite_table_row(problem, rows)
            assert row in page, f"{name}: {row}"
    # gaussian-3 with one-layer, 16-unit (the defaults) and 32-unit two-layer termination networks
    for name, label in (("gaussian3_one_layer", "one layer of 8 (the previous defaults)"),
                        ("defaults_2026-12-05",
                         "**two layers of 16 (the defaults; stopped after 20 iterations without gain until 2026-12-06)**"),
                        ("gaussian3_termination32", "two layers of 32")):  # fmt: skip
        rows = [r for r in _suite_rows(name) if r["problem"] == "gaussian-3"]
        assert sorted(r["seed"] for r in rows) == list(range(10)), name
        row = f"| {label} " + suite_table_row("gaussian-3", rows).split("| gaussian-3 ", 1)[1]
        assert row in page, f"{name}: {row}"
    # the runs on part of the suite: segment starts with num_cells="auto", the two-level problem at 10 seeds
    for name, expected in (("segments_auto_width", {"landmarks-8", "walls-4", "geometric-4", "landmarks-3"}),
                           ("two_level_10_seeds", {"two-level-4x4"})):  # fmt: skip
        rows = _suite_rows(name)
        assert {r["problem"] for r in rows} == expected
        for problem in expected:
            assert sorted(r["seed"] for r in rows if r["problem"] == problem) == list(range(10)), (name, problem)
            row = suite_table_row(problem, rows)
            assert row in page, f"{name}: {row}"
    # more trajectories: 4x for walls-4, geometric-4 and the two-level problem (seeds 0-9) and landmarks-8 (seeds
    # 0-4), 16x for walls-4
    for name, expected, seeds in (("four_times_the_data", {"walls-4", "geometric-4"}, 10),
                                  ("landmarks8_four_times_the_data", {"landmarks-8"}, 5),
                                  ("two_level_four_times_the_data", {"two-level-4x4"}, 10),
                                  ("walls4_sixteen_times_the_data", {"walls-4"}, 10)):  # fmt: skip
        rows = _suite_rows(name)
        assert {r["problem"] for r in rows} == expected
        for problem in expected:
            runs = [r for r in rows if r["problem"] == problem]
            assert sorted(r["seed"] for r in runs) == list(range(seeds)), (name, problem)
            mean = lambda k: sum(r[k] for r in runs) / len(runs)  # noqa: E731
            near = sum(r["ceiling"] - r["accuracy"] <= 0.02 and r["ll"] >= r["truth_ll"] - 1e-3 for r in runs)
            row = (f"| {mean('ceiling'):.3f} | {mean('accuracy'):.3f} | "
                   f"{100 * max(r['ceiling'] - r['accuracy'] for r in runs):.1f} | "
                   f"{mean('ll') - mean('truth_ll'):+.4f} | {near}/{seeds} |")  # fmt: skip
            assert row in page, f"{name}: {row}"
