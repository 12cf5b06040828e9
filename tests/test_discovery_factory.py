"""discovery/discover.py with a user's networks: ``options_factory`` and ``meta_control_factory`` (issue 51 part 2).

A factory of the default modules gives the defaults' results bit for bit (every start strategy, restarts, width
choice); a small conv net on the planted grid rendered as pixels reaches the Bayes ceiling through the factory, as
the default MLP does on the coordinates; and what a factory cannot do is refused at the door.
"""
import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_options import DDOLoss, discover_options, GaussianOptionsMLP, MetaControlMLP, OptionsMLP
from torchrl_options.discovery import clone_from_labels, pretrain_on_clusters, pretrain_on_segments
from torchrl_options.testing import PLANTED_SUITE, planted_corridor_demonstrations, posterior_accuracy


def _problem(name):
    return next(p for p in PLANTED_SUITE if p.name == name)


def _same(a, b):
    """Two DiscoveryResults are the same run: every iteration's log-likelihood, every start's, every parameter."""
    assert [h["log_likelihood_per_step"] for h in a.history] == [h["log_likelihood_per_step"] for h in b.history]
    assert a.restart_log_likelihoods == b.restart_log_likelihoods
    assert a.num_cells == b.num_cells and a.width_log_likelihoods == b.width_log_likelihoods
    for x, y in ((a.options, b.options), (a.meta_control, b.meta_control)):
        if x is None:
            assert y is None
            continue
        sx, sy = x.state_dict(), y.state_dict()
        assert sx.keys() == sy.keys() and all(torch.equal(sx[k], sy[k]) for k in sx)


@pytest.fixture(scope="module")
def corridor():
    data, _ = _problem("corridor-2").make(0, num_trajectories=10)
    return data


_SHORT = dict(num_iterations=100, restart_iterations=15, seed=0, progress=False, return_info=True)


@pytest.mark.parametrize("init", ["auto", "random", "kmeans"])
def test_a_factory_of_the_default_modules_gives_the_defaults_bit_for_bit(corridor, init):
    def make():
        return OptionsMLP(2, 2, 2, num_cells=8, in_keys=["observation"])

    default = discover_options(corridor, 2, init=init, **_SHORT)
    made = discover_options(corridor, 2, init=init, options_factory=make, **_SHORT)
    assert len(default.restart_log_likelihoods) > 1  # the default starts, which an options instance turns off
    _same(default, made)


def test_meta_control_factory_gives_the_learned_default_bit_for_bit(corridor):
    def make_meta():
        return MetaControlMLP(2, 2, num_cells=8, in_keys=["observation"])

    kwargs = dict(_SHORT, meta_control="learned", init="segments", restarts=2)  # segment starts clone the meta-control
    default = discover_options(corridor, 2, **kwargs)
    made = discover_options(corridor, 2, meta_control_factory=make_meta, **kwargs)
    assert default.meta_control is not None
    _same(default, made)


def test_width_choice_calls_the_factory_with_num_cells(corridor):
    widths = []

    def make(num_cells):
        widths.append(num_cells)
        return OptionsMLP(2, 2, 2, num_cells=num_cells, in_keys=["observation"])

    settings = dict(num_cells="auto", init="random", num_iterations=40, restart_iterations=5, seed=0,
                    progress=False, return_info=True)  # fmt: skip
    default = discover_options(corridor, 2, **settings)
    made = discover_options(corridor, 2, options_factory=make, **settings)
    assert sorted(set(widths)) == [4, 8] and len(widths) == 8  # 4 random starts per width
    _same(default, made)


def test_split_merge_with_a_factory(corridor):
    def make():
        return OptionsMLP(2, 2, 2, num_cells=8)

    kwargs = dict(_SHORT, init="random", split_merge=1, split_merge_iterations=10)
    _same(discover_options(corridor, 2, **kwargs), discover_options(corridor, 2, options_factory=make, **kwargs))


# ------------------------------------------------------------------------------------------------ an image problem
def _render(data, height, width):
    """The planted grid as a one-plane picture: the agent's cell lit, ``[.., 1, H, W]``."""
    for key in ("state", ("next", "state")):
        pixels = nn.functional.one_hot(data[key], height * width).float()
        data[key[:-1] + ("pixels",) if isinstance(key, tuple) else "pixels"] = pixels.reshape(
            *data[key].shape, 1, height, width
        )
    return data


class ConvOptions(nn.Module):
    """K options from a picture: a 3x3 convolution, a tanh layer, and one linear head per output; any leading dims."""

    def __init__(self, height, width, num_actions, num_options, channels=4, num_cells=8):
        super().__init__()
        self.shape = (num_options, num_actions + 1)
        self.trunk = nn.Sequential(
            nn.Conv2d(1, channels, 3, padding=1), nn.Tanh(), nn.Flatten(),
            nn.Linear(channels * height * width, num_cells), nn.Tanh(),
        )  # fmt: skip
        self.head = nn.Linear(num_cells, num_options * (num_actions + 1))

    def forward(self, pixels):
        lead = pixels.shape[:-3]
        out = self.head(self.trunk(pixels.reshape(-1, *pixels.shape[-3:]))).reshape(*lead, *self.shape)
        return out[..., :-1], out[..., -1]


@pytest.mark.parametrize(
    "name, size, rows",
    [("landmarks-3", 7, 96), pytest.param("walls-4", 5, 64, marks=pytest.mark.slow)],
)
def test_a_conv_net_on_pixels_reaches_the_bayes_ceiling_through_the_factory(name, size, rows):
    """The planted grid rendered as pictures (one plane, the agent's cell lit): a small conv net made by the factory
    labels the steps within 3 points of the truth's own posterior, as the default MLP does on the coordinates
    (tests/test_planted_suite.py), with the default starts (segments clustered on the pictures) and restarts."""
    torch.set_num_threads(1)
    problem = _problem(name)
    data, truth = problem.make(0, num_trajectories=rows)
    data = _render(data, size, size)
    ceiling, truth_ll = problem.ceiling(data, truth)

    def make():
        net = ConvOptions(size, size, 4, problem.num_options)
        return TensorDictModule(net, in_keys=["pixels"], out_keys=["option_logits", "termination_logits"])

    result = discover_options(data, problem.num_options, options_factory=make, obs_keys="pixels", seed=0,
                              progress=False, return_info=True)  # fmt: skip
    assert len(result.restart_log_likelihoods) > 1
    with torch.no_grad():
        acc, ll = posterior_accuracy(DDOLoss(result.options).log_probabilities(data), data["true_option"])
    assert acc >= ceiling - 0.03, (acc, ceiling)
    assert ll >= truth_ll - 5e-3, (ll, truth_ll)


# ------------------------------------------------------------------------------------------------- at the door
def test_factories_are_refused_at_the_door(corridor):
    def make():
        return OptionsMLP(2, 2, 2)

    quiet = dict(num_iterations=2, progress=False)
    with pytest.raises(ValueError, match="options .* or options_factory .*, not both"):
        discover_options(corridor, 2, options=make(), options_factory=make, **quiet)
    with pytest.raises(TypeError, match="options_factory must be a callable .* got a module instance .*options="):
        discover_options(corridor, 2, options_factory=make(), **quiet)
    with pytest.raises(TypeError, match="options_factory must be a callable"):
        discover_options(corridor, 2, options_factory=3, **quiet)
    with pytest.raises(TypeError, match="options_factory must return a TensorDictModuleBase, got Linear"):
        discover_options(corridor, 2, options_factory=lambda: nn.Linear(2, 2), **quiet)
    with pytest.raises(ValueError, match="options_factory's module has K=3 options"):
        discover_options(corridor, 2, options_factory=lambda: OptionsMLP(2, 2, 3), **quiet)
    with pytest.raises(ValueError, match="options_factory's module cannot read the trajectories"):
        discover_options(corridor, 2, options_factory=lambda: OptionsMLP(5, 2, 2), **quiet)
    with pytest.raises(ValueError, match="meta_control_factory .* needs meta_control='learned', got meta_control='uniform'"):
        discover_options(corridor, 2, meta_control_factory=lambda: MetaControlMLP(2, 2), **quiet)
    with pytest.raises(ValueError, match="meta_control_factory's module writes 3 meta_logits"):
        discover_options(corridor, 2, meta_control="learned", meta_control_factory=lambda: MetaControlMLP(2, 3), **quiet)
    with pytest.raises(ValueError, match="num_cells='auto' .* options_factory must take a num_cells keyword"):
        discover_options(corridor, 2, num_cells="auto", options_factory=make, **quiet)
    with pytest.raises(ValueError, match="leading dimension"):  # split_merge: checked on the first module made
        discover_options(corridor, 2, split_merge=1, options_factory=lambda: OptionsMLP(2, 2, 2, architecture="shared"),
                         **quiet)  # fmt: skip


def test_init_scale_is_refused_with_given_options():
    """Issue 53: init_scale sets the default Gaussian options' start; silently ignored with the user's own before."""
    data, _ = _problem("gaussian-3").make(0, num_trajectories=4)
    for given in (dict(options=GaussianOptionsMLP(2, 2, 3)), dict(options_factory=lambda: GaussianOptionsMLP(2, 2, 3))):
        with pytest.raises(ValueError, match="init_scale sets the starting standard deviation of the default"):
            discover_options(data, 3, action_space="continuous", init_scale=0.3, num_iterations=1, progress=False,
                             **given)  # fmt: skip


def test_data_without_next_observations_and_flat_continuous_actions_are_refused():
    """Issue 53: no ("next", "observation") failed with an AttributeError deep inside, [B, T] continuous actions
    with an IndexError."""
    data = planted_corridor_demonstrations(4, 10, seed=0)
    with pytest.raises(ValueError, match=r"no \('next', 'observation'\) entry"):
        discover_options(data.exclude("next"), 2, num_iterations=1, progress=False)
    gaussian, _ = _problem("gaussian-3").make(0, num_trajectories=4)
    gaussian["action"] = gaussian["action"][..., 0]
    with pytest.raises(ValueError, match=r"needs 'action' of shape \[B, T, D\].*unsqueeze\(-1\)"):
        discover_options(gaussian, 3, action_space="continuous", num_iterations=1, progress=False)


def test_pretraining_refuses_options_for_other_features_or_another_k():
    """Issue 53: options built for other features failed with a matrix-shape error, another K went unnoticed."""
    data = planted_corridor_demonstrations(4, 10, seed=0)
    mask = data["collector", "mask"]
    starts = torch.zeros_like(mask)
    starts[:, 0] = True
    labels = torch.zeros(mask.shape, dtype=torch.long)
    for pretrain in (pretrain_on_segments, pretrain_on_clusters):
        with pytest.raises(ValueError, match="options module cannot read the trajectories"):
            pretrain(OptionsMLP(5, 2, 2), data, mask, num_options=2, num_steps=1)
        with pytest.raises(ValueError, match="num_options=2 but the options module has K=3"):
            pretrain(OptionsMLP(2, 2, 3), data, mask, num_options=2, num_steps=1)
    with pytest.raises(ValueError, match="options module cannot read the trajectories"):
        clone_from_labels(OptionsMLP(5, 2, 2), data, mask, labels, starts, num_steps=1)
    with pytest.raises(ValueError, match=r"labels must lie in \[0, 2\)"):
        clone_from_labels(OptionsMLP(2, 2, 2), data, mask, labels + 2, starts, num_steps=1)
    with pytest.raises(ValueError, match=r"no \('next', 'observation'\) entry"):
        pretrain_on_segments(OptionsMLP(2, 2, 2), data.exclude("next"), mask, num_options=2, num_steps=1)


def test_pretraining_needs_only_the_options_output_keys():
    """pretrain_on_segments / clone_from_labels train any module writing option_logits and termination_logits
    (here a plain TensorDictModule with no num_options attribute)."""
    data = planted_corridor_demonstrations(8, 20, seed=0)
    mask = data["collector", "mask"]
    torch.manual_seed(0)
    net = TensorDictModule(
        nn.Sequential(nn.Linear(2, 2 * 3), nn.Unflatten(-1, (2, 3))), in_keys=["observation"], out_keys=["raw"]
    )

    class Split(nn.Module):
        def forward(self, raw):
            return raw[..., :2], raw[..., 2]

    from tensordict.nn import TensorDictSequential

    module = TensorDictSequential(net, TensorDictModule(Split(), in_keys=["raw"],
                                                        out_keys=["option_logits", "termination_logits"]))  # fmt: skip
    before = {k: v.clone() for k, v in module.state_dict().items()}
    pretrain_on_segments(module, data, mask, num_options=2, num_steps=5, generator=torch.Generator().manual_seed(0))
    assert any(not torch.equal(before[k], v) for k, v in module.state_dict().items())
