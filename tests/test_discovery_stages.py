"""discovery/settings.py, batch.py, networks.py and stages.py: the settings as a Hydra structured config, the
trajectories checked once at the door, and the stages composed by hand giving what the front door gives."""
import pytest
import torch

import torchrl_options.discovery.batch as batch_module
from torchrl_options import discover_options, OptionsMLP
from torchrl_options.discovery import discover, DiscoverySettings, Networks
from torchrl_options.discovery.batch import discovery_batch
from torchrl_options.discovery.networks import resolve_settings
from torchrl_options.discovery.stages import best_of_starts, fit_starts, run_discovery, seeded
from torchrl_options.testing import planted_corridor_demonstrations


@pytest.fixture(scope="module")
def data():
    return planted_corridor_demonstrations(8, 30, seed=0)


def _equal(a, b):
    assert [h["log_likelihood_per_step"] for h in a.history] == [h["log_likelihood_per_step"] for h in b.history]
    assert a.restart_log_likelihoods == b.restart_log_likelihoods
    sa, sb = a.options.state_dict(), b.options.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_settings_are_a_hydra_structured_config(data):
    pytest.importorskip("hydra")
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    ConfigStore.instance().store(group="ddo", name="schema_test", node=DiscoverySettings)
    node = ConfigStore.instance().load("ddo/schema_test.yaml").node
    assert node.num_iterations == 1000 and node.init == "auto" and node.trajectory_key == ["collector", "traj_ids"]
    yaml = "num_options: 2\nnum_iterations: 30\nrestart_iterations: 5\ninit: random\nseed: 0\nprogress: false\n"
    config = OmegaConf.merge(OmegaConf.structured(DiscoverySettings), OmegaConf.create(yaml))
    settings = OmegaConf.to_object(config)
    assert isinstance(settings, DiscoverySettings) and settings.trajectory_key == ("collector", "traj_ids")
    kwargs = dict(num_iterations=30, restart_iterations=5, init="random", seed=0, progress=False, return_info=True)
    _equal(discover(data, settings), discover_options(data, 2, **kwargs))
    with pytest.raises(Exception, match="num_iterations"):  # OmegaConf refuses a value of another type
        OmegaConf.merge(OmegaConf.structured(DiscoverySettings), OmegaConf.create("num_iterations: many"))


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(init="spectral"), ValueError, "init must be one of 'random', 'kmeans', 'segments', 'auto'"),
        (dict(meta_control="deep"), ValueError, "meta_control must be 'uniform', 'learned' or a module"),
        (dict(num_cells="wide"), ValueError, "num_cells must be an int, a sequence of ints or 'auto'"),
        (dict(m_steps=0), ValueError, "m_steps must be an int >= 1, got 0"),
        (dict(num_options=1.0), TypeError, "num_options must be an int"),
        (dict(action_key=3), TypeError, "action_key must be a NestedKey"),
        (dict(tol=-1.0), ValueError, "tol must be a number >= 0"),
        (dict(batch_size=0), ValueError, "batch_size must be an int >= 1"),
    ],
)
def test_settings_refuse_bad_values_when_made(kwargs, error, match):
    kwargs = dict(dict(num_options=2), **kwargs)
    with pytest.raises(error, match=match):
        DiscoverySettings(**kwargs)


def test_settings_keys_from_yaml_lists():
    settings = DiscoverySettings(2, obs_keys=["pixels", ["agent", "obs"]], action_key=["agent", "action"])
    assert settings.obs_key_list == ["pixels", ("agent", "obs")] and settings.action_key == ("agent", "action")
    assert DiscoverySettings(2).stopping_patience == 20
    assert DiscoverySettings(2, action_space="continuous").stopping_patience == 100


def test_the_door_pads_and_checks_the_trajectories_once(data, monkeypatch):
    """Width choice and split-and-merge re-fit many times; the trajectories are padded and checked once."""
    calls = {"as_trajectory_batch": 0, "check_step_data": 0}
    for name in calls:
        real = getattr(batch_module, name)

        def counted(*args, _real=real, _name=name, **kwargs):
            calls[_name] += 1
            return _real(*args, **kwargs)

        monkeypatch.setattr(batch_module, name, counted)
    trajectories = [data[i][data[i]["collector", "mask"]].exclude("collector") for i in range(8)]
    result = discover_options(trajectories, 2, num_cells="auto", init="random", split_merge=1,
                              split_merge_iterations=5, num_iterations=20, restart_iterations=5, seed=0,
                              progress=False, return_info=True)  # fmt: skip
    assert result.num_cells in (4, 8) and len(result.split_merge_moves) == 1
    assert calls == {"as_trajectory_batch": 1, "check_step_data": 1}


def test_stages_composed_by_hand_are_the_front_door(data):
    """The door, then the stages: fit_starts is one width's fit with its starts; best_of_starts the choice."""
    settings = resolve_settings(DiscoverySettings(2, num_iterations=40, restarts=3, restart_iterations=5, seed=1,
                                                  progress=False, init="kmeans"), Networks())  # fmt: skip
    with seeded(1) as generator:
        batch = discovery_batch(data, settings)
        staged = fit_starts(batch, settings, Networks(), generator)
    front = discover_options(data, 2, num_iterations=40, restarts=3, restart_iterations=5, seed=1, progress=False,
                             init="kmeans", return_info=True)  # fmt: skip
    _equal(staged, front)
    with seeded(1) as generator:
        _equal(run_discovery(discovery_batch(data, settings), settings, Networks(), generator), front)


def test_best_of_starts_keeps_the_best_and_continues_it():
    trained = []

    def train(start, n, label, final):
        trained.append((start, n, label, final))
        return [{"log_likelihood_per_step": float(start == 1)}] * n

    start, history, lls = best_of_starts(lambda r: r, train, restarts=3, restart_iterations=2, num_iterations=5,
                                         tol=None, patience=20, desc="fit")  # fmt: skip
    assert start == 1 and lls == [0.0, 1.0, 0.0] and len(history) == 5
    assert trained[-1] == (1, 3, "fit", True) and trained[0] == (0, 2, "fit start 1/3", False)
    start, history, lls = best_of_starts(lambda r: r, train, restarts=1, restart_iterations=2, num_iterations=5,
                                         tol=None, patience=20, desc="fit")  # fmt: skip
    assert start == 0 and lls == [] and len(history) == 5


def test_networks_refuse_what_they_cannot_do(data):
    with pytest.raises(TypeError, match="options must be None or a TensorDictModuleBase, got Linear"):
        Networks(options=torch.nn.Linear(2, 2))
    with pytest.raises(ValueError, match="lr_scheduler must be a callable"):
        Networks(lr_scheduler="cosine")
    options = OptionsMLP(2, 2, 2)
    with pytest.raises(ValueError, match="restarts=2 draws fresh modules"):
        discover(data, DiscoverySettings(2, restarts=2, restart_iterations=5, num_iterations=20, progress=False), Networks(options=options))
