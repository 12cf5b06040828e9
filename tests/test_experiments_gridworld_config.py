"""The GridWorld and segmentation recipes' Hydra schemas (experiments/gridworld_config.py, segment_config.py,
recipe_config.py): the composed settings are the ones the recipes ran with before the schema (pinned, and the kept
runs' settings.json), the sections follow the library's classes, and a bad key or value is refused."""
import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from torchrl_options.agents import OptionsDQNConfig, OptionsPPOConfig
from torchrl_options.experiments.gridworld_config import DQNSection, gridworld_settings, PPOSection
from torchrl_options.experiments.gridworld_run import RUN_ONLY_SETTINGS
from torchrl_options.experiments.run_settings import flatten_settings, settings_differences
from torchrl_options.experiments.segment_config import segment_settings

ROOT = Path(__file__).resolve().parents[1]

# protocol=paper at scale=paper, as the recipes resolved it before the schema (apply_protocol over the composed
# YAML, keys left at null dropped; the run-only keys left out): the paper's DDO settings and greedy rollouts
FOUR_ROOMS_PAPER = {
    "checkpoint_every": 100,
    "conditions.A.mode": "actions",
    "conditions.H1s.meta_control": "learned",
    "conditions.H1s.mode": "both",
    "conditions.H1u.meta_control": "uniform",
    "conditions.H1u.mode": "both",
    "conditions.H2s.levels": 2,
    "conditions.H2s.meta_control": "learned",
    "conditions.H2s.mode": "both",
    "conditions.H2u.levels": 2,
    "conditions.H2u.meta_control": "uniform",
    "conditions.H2u.mode": "both",
    "demos.length": 1000,
    "demos.num": 50,
    "discovery.activation": "tanh",
    "discovery.batch_size": 10,
    "discovery.init": "random",
    "discovery.lr": 0.01,
    "discovery.num_cells": 2,
    "discovery.num_iterations": 500,
    "discovery.num_options": 4,
    "discovery.preset": "paper",
    "dqn.batch_size": 128,
    "dqn.buffer_size": 100000,
    "dqn.eps_end": 0.2,
    "dqn.eps_init": 0.2,
    "dqn.frames_per_batch": 160,
    "dqn.gamma": 0.9,
    "dqn.hard_update_interval": 200,
    "dqn.hidden_sizes": [2],
    "dqn.learning_starts": 500,
    "dqn.loss_function": "l2",
    "dqn.lr": 0.01,
    "dqn.max_grad_norm": 10.0,
    "dqn.updates_per_batch": 8,
    "env.grid": "four-rooms",
    "env.max_steps": 100,
    "env.noise": 0.3,
    "env.task": "apple",
    "episodes": 5000,
    "num_envs": 16,
    "protocol": "paper",
    "settings.exploration.greedy.epsilon": 0.0,
    "settings.exploration.greedy.keep": "all",
    "settings.exploration.greedy.length": 1000,
    "settings.exploration.greedy.num": 100,
    "settings.exploration.pretrain_episodes": 2000,
    "settings.exploration.source": "greedy",
    "settings.supervised.source": "supervisor",
}
THREE_ROOMS_PAPER = {
    "checkpoint_every": 100,
    "conditions.A.mode": "actions",
    "conditions.H1u.meta_control": "uniform",
    "conditions.H1u.mode": "both",
    "discovery.activation": "tanh",
    "discovery.batch_size": 20,
    "discovery.init": "random",
    "discovery.lr": 0.01,
    "discovery.num_cells": 2,
    "discovery.num_iterations": 500,
    "discovery.num_options": 2,
    "discovery.preset": "paper",
    "dqn.batch_size": 128,
    "dqn.buffer_size": 100000,
    "dqn.eps_end": 0.2,
    "dqn.eps_init": 0.2,
    "dqn.frames_per_batch": 160,
    "dqn.gamma": 0.9,
    "dqn.hard_update_interval": 200,
    "dqn.hidden_sizes": [2],
    "dqn.learning_starts": 500,
    "dqn.loss_function": "l2",
    "dqn.lr": 0.01,
    "dqn.max_grad_norm": 10.0,
    "dqn.updates_per_batch": 8,
    "env.grid": "three-rooms",
    "env.max_steps": 100,
    "env.noise": 0.3,
    "env.task": "subgoals",
    "episodes": 5000,
    "num_envs": 16,
    "protocol": "paper",
    "settings.exploration.greedy.epsilon": 0.0,
    "settings.exploration.greedy.keep": "all",
    "settings.exploration.greedy.length": 100,
    "settings.exploration.greedy.num": 100,
    "settings.exploration.pretrain_episodes": 5000,
    "settings.exploration.source": "greedy",
}


def _compose(name, *overrides):
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


@pytest.mark.parametrize("name, pinned", [("four_rooms", FOUR_ROOMS_PAPER), ("three_rooms", THREE_ROOMS_PAPER)])
def test_protocol_paper_at_paper_scale_is_the_old_config(name, pinned):
    settings = gridworld_settings(_compose(name, "scale=paper", "protocol=paper"))
    assert flatten_settings(settings, ignore=RUN_ONLY_SETTINGS) == pinned


@pytest.mark.parametrize(
    "kept, name, overrides",
    [("four_rooms_default_ours", "four_rooms", ["scale=default"]),
     ("four_rooms_exploration_ours", "four_rooms", ["scale=paper", "episodes=1000"]),
     ("four_rooms_ppo_15seeds", "four_rooms_ppo", ["scale=default"])],
)  # fmt: skip
def test_kept_runs_resume_with_the_schema(kept, name, overrides):
    """The settings recorded by kept runs (made before the schema) match the composed ones: their out_dirs resume."""
    recorded = json.loads((ROOT / "results" / kept / "settings.json").read_text())
    now = flatten_settings(gridworld_settings(_compose(name, *overrides)), ignore=RUN_ONLY_SETTINGS)
    assert settings_differences(recorded, now) == {}


def test_agent_sections_are_the_agents_config_fields():
    """The dqn/ppo sections' keys are the agents' config fields (not a copy), but those the recipe sets per cell."""
    import dataclasses

    for section, config in ((DQNSection, OptionsDQNConfig), (PPOSection, OptionsPPOConfig)):
        names = {f.name for f in dataclasses.fields(section)}
        assert names == {f.name for f in dataclasses.fields(config)} - {"mode", "num_envs", "seed"}
        assert all(f.default == "???" for f in dataclasses.fields(section))  # not set: the agent's default


def test_settings_left_out_take_the_readers_defaults():
    settings = gridworld_settings(_compose("two_rooms", "scale=tiny"))
    assert "protocol" not in settings and "algorithm" not in settings and "paper" not in settings["discovery"]
    assert settings["dqn"]["max_decisions"] is None and "double_dqn" not in settings["dqn"]  # null is a value there
    no_clipping = gridworld_settings(_compose("two_rooms", "scale=tiny", "dqn.max_grad_norm=null"))
    assert no_clipping["dqn"]["max_grad_norm"] is None  # not OptionsDQNConfig's default 10.0
    assert settings["demos"]["env"] == {"start": "random", "goal": "random", "max_steps": 100}
    with pytest.raises(ValueError, match="dqn.gamma must be in"):
        gridworld_settings({**settings, "dqn": {**settings["dqn"], "gamma": 1.5}})


def test_segment_settings_keep_the_yaml():
    cfg = segment_settings(_compose("segment", "discovery.init=segments"))
    assert cfg.discovery.init == "segments" and list(cfg.discovery.num_cells) == [16]
    with pytest.raises(ValueError, match="segmentation.method must be one of"):
        segment_settings(_compose("segment", "segmentation.method=greedy"))


def test_usage_floor_reaches_discover_options_and_is_refused_where_it_cannot_apply(monkeypatch, tmp_path):
    """``discovery.usage_floor`` (issue 49): checked at the config's door, refused with a multi-level condition, and
    passed to one-level discovery."""
    from torchrl_options.experiments import gridworld

    one_level = ["scale=tiny", "discovery.usage_floor=0.5", "conditions_to_run=[A,H1u]"]
    assert gridworld_settings(_compose("four_rooms", *one_level))["discovery"]["usage_floor"] == 0.5
    with pytest.raises(ValueError, match=r"discovery.usage_floor must be a share of the uniform usage 1/K in \(0, 1\), got 1.5"):
        gridworld_settings(_compose("four_rooms", "scale=tiny", "discovery.usage_floor=1.5", "conditions_to_run=[A,H1u]"))
    with pytest.raises(ValueError, match="discovery.usage_floor=0.5 applies to one-level discovery, but condition 'H2u'"):
        gridworld_settings(_compose("four_rooms", "scale=tiny", "discovery.usage_floor=0.5", "conditions_to_run=[A,H2u]"))
    seen = {}

    class Stop(Exception):
        pass

    def fake(*args, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(gridworld, "discover_options", fake)
    with pytest.raises(Stop):
        gridworld.discover_cached(lambda: None, tmp_path / "o.pt", num_options=2, meta_control="uniform", seed=0,
                                    discovery={"preset": "defaults", "usage_floor": 0.5})  # fmt: skip
    assert seen["usage_floor"] == 0.5
    with pytest.raises(ValueError, match="usage_floor applies to one-level discovery"):
        gridworld.discover_hierarchy_cached(lambda: None, tmp_path / "h.pt", num_options=[2, 2], meta_control="uniform",
                                            seed=0, discovery={"usage_floor": 0.5})  # fmt: skip
