"""OneHotByteOptions: the paper's one-hot byte encoding as options (torchrl_options/modules/byte_options.py)."""
import os

import pytest
import torch
from tensordict import TensorDict

from torchrl_options import DDOLoss, discover_options, load_options, OptionsMLP, save_options
from torchrl_options.modules import OneHotByteOptions
from torchrl_options.modules.byte_options import bytes_from_observation


def _reference(options: OneHotByteOptions, ram: torch.Tensor):
    """The same networks written with the explicit one-hot vector and dense layers."""
    K, width = options.num_options, options.first_bias.shape[-1]
    one_hot = torch.nn.functional.one_hot(ram.long(), 256).flatten(-2).float()
    outs = []
    for part, layers in ((0, options.control), (1, options.termination)):
        ys = []
        for h in range(K):
            col = (part * K + h) * width
            y = torch.tanh(one_hot @ options.embedding.weight[:, col : col + width] + options.first_bias[part * K + h])
            for i, layer in enumerate(layers):
                y = y @ layer.weight[h].T + layer.bias[h]
                y = torch.tanh(y) if i < len(layers) - 1 else y
            ys.append(y)
        outs.append(torch.stack(ys, -2))
    return outs[0], outs[1].squeeze(-1)


def test_equals_dense_layers_on_the_one_hot_vector():
    torch.manual_seed(0)
    options = OneHotByteOptions(6, num_actions=4, num_options=3, num_cells=[5, 7])
    ram = torch.randint(0, 256, (2, 9, 6), dtype=torch.uint8)
    td = options(TensorDict(observation=ram, batch_size=[2, 9]))
    logits, term = _reference(options, ram.reshape(-1, 6))
    assert td["option_logits"].shape == (2, 9, 3, 4) and td["termination_logits"].shape == (2, 9, 3)
    torch.testing.assert_close(td["option_logits"].reshape(-1, 3, 4), logits)
    torch.testing.assert_close(td["termination_logits"].reshape(-1, 3), term)
    # the options differ (separate networks), and every byte position matters
    assert not torch.allclose(logits[:, 0], logits[:, 1])
    changed = ram.clone()
    changed[..., 5] ^= 1
    assert not torch.allclose(options(TensorDict(observation=changed, batch_size=[2, 9]))["option_logits"], td["option_logits"])


@pytest.mark.parametrize(
    "obs, scale",
    [
        (torch.tensor([[1, 256]]), 1.0),  # above 255
        (torch.tensor([[-1, 3]]), 1.0),  # negative
        (torch.tensor([[0.5, 3.0]]), 1.0),  # not a whole number
        (torch.tensor([[float("nan"), 3.0]]), 1.0),
        (torch.tensor([[0.5, 0.2]]), 1 / 255),  # not bytes / 255
        (torch.tensor([[1.01, 0.2]]), 1 / 255),  # above 255 / 255
    ],
)
def test_refuses_what_is_not_a_byte(obs, scale):
    options = OneHotByteOptions(2, 3, 2, num_cells=[4], value_scale=scale)
    with pytest.raises(ValueError, match="'observation' must hold bytes"):
        options(TensorDict(observation=obs, batch_size=[1]))


def test_refuses_bad_settings_and_sizes():
    with pytest.raises(ValueError, match="num_bytes"):
        OneHotByteOptions(0, 3, 2)
    with pytest.raises(ValueError, match="value_scale"):
        OneHotByteOptions(4, 3, 2, value_scale=0.0)
    with pytest.raises(ValueError, match="num_cells"):
        OneHotByteOptions(4, 3, 2, num_cells=[])
    with pytest.raises(ValueError, match="built for 4 bytes, got an observation of 3"):
        OneHotByteOptions(4, 3, 2)(TensorDict(observation=torch.zeros(1, 3, dtype=torch.uint8), batch_size=[1]))
    with pytest.raises(KeyError, match="ram"):
        OneHotByteOptions(4, 3, 2, in_keys="ram")(TensorDict(observation=torch.zeros(1, 4), batch_size=[1]))


def test_bytes_over_255_scaled_read_back_exactly():
    b = torch.arange(256)
    assert torch.equal(bytes_from_observation(b.float() / 255, value_scale=1 / 255), b)
    assert torch.equal(bytes_from_observation(b.to(torch.uint8)), b)


def test_save_load_round_trip(tmp_path):
    options = OneHotByteOptions(5, 3, 2, num_cells=[4, 4], value_scale=1 / 255, in_keys=[("agent", "ram")])
    path = os.path.join(tmp_path, "options.pt")
    save_options(options, path)
    loaded = load_options(path)
    assert isinstance(loaded, OneHotByteOptions) and loaded.value_scale == options.value_scale
    td = TensorDict({("agent", "ram"): torch.randint(0, 256, (3, 5)).float() / 255}, [3])
    torch.testing.assert_close(loaded(td.clone())["option_logits"], options(td.clone())["option_logits"])


def _flag_demos(seed: int = 0, num_bytes: int = 8, B: int = 4, T: int = 60):
    """Random byte states (byte 0 in 120-135, the others in 0-3, as most of an Atari RAM varies little); the action is byte 0's lowest bit (a flag): one embedding row per
    value for one-hot options, an oscillation between neighbouring values for a network reading bytes / 255."""
    g = torch.Generator().manual_seed(seed)
    ram = torch.randint(0, 4, (B, T + 1, num_bytes), generator=g)
    ram[..., 0] = torch.randint(120, 136, (B, T + 1), generator=g)
    obs = ram.float() / 255
    return TensorDict(
        {"observation": obs[:, :-1], "action": ram[:, :-1, 0] % 2, "next": {"observation": obs[:, 1:]}}, [B, T]
    )


def test_discovery_fits_a_byte_flag_that_bytes_over_255_cannot():
    data = _flag_demos()
    kwargs = dict(num_options=1, num_actions=2, num_iterations=60, m_steps=5, lr=0.03, tol=None, restarts=1, seed=0,
                  progress=False, return_info=True)  # fmt: skip
    torch.manual_seed(0)
    one_hot = discover_options(data, options=OneHotByteOptions(8, 2, 1, num_cells=[16], value_scale=1 / 255), **kwargs)
    mlp = discover_options(data, num_cells=[16], **kwargs)
    assert isinstance(mlp.options, OptionsMLP)
    # one-hot: the flag is one embedding row per value; bytes / 255: a parity is far from any smooth function
    assert one_hot.final_log_likelihood_per_step > -0.05
    assert mlp.final_log_likelihood_per_step < -0.5
    # and on demonstrations it has not seen
    held_out = _flag_demos(seed=1)
    for result, bound in ((one_hot, lambda ll: ll > -0.05), (mlp, lambda ll: ll < -0.5)):
        ll = -float(DDOLoss(result.options)(held_out.clone())["loss_ddo"])
        assert bound(ll), ll

