"""GridConvOptions: options as small conv nets over a one-hot grid view (torchrl_options.modules.grid_options)."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_options import discover_options
from torchrl_options.modules import GridConvOptions

OBS = 20 * 49 + 4


def _td(x):
    return TensorDict(observation=x, batch_size=x.shape[:-1])


@pytest.mark.parametrize("architecture", ["shared", "separate"])
def test_shapes_batches_and_locality(architecture):
    torch.manual_seed(0)
    options = GridConvOptions(7, 3, architecture=architecture)
    x = torch.rand(2, 5, OBS)
    out = options(_td(x))
    assert out["option_logits"].shape == (2, 5, 3, 7) and out["termination_logits"].shape == (2, 5, 3)
    # the same as one flat batch
    flat = options(_td(x.reshape(10, OBS)))
    torch.testing.assert_close(flat["option_logits"].reshape(2, 5, 3, 7), out["option_logits"])
    # two valid 3x3 convolutions on 7x7 leave a 3x3 map: every cell reaches the output, and the direction too
    y = x.clone()
    y[..., 0] += 1.0  # channel 0 of cell (0, 0)
    assert not torch.allclose(options(_td(y))["option_logits"], out["option_logits"])
    z = x.clone()
    z[..., -1] += 1.0  # the last direction feature
    assert not torch.allclose(options(_td(z))["termination_logits"], out["termination_logits"])


def test_separate_networks_do_not_share_filters():
    torch.manual_seed(0)
    sep = GridConvOptions(7, 2, architecture="separate")
    x = torch.rand(4, OBS)
    before = sep(_td(x))["option_logits"].detach()
    with torch.no_grad():  # option 0's control filters are the first group of the first convolution
        conv = sep.conv[0]
        per_group = conv.out_channels // sep.groups
        conv.weight[:per_group] = 0.0
        conv.bias[:per_group] = 0.0
    after = sep(_td(x))["option_logits"].detach()
    assert not torch.allclose(after[:, 0], before[:, 0]) and torch.allclose(after[:, 1], before[:, 1])


def test_bad_settings_and_inputs_are_refused():
    with pytest.raises(ValueError, match="architecture"):
        GridConvOptions(7, 2, architecture="tied")
    with pytest.raises(ValueError, match="too many for a 7x7 view"):
        GridConvOptions(7, 2, conv_channels=[4, 4, 4, 4])
    with pytest.raises(ValueError, match="num_options"):
        GridConvOptions(7, 0)
    with pytest.raises(ValueError, match="expects 984 features"):
        GridConvOptions(7, 2)(_td(torch.rand(3, 10)))
    small = GridConvOptions(3, 2, channels=2, view_size=3, extra_features=0, conv_channels=[4])
    assert small(_td(torch.rand(5, 18)))["option_logits"].shape == (5, 2, 3)


def test_discover_options_trains_it():
    # two planted skills over a 3x3 one-channel "view": action 0 where the centre cell is lit, action 1 elsewhere
    g = torch.Generator().manual_seed(0)
    B, T = 6, 20
    lit = torch.rand(B, T + 1, generator=g) < 0.5
    obs = torch.zeros(B, T + 1, 9)
    obs[..., 4] = lit.float()
    data = TensorDict({"observation": obs[:, :-1], "action": (~lit[:, :-1]).long(),
                       ("next", "observation"): obs[:, 1:]}, [B, T])
    torch.manual_seed(0)
    options = GridConvOptions(2, 2, channels=1, view_size=3, extra_features=0, conv_channels=[4], num_cells=[8])
    result = discover_options(data, 2, options=options, num_iterations=60, lr=0.05, progress=False,
                              return_info=True, seed=0)
    lls = [h["log_likelihood_per_step"] for h in result.history]
    assert lls[-1] > lls[0] + 0.3 and lls[-1] > -0.3  # it learns the action from the view
    assert result.options is options
