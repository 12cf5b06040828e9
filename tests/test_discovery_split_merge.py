"""discovery.split_merge: split-and-merge moves after DDO's main fit (discover_options(split_merge=n))."""
import pytest
import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_options import DDOLoss, discover_options, GaussianOptionsMLP, OptionsMLP
from torchrl_options.discovery import option_diagnostics
from torchrl_options.discovery.split_merge import (
    check_split_merge_options,
    copy_option,
    MIN_GAIN,
    propose_pairs,
)
from torchrl_options.discovery.width import held_out_log_likelihood
from torchrl_options.testing import planted_corridor_demonstrations

FAST = dict(num_iterations=30, restarts=1, progress=False, return_info=True)
MOVE_FIELDS = {"move", "victim", "donor", "log_likelihood_before", "log_likelihood_after", "accepted"}


@pytest.fixture(scope="module")
def data():
    return planted_corridor_demonstrations(6, 20, seed=0)


def _params(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def _same(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_propose_pairs_cycles_victims_by_usage_with_duplicates_first():
    usage = [0.4, 0.05, 0.35, 0.2]
    # victims in increasing usage, the most-used option never a victim; donor: the most-used other option
    assert [propose_pairs(usage, [], m) for m in range(3)] == [(1, 0), (3, 0), (2, 0)]
    # second pass: the second most-used donor
    assert propose_pairs(usage, [], 3) == (1, 2)
    assert propose_pairs(usage, [], 5) == (2, 3)
    # the less-used member of a duplicated pair first
    assert propose_pairs(usage, [(0, 2)], 0) == (2, 0)
    assert propose_pairs(usage, [(0, 2)], 1) == (1, 0)


@pytest.mark.parametrize(
    "make", [lambda: OptionsMLP(3, 2, 4, num_cells=5), lambda: GaussianOptionsMLP(3, 2, 4, num_cells=5)]
)
def test_copy_option_overwrites_only_the_victim_with_a_noisy_copy(make):
    options = make()
    before = dict(options.named_parameters())
    before = {k: v.detach().clone() for k, v in before.items()}
    new = copy_option(options, victim=1, donor=3, generator=torch.Generator().manual_seed(0), noise=0.3)
    # the original is untouched
    assert all(torch.equal(before[k], v) for k, v in options.named_parameters())
    moved = False
    for name, p in new.named_parameters():
        old = before[name]
        for k in (0, 2, 3):
            assert torch.equal(p[k], old[k]), name
        scale = 0.3 * old[3].abs().mean()
        # a copy of the donor up to noise of the stated scale (4 standard deviations)
        assert (p[1] - old[3]).abs().max() <= 4 * scale + 1e-6, name
        moved |= not torch.equal(p[1], old[1])
    assert moved
    exact = copy_option(options, victim=1, donor=3, generator=torch.Generator(), noise=0.0)
    for name, p in exact.named_parameters():
        assert torch.equal(p[1], before[name][3])


def test_check_split_merge_options_refuses_parameters_shared_by_options():
    check_split_merge_options(GaussianOptionsMLP(3, 2, 4), 4)
    with pytest.raises(ValueError, match="leading dimension \\(num_options=4\\), got trunk.0.weight"):
        check_split_merge_options(OptionsMLP(3, 2, 4, architecture="shared"), 4)
    with pytest.raises(ValueError, match="num_options=5"):
        check_split_merge_options(OptionsMLP(3, 2, 4), 5)


def test_split_merge_zero_is_the_fit_without_moves(data):
    today = discover_options(data, 3, seed=0, **FAST)
    off = discover_options(data, 3, seed=0, split_merge=0, split_merge_iterations=7, **FAST)
    assert _same(_params(today.options), _params(off.options))
    assert off.history == today.history and off.option_usage == today.option_usage
    assert off.split_merge_moves == [] and today.split_merge_moves == []


def test_moves_never_lower_the_training_likelihood_and_are_logged(data):
    main = discover_options(data, 3, seed=0, **FAST)
    result = discover_options(data, 3, seed=0, split_merge=3, split_merge_iterations=15, **FAST)
    main_ll = held_out_log_likelihood(main.options, None, data)
    final_ll = held_out_log_likelihood(result.options, None, data)
    assert final_ll >= main_ll - 1e-6
    # the main fit is unchanged by the moves that follow it
    assert result.history[: len(main.history)] == main.history
    moves = result.split_merge_moves
    assert len(moves) == 3 and all(set(m) == MOVE_FIELDS for m in moves)
    assert [m["move"] for m in moves] == [0, 1, 2]
    assert moves[0]["log_likelihood_before"] == pytest.approx(main_ll, abs=1e-6)
    current = main_ll
    for m in moves:
        assert m["victim"] != m["donor"] and {m["victim"], m["donor"]} <= {0, 1, 2}
        assert m["log_likelihood_before"] == pytest.approx(current, abs=1e-9)
        assert m["accepted"] == (m["log_likelihood_after"] > m["log_likelihood_before"] + MIN_GAIN)
        if m["accepted"]:
            current = m["log_likelihood_after"]
    assert final_ll == pytest.approx(current, abs=1e-6)


def test_accepted_moves_report_the_final_model(data):
    # a barely trained main fit: re-training from a copy for 40 iterations is sure to raise the likelihood
    result = discover_options(data, 3, seed=1, num_iterations=2, restarts=1, progress=False, return_info=True,
                              split_merge=2, split_merge_iterations=40)  # fmt: skip
    accepted = [m for m in result.split_merge_moves if m["accepted"]]
    assert accepted, result.split_merge_moves
    with torch.no_grad():
        diagnostics = option_diagnostics(DDOLoss(result.options, None).log_probabilities(data))
    assert result.option_usage == pytest.approx(diagnostics.usage)
    assert result.duplicate_options == diagnostics.duplicates
    assert held_out_log_likelihood(result.options, None, data) == pytest.approx(accepted[-1]["log_likelihood_after"])
    # history: the main fit's 2 iterations, then each accepted re-fit's
    assert 2 < len(result.history) <= 2 + 40 * len(accepted)
    # without return_info, the final options module
    options = discover_options(data, 3, seed=1, num_iterations=2, restarts=1, progress=False, split_merge=2,
                               split_merge_iterations=40)  # fmt: skip
    assert _same(_params(options), _params(result.options))


def test_split_merge_is_deterministic_given_the_seed(data):
    kwargs = dict(seed=3, split_merge=2, split_merge_iterations=10, **FAST)
    a, b = discover_options(data, 3, **kwargs), discover_options(data, 3, **kwargs)
    assert a.split_merge_moves == b.split_merge_moves
    assert _same(_params(a.options), _params(b.options))


def test_split_merge_follows_the_final_fit_of_auto_width(data):
    result = discover_options(data, 2, num_cells="auto", num_iterations=8, restarts=1, progress=False,
                              return_info=True, seed=0, split_merge=1, split_merge_iterations=5)  # fmt: skip
    assert result.num_cells is not None and len(result.split_merge_moves) == 1


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(split_merge=-1), ValueError, "split_merge must be an int >= 0.*got -1"),
        (dict(split_merge=1.5), TypeError, "split_merge must be an int, got 1.5"),
        (dict(split_merge=True), TypeError, "split_merge must be an int, got True"),
        (dict(split_merge=1, split_merge_iterations=0), ValueError, "split_merge_iterations must be an int >= 1, got 0"),
        (dict(split_merge=1, split_merge_iterations=2.0), TypeError, "split_merge_iterations must be an int"),
        (dict(split_merge=1, architecture="shared"), ValueError, "architecture='separate'.*got architecture='shared'"),
        (dict(split_merge=1, meta_control="learned"), ValueError, "meta_control='uniform'.*got meta_control='learned'"),
        (dict(split_merge=1, options=OptionsMLP(2, 2, 3, architecture="shared")), ValueError, "leading dimension"),
        (dict(split_merge=1, num_options=1), ValueError, "num_options >= 2, got 1"),
    ],
)
def test_bad_split_merge_settings_are_refused(data, kwargs, error, match):
    kwargs = dict(kwargs)
    num_options = kwargs.pop("num_options", 3)
    with pytest.raises(error, match=match):
        discover_options(data, num_options, num_iterations=1, restarts=1, progress=False, **kwargs)


def test_split_merge_refuses_an_optimizer_instance_and_a_replay_buffer(data):
    options = OptionsMLP(2, 2, 3)
    opt = torch.optim.Adam(options.parameters())
    with pytest.raises(ValueError, match="optimizer factory.*got Adam"):
        discover_options(data, 3, options=options, optimizer=opt, num_iterations=1, progress=False, split_merge=1)
    buffer = ReplayBuffer(storage=LazyTensorStorage(10), batch_size=2)
    buffer.extend(data)
    with pytest.raises(ValueError, match="not a replay buffer"):
        discover_options(buffer, 3, num_iterations=1, progress=False, split_merge=1)
