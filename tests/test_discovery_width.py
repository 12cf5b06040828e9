"""discovery.width: the held-out split, the held-out likelihood, and discover_options(num_cells="auto")."""
import pytest
import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_options import DDOLoss, discover_options, OptionsMLP
from torchrl_options.discovery import DiscoveryResult
from torchrl_options.discovery.width import (
    AUTO_WIDTHS,
    held_out_log_likelihood,
    select_width,
    split_trajectories,
)
from torchrl_options.testing import planted_corridor_demonstrations
from torchrl_options.testing.planted_suite import posterior_accuracy


def test_split_is_a_partition_of_the_trajectories():
    data = planted_corridor_demonstrations(11, 6, seed=0)
    data["row"] = torch.arange(11)[:, None].expand(11, 6)
    train, held = split_trajectories(data, 0.2, torch.Generator().manual_seed(3))
    assert held.batch_size[0] == 2 and train.batch_size[0] == 9
    rows = torch.cat([train["row"][:, 0], held["row"][:, 0]]).sort().values
    assert torch.equal(rows, torch.arange(11))
    again, _ = split_trajectories(data, 0.2, torch.Generator().manual_seed(3))
    assert torch.equal(again["row"], train["row"])
    # at least one row on each side, however small the fraction
    train, held = split_trajectories(data[:2], 0.01, torch.Generator().manual_seed(0))
    assert (train.batch_size[0], held.batch_size[0]) == (1, 1)


@pytest.mark.parametrize("fraction", [0.0, 1.0, -0.5])
def test_split_refuses_bad_fractions(fraction):
    with pytest.raises(ValueError, match="fraction must be in \\(0, 1\\)"):
        split_trajectories(planted_corridor_demonstrations(4, 5), fraction, torch.Generator())


def test_held_out_likelihood_is_the_loss_forward_per_step():
    data = planted_corridor_demonstrations(6, 20, seed=1)
    options = OptionsMLP(2, 2, 2)
    expected = DDOLoss(options)(data)["log_likelihood_per_step"].item()
    assert held_out_log_likelihood(options, None, data) == pytest.approx(expected)


def test_select_width_keeps_the_best_held_out_fit_and_prefers_narrow_ties():
    data = planted_corridor_demonstrations(20, 40, seed=0)
    trained = discover_options(data, 2, num_cells=4, num_iterations=60, restarts=1, lr=0.05, seed=0, progress=False)

    def fit(part, width):  # width 8: untrained, so its held-out likelihood must be lower
        options = trained if width == 4 else OptionsMLP(2, 2, 2, num_cells=8)
        return DiscoveryResult(options=options, meta_control=None)

    width, result, scores = select_width(fit, data, generator=torch.Generator().manual_seed(0))
    assert sorted(scores) == [4, 8] and scores[4] > scores[8]
    assert width == 4 and result.options is trained
    same = OptionsMLP(2, 2, 2)
    width, _, scores = select_width(
        lambda part, w: DiscoveryResult(options=same, meta_control=None), data, widths=(8, 4),
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert scores[4] == scores[8] and width == 4
    with pytest.raises(ValueError, match="widths"):
        select_width(fit, data, widths=(), generator=torch.Generator())


def test_auto_width_discovers_the_planted_options():
    """num_cells='auto' scores every width, keeps the best, and the kept fit labels the corridor like the truth."""
    data = planted_corridor_demonstrations(24, 60, seed=2)
    result = discover_options(
        data, 2, num_cells="auto", num_iterations=100, restarts=2, restart_iterations=20, seed=0, progress=False,
        return_info=True,
    )  # fmt: skip
    assert sorted(result.width_log_likelihoods) == sorted(AUTO_WIDTHS)
    assert result.num_cells == max(result.width_log_likelihoods, key=result.width_log_likelihoods.get)
    assert all(torch.isfinite(torch.tensor(v)) for v in result.width_log_likelihoods.values())
    with torch.no_grad():
        accuracy, _ = posterior_accuracy(DDOLoss(result.options).log_probabilities(data), data["true_option"])
    assert accuracy >= 0.9, accuracy
    again = discover_options(
        data, 2, num_cells="auto", num_iterations=100, restarts=2, restart_iterations=20, seed=0, progress=False,
        return_info=True,
    )  # fmt: skip
    assert again.width_log_likelihoods == result.width_log_likelihoods
    assert again.final_log_likelihood_per_step == result.final_log_likelihood_per_step


def test_auto_width_refuses_what_it_cannot_split():
    data = planted_corridor_demonstrations(8, 10, seed=0)
    with pytest.raises(ValueError, match="num_cells must be an int, a sequence of ints or 'auto', got 'wide'"):
        discover_options(data, 2, num_cells="wide", progress=False)
    with pytest.raises(ValueError, match="num_cells='auto'.*at least 5 trajectories.*got 4"):
        discover_options(data[:4], 2, num_cells="auto", progress=False)
    with pytest.raises(ValueError, match="num_cells='auto'.*options=None"):
        discover_options(data, 2, num_cells="auto", options=OptionsMLP(2, 2, 2), progress=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(100), batch_size=8)
    with pytest.raises(ValueError, match="num_cells='auto'.*replay buffer"):
        flat = data.reshape(-1)
        flat["collector", "traj_ids"] = torch.arange(8)[:, None].expand(8, 10).reshape(-1)
        buffer.extend(flat)
        discover_options(buffer, 2, num_cells="auto", progress=False)
