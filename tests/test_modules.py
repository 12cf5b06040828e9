"""Options and meta-control modules: shapes, batching, configuration, and hand-written modules."""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_options import DDOLoss, GaussianOptionsMLP, MetaControlMLP, OptionsMLP, UniformMetaControl


@pytest.mark.parametrize("architecture", ["separate", "shared"])
@pytest.mark.parametrize("batch", [(), (5,), (3, 7)])
def test_options_mlp_shapes(architecture, batch):
    options = OptionsMLP(4, 6, 3, num_cells=[8, 8], architecture=architecture)
    td = options(TensorDict({"observation": torch.randn(*batch, 4)}, list(batch)))
    assert td["option_logits"].shape == (*batch, 3, 6)
    assert td["termination_logits"].shape == (*batch, 3)


def test_separate_options_are_independent_networks():
    torch.manual_seed(0)
    options = OptionsMLP(4, 5, 3, num_cells=16)
    td = options(TensorDict({"observation": torch.randn(10, 4)}, [10]))
    logits = td["option_logits"]
    # different parameters per option: the options disagree
    assert not torch.allclose(logits[:, 0], logits[:, 1])
    # each option's output depends only on its own parameters: perturbing option 0's do not change option 1
    loss = logits[:, 0].sum()
    grads = torch.autograd.grad(loss, list(options.control.parameters()))
    stacked = [g for g in grads if g.shape[:1] == (3,)]
    assert stacked, "expected stacked per-option parameters"
    for g in stacked:
        assert g[1:].abs().sum() == 0 and g[0].abs().sum() > 0


def test_multiple_in_keys_are_concatenated():
    options = OptionsMLP(5, 2, 2, in_keys=["a", ("b", "c")])
    td = TensorDict({"a": torch.randn(3, 2), "b": {"c": torch.randint(3, (3, 3))}}, [3])
    assert options(td)["option_logits"].shape == (3, 2, 2)
    assert ("next", "b", "c") in DDOLoss(options).in_keys


def test_missing_in_key_is_named():
    options = OptionsMLP(4, 2, 2, in_keys=["pixels"])
    with pytest.raises(KeyError, match="pixels"):
        options(TensorDict({"observation": torch.randn(3, 4)}, [3]))


def test_gaussian_options_shapes_and_scale_floor():
    options = GaussianOptionsMLP(3, 2, 4, init_scale=0.5, min_scale=0.01)
    td = options(TensorDict({"observation": torch.randn(6, 3)}, [6]))
    assert td["option_loc"].shape == (6, 4, 2)
    torch.testing.assert_close(td["option_scale"], torch.full((6, 4, 2), 0.5))
    with torch.no_grad():
        options.raw_scale.fill_(-100.0)
    assert (options(td)["option_scale"] >= 0.01).all()
    state = GaussianOptionsMLP(3, 2, 4, state_dependent_scale=True)
    assert state(td)["option_scale"].shape == (6, 4, 2)


def test_meta_control_modules():
    td = TensorDict({"observation": torch.randn(2, 5, 4)}, [2, 5])
    assert MetaControlMLP(4, 3)(td.clone())["meta_logits"].shape == (2, 5, 3)
    uniform = UniformMetaControl(3)(td.clone())["meta_logits"]
    assert uniform.shape == (2, 5, 3) and (uniform == 0).all()
    assert not list(UniformMetaControl(3).parameters())


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(in_features=0, num_actions=2, num_options=2), "positive"),
        (dict(in_features=2, num_actions=2, num_options=0), "positive"),
        (dict(in_features=2, num_actions=2, num_options=2, architecture="wide"), "architecture"),
        (dict(in_features=2, num_actions=2, num_options=2, activation="sine"), "activation"),
        (dict(in_features=2, num_actions=2, num_options=2, num_cells=0), "num_cells"),
        (dict(in_features=2, num_actions=2, num_options=2, num_cells=[4, -1]), "num_cells"),
        (dict(in_features=2, num_actions=2, num_options=2, num_cells=[]), "num_cells"),
        (dict(in_features=2, num_actions=2, num_options=2, termination_cells=[0]), "termination_cells"),
        (dict(in_features=2, num_actions=2, num_options=2, termination_cells=4, architecture="shared"),
         "termination_cells needs architecture='separate'"),
    ],
)
def test_options_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        OptionsMLP(**kwargs)


@pytest.mark.parametrize("cells", ["8", 2.5, True, None])
def test_hidden_sizes_of_the_wrong_type_are_named(cells):
    for build in (lambda c: OptionsMLP(2, 2, 2, num_cells=c), lambda c: GaussianOptionsMLP(2, 2, 2, num_cells=c),
                  lambda c: MetaControlMLP(2, 2, num_cells=c)):  # fmt: skip
        with pytest.raises(TypeError, match="num_cells must be an int or a sequence of ints"):
            build(cells)
    with pytest.raises(TypeError, match="termination_cells"):
        GaussianOptionsMLP(2, 2, 2, termination_cells="8" if cells is None else cells)


@pytest.mark.parametrize("cls", [OptionsMLP, GaussianOptionsMLP])
def test_termination_cells_shape_only_the_termination_networks(cls):
    """termination_cells gives the termination networks their own hidden sizes; by default they follow num_cells."""
    torch.manual_seed(0)
    plain = cls(3, 2, 4, num_cells=5)
    torch.manual_seed(0)
    same = cls(3, 2, 4, num_cells=5, termination_cells=None)
    for a, b in zip(plain.parameters(), same.parameters()):
        torch.testing.assert_close(a, b)
    deep = cls(3, 2, 4, num_cells=5, termination_cells=[6, 7])
    assert deep.config["termination_cells"] == [6, 7] and plain.config["termination_cells"] == [5]
    sizes = [p.shape for p in deep.termination.parameters()]
    assert sizes == [torch.Size([4, 6, 3]), torch.Size([4, 6]), torch.Size([4, 7, 6]), torch.Size([4, 7]),
                     torch.Size([4, 1, 7]), torch.Size([4, 1])], sizes  # fmt: skip
    assert [p.shape for p in deep.control.parameters()] == [p.shape for p in plain.control.parameters()]
    td = deep(TensorDict({"observation": torch.randn(9, 3)}, [9]))
    assert td["termination_logits"].shape == (9, 4)
    rebuilt = cls(**{k: v for k, v in deep.config.items() if k not in ("in_keys", "out_keys")})
    rebuilt.load_state_dict(deep.state_dict())  # the configuration rebuilds the module
    # a file saved before termination_cells existed (no such key in its configuration) loads with num_cells
    from torchrl_options.discovery.serialization import module_from_dict, module_to_dict

    entry = module_to_dict(plain)
    del entry["config"]["termination_cells"]
    old = module_from_dict(entry)
    assert old.config["termination_cells"] == [5]
    for a, b in zip(old.parameters(), plain.parameters()):
        torch.testing.assert_close(a, b)


def test_hand_written_options_are_first_class():
    """A plain TensorDictModule writing the two entries trains with DDOLoss like the built-in ones."""

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(2, 2 * 3 + 2)

        def forward(self, obs):
            out = self.lin(obs)
            return out[..., :6].unflatten(-1, (2, 3)), out[..., 6:]

    options = TensorDictModule(Net(), in_keys=["observation"], out_keys=["option_logits", "termination_logits"])
    data = TensorDict(
        {"observation": torch.randn(2, 9, 2), "action": torch.randint(3, (2, 9)), "next": {"observation": torch.randn(2, 9, 2)}},
        [2, 9],
    )
    out = DDOLoss(options)(data)
    out["loss_ddo"].backward()
    assert options.module.lin.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("cells", [[2], [8, 3], [4, 4, 4]])
@pytest.mark.parametrize("batch", [(), (5,), (3, 7)])
def test_ensemble_products_equal_torchrl_vmapped_ensemble(cells, batch):
    """The stacked-parameter products give TorchRL's vmapped MultiAgentMLP outputs and gradients."""
    from torchrl_options.modules.options import _ensemble, _ensemble_forward

    torch.manual_seed(0)
    net = _ensemble(4, 6, 3, cells, "tanh")
    x = torch.randn(*batch, 4)
    fast = _ensemble_forward(net, x)
    ref = net(x.unsqueeze(-2).expand(*batch, 3, 4))
    assert fast.shape == ref.shape == (*batch, 3, 6)
    torch.testing.assert_close(fast, ref)
    g_fast = torch.autograd.grad(fast.square().sum(), list(net.parameters()))
    g_ref = torch.autograd.grad(ref.square().sum(), list(net.parameters()))
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b)
