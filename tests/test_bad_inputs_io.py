"""Every bad input gets a clear error at the API's door: one row per case, asserting the error type and a phrase
of its message (issue 26). Discovery, segmentation, option/hierarchy/checkpoint/trajectory files, the DQN and its
configuration, the Atari configuration, and every recipe setting."""
import copy
import os
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_options import (
    as_trajectory_batch,
    discover_hierarchy,
    discover_options,
    load_hierarchy,
    load_options,
    MetaControlMLP,
    OptionHierarchy,
    OptionsDQNConfig,
    OptionsMLP,
    save_hierarchy,
    save_options,
    segment,
)
from torchrl_options.experiments.atari import AtariConfig
from torchrl_options.experiments.atari.config import check_atari_recipe_settings
from torchrl_options.experiments.gridworld_config import gridworld_settings
from torchrl_options.experiments.recipe_runner import setting_error_line
from torchrl_options.experiments.segment_config import segment_settings
from torchrl_options.segmentation.io import load_trajectories, TrajectoryFileError

ROOT = Path(__file__).resolve().parents[1]


def _data(B=2, T=5, D=2, A=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, T + 1, D, generator=g)
    action = torch.randint(A, (B, T), generator=g)
    return TensorDict({"observation": obs[:, :-1], "action": action, "next": {"observation": obs[:, 1:]}}, [B, T])


def _with(td, key, value):
    td = td.clone()
    td.set(key, value)
    return td


def _without(td, key):
    return td.exclude(key)


def _discover(data, k=2, **kw):
    return lambda: discover_options(data, k, num_iterations=1, progress=False, **kw)


D = _data()


def _save(data):
    import tempfile

    from torchrl_options.segmentation.io import save_trajectories

    return save_trajectories(data, Path(tempfile.mkdtemp()) / "demos.npz")

TRAJS = [D[0], D[1]]

# ------------------------------------------------------------------------------------------- discovery
DISCOVERY = [
    ("list with an empty trajectory", _discover([D[0], D[1][:0]]), ValueError, "trajectories[1] is empty"),
    ("empty [0, T] batch", _discover(D[:0]), ValueError, "trajectories is empty"),
    ("empty [B, 0] batch", _discover(D[:, :0]), ValueError, "trajectories is empty"),
    ("empty list", _discover([]), ValueError, "empty list"),
    ("list of non-tensordicts", _discover([torch.zeros(3)]), TypeError, "trajectories[0] must be a [T] TensorDict"),
    ("a string", _discover("demos.npz"), TypeError, "trajectories must be a TensorDict"),
    ("[B, T, X] batch", _discover(D.unsqueeze(-1)), ValueError, "must be [B, T]"),
    ("[B, T] items in a list", _discover([D, D]), ValueError, "trajectories[0] must be a [T] TensorDict"),
    ("list items with other keys", _discover([D[0], D[1].exclude("action")]), ValueError, "other entries"),
    ("K of the options module differs", _discover(D, 3, options=OptionsMLP(2, 3, 2)), ValueError,
     "num_options=3 but the options module has K=2"),
    ("A of the options module differs", _discover(D, 2, options=OptionsMLP(2, 4, 2), num_actions=3), ValueError,
     "num_actions=3 but the options module has A=4"),
    ("float num_options", _discover(D, 2.0), TypeError, "num_options must be an int"),
    ("bool num_options", _discover(D, True), TypeError, "num_options must be an int"),
    ("num_options 0", _discover(D, 0), ValueError, "num_options must be an int >= 1"),
    ("str num_options", _discover(D, "2"), TypeError, "num_options must be an int"),
    ("num_actions 0", _discover(D, num_actions=0), ValueError, "num_actions must be an int >= 1"),
    ("float mask", _discover(_with(D, ("collector", "mask"), torch.ones(2, 5))), ValueError, "must be bool"),
    ("mask of another shape", _discover(_with(D, ("collector", "mask"), torch.ones(2, 5, 2, dtype=torch.bool))),
     ValueError, "must have shape [2, 5]"),
    ("a row without a valid step", _discover(_with(D, ("collector", "mask"), torch.tensor([[True] * 5, [False] * 5]))),
     ValueError, "trajectory 1 has no valid step"),
    ("missing action", _discover(_without(D, "action")), ValueError, "no 'action' entry (action_key)"),
    ("missing observation", _discover(_without(D, "observation")), ValueError, "no 'observation' entry (obs_keys)"),
    ("obs features differ from the options module", _discover(D, options=OptionsMLP(5, 3, 2)), ValueError,
     "cannot read the trajectories"),
    ("next observation of another shape", _discover(_with(D, ("next", "observation"), torch.zeros(2, 5, 3))),
     ValueError, "('next', 'observation') must have the shape of 'observation'"),
    ("terminated of the wrong shape", _discover(_with(D, ("next", "terminated"), torch.zeros(2, 5, 2, dtype=torch.bool))),
     ValueError, "('next', 'terminated') must have shape [B, T]"),
    ("NaN observation at a valid step", _discover(_with(D, "observation", D["observation"].index_fill(1, torch.tensor([2]), float("nan")))),
     ValueError, "NaN or inf at trajectory 0, step 2"),
    ("negative action", _discover(_with(D, "action", -D["action"] - 1)), ValueError, "negative actions"),
    ("action out of num_actions", _discover(D, num_actions=2, options=None), ValueError, "outside [0, num_actions=2)"),
    ("non-integer categorical actions", _discover(_with(D, "action", D["action"] + 0.5)), ValueError, "non-integer"),
    ("integer actions, continuous space", _discover(D, action_space="continuous"), ValueError, "needs float actions"),
    ("options not a module", _discover(D, options=torch.nn.Linear(2, 2)), TypeError, "options must be None or a TensorDictModuleBase"),
    ("meta_control of a wrong type", _discover(D, meta_control=3), TypeError, "meta_control must be"),
    ("meta_control module of another K", _discover(D, 2, meta_control=MetaControlMLP(2, 3)), ValueError,
     "writes 3 meta_logits"),
    ("flat sample without its trajectory_key", lambda: as_trajectory_batch(D[0], trajectory_key="ids"), ValueError,
     "no 'ids' entry (trajectory_key)"),
    ("hierarchy: missing action", lambda: discover_hierarchy(_without(D, "action"), [2], num_iterations=1, progress=False),
     ValueError, "no 'action' entry"),
    ("hierarchy: num_options 0", lambda: discover_hierarchy(D, [2, 0], num_iterations=1, progress=False), ValueError,
     "num_options must be a non-empty list of positive ints"),
    ("hierarchy: next observation of another shape",
     lambda: discover_hierarchy(_with(D, ("next", "observation"), torch.zeros(2, 5, 1)), [2], num_iterations=1, progress=False),
     ValueError, "must have the shape of 'observation'"),
    ("hierarchy: empty trajectory", lambda: discover_hierarchy([D[0], D[1][:0]], [2], num_iterations=1, progress=False),
     ValueError, "trajectories[1] is empty"),
    ("segment: options not a module", lambda: segment(D, torch.nn.Linear(2, 2)), TypeError, "options must be a TensorDictModuleBase"),
    ("segment: obs features differ", lambda: segment(D, OptionsMLP(4, 3, 2)), ValueError, "cannot read the trajectories"),
    ("segment: missing action", lambda: segment(_without(D, "action"), OptionsMLP(2, 3, 2)), ValueError, "no 'action' entry"),
    ("segment: threshold 2", lambda: segment(D, OptionsMLP(2, 3, 2), method="posterior", threshold=2.0), ValueError,
     "threshold must be a number in [0, 1], got 2"),
    ("segment: batch_size 0", lambda: segment(D, OptionsMLP(2, 3, 2), batch_size=0), ValueError, "batch_size must be an int >= 1"),
    ("segment: meta_control of a wrong type", lambda: segment(D, OptionsMLP(2, 3, 2), meta_control=3), TypeError,
     "meta_control must be None or a TensorDictModuleBase"),
    ("save_trajectories: [T] data", lambda: _save(D[0]), ValueError, "must be a [B, T] TensorDict"),
    ("save_trajectories: missing action", lambda: _save(_without(D, "action")), ValueError, "data lacks ['action']"),
    ("save_trajectories: not a TensorDict", lambda: _save([1]), TypeError, "data must be a [B, T] TensorDict"),
    ("segment: empty trajectory", lambda: segment([D[0][:0]], OptionsMLP(2, 3, 2)), ValueError, "trajectories[0] is empty"),
]  # fmt: skip


@pytest.mark.parametrize("name, call, error, phrase", DISCOVERY, ids=[c[0] for c in DISCOVERY])
def test_discovery_bad_inputs(name, call, error, phrase):
    with pytest.raises(error) as info:
        call()
    assert phrase in str(info.value)


# ------------------------------------------------------------------------------------------------ files
def _options_file(path):
    save_options(OptionsMLP(2, 3, 2), path)
    return path


def _hierarchy_file(path):
    save_hierarchy(OptionHierarchy(3, [OptionsMLP(2, 3, 2)]), path)
    return path


def _rewrite(path, change):
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, path)
    return path


def _set_config(payload, key, value):
    payload["options"]["config"][key] = value


FILES = [
    ("options: missing file", lambda p: load_options(p / "nope.pt"), ValueError, "no such options file"),
    ("options: missing file is a FileNotFoundError", lambda p: load_options(p / "nope.pt"), FileNotFoundError, "nope.pt"),
    ("options: empty file", lambda p: (open(p / "e.pt", "wb").close(), load_options(p / "e.pt")), ValueError, "e.pt: this options file is empty"),
    ("options: truncated file", lambda p: load_options(_truncate(_options_file(p / "t.pt"))), ValueError, "t.pt: not a readable options file"),
    ("options: corrupt file", lambda p: load_options(_garbage(p / "c.pt")), ValueError, "c.pt: not a readable options file"),
    ("options: a directory", lambda p: load_options(p), ValueError, "got a directory"),
    ("options: plain data of another kind", lambda p: (torch.save({"a": 1}, p / "o.pt"), load_options(p / "o.pt")),
     ValueError, "o.pt: not an options file written by torchrl_options.save_options"),
    ("options: config disagrees with weights",
     lambda p: load_options(_rewrite(_options_file(p / "w.pt"), lambda d: _set_config(d, "num_options", 3))),
     ValueError, "weights disagree with its stored configuration"),
    ("options: unknown class", lambda p: load_options(_rewrite(_options_file(p / "u.pt"), lambda d: d["options"].update({"class": "Evil"}))),
     ValueError, "unknown module class 'Evil'"),
    ("options: config that builds nothing",
     lambda p: load_options(_rewrite(_options_file(p / "b.pt"), lambda d: _set_config(d, "activation", "nope"))),
     ValueError, "configuration does not build one"),
    ("options: entry without weights", lambda p: load_options(_rewrite(_options_file(p / "n.pt"), lambda d: d["options"].pop("state_dict"))),
     ValueError, "must hold 'class', 'config' and 'state_dict'"),
    ("hierarchy: missing file", lambda p: load_hierarchy(p / "nope.pt"), ValueError, "no such hierarchy file"),
    ("hierarchy: empty file", lambda p: (open(p / "e.pt", "wb").close(), load_hierarchy(p / "e.pt")), ValueError, "is empty"),
    ("hierarchy: truncated file", lambda p: load_hierarchy(_truncate(_hierarchy_file(p / "t.pt"))), ValueError, "not a readable hierarchy file"),
    ("hierarchy: an options file", lambda p: load_hierarchy(_options_file(p / "o.pt")), ValueError, "not a hierarchy file"),
    ("hierarchy: missing entries", lambda p: load_hierarchy(_rewrite(_hierarchy_file(p / "m.pt"), lambda d: d.pop("levels"))),
     ValueError, "lacks ['levels']"),
    ("hierarchy: level weights disagree", lambda p: load_hierarchy(_rewrite(_hierarchy_file(p / "w.pt"),
     lambda d: d["levels"][0]["config"].update({"in_features": 5}))), ValueError, "weights disagree"),
    ("hierarchy: inconsistent levels", lambda p: load_hierarchy(_rewrite(_hierarchy_file(p / "i.pt"), lambda d: d.update({"num_actions": 7}))),
     ValueError, "the stored hierarchy is inconsistent"),
    ("trajectories: .pt of another kind", lambda p: (torch.save([1, 2], p / "l.pt"), load_trajectories(p / "l.pt")),
     TrajectoryFileError, "expected trajectories"),
    ("trajectories: empty .pt", lambda p: (open(p / "e.pt", "wb").close(), load_trajectories(p / "e.pt")), TrajectoryFileError, "is empty"),
    ("trajectories: truncated .pt", lambda p: load_trajectories(_truncate(_traj_file(p / "t.pt"))), TrajectoryFileError, "not a readable trajectories file"),
    ("trajectories: directory without meta.json", lambda p: ((p / "d").mkdir(), load_trajectories(p / "d")),
     TrajectoryFileError, "not a TensorDict directory"),
    ("DQN checkpoint: missing", lambda p: _agent().load(p / "nope.pt"), ValueError, "no such OptionsDQN checkpoint file"),
    ("DQN checkpoint: truncated", lambda p: _agent().load(_truncate(_dqn_file(p / "t.pt"))), ValueError, "not a readable OptionsDQN checkpoint"),
    ("DQN checkpoint: an options file", lambda p: _agent().load(_options_file(p / "o.pt")), ValueError, "not an OptionsDQN checkpoint"),
    ("DQN checkpoint: another mode", lambda p: _agent().load(_rewrite(_dqn_file(p / "m.pt"), lambda d: d["config"].update({"mode": "both"}))),
     ValueError, "mode='both', this agent has mode='actions'"),
    ("DQN checkpoint: another network", lambda p: _agent(hidden=(3,)).load(_dqn_file(p / "n.pt")), ValueError, "networks do not fit"),
    ("DQN state: not a dict", lambda p: _agent().load_state_dict([1]), TypeError, "expected a dict"),
]  # fmt: skip


def _truncate(path):
    data = Path(path).read_bytes()
    Path(path).write_bytes(data[: len(data) // 2])
    return path


def _garbage(path):
    Path(path).write_bytes(os.urandom(256))
    return path


def _traj_file(path):
    from torchrl_options.segmentation.io import save_trajectories

    return save_trajectories(_with(D, ("collector", "mask"), torch.ones(2, 5, dtype=torch.bool)), path)


def _agent(hidden=(2,)):
    from torchrl_options.experiments.gridworld import make_agent

    cfg = {"env": {"grid": "two-rooms", "task": "goal", "max_steps": 10}, "num_envs": 2,
           "dqn": {"hidden_sizes": list(hidden), "frames_per_batch": 8, "buffer_size": 64}}  # fmt: skip
    return make_agent(cfg, "actions", 0)


def _dqn_with(**kw):
    from torchrl_options import GridWorldEnv, OptionsDQN

    args = {"env_factory": lambda: GridWorldEnv("two-rooms", task="goal"), "config": OptionsDQNConfig(mode="both"),
            "options": OptionsMLP(4, 4, 2), "num_options": 2, **kw}  # fmt: skip
    return OptionsDQN(args.pop("env_factory"), args.pop("config"), **args)


def _dqn_file(path):
    _agent().save(path)
    return path


@pytest.mark.parametrize("name, call, error, phrase", FILES, ids=[c[0] for c in FILES])
def test_file_bad_inputs(tmp_path, name, call, error, phrase):
    with pytest.raises(error) as info:
        call(tmp_path)
    assert phrase in str(info.value)


# ----------------------------------------------------------------------------------------- configurations
CONFIGS = [
    ("dqn gamma 1.5", lambda: OptionsDQNConfig(gamma=1.5), ValueError, "gamma must be in [0, 1], got 1.5"),
    ("dqn gamma -0.5", lambda: OptionsDQNConfig(gamma=-0.5), ValueError, "gamma must be in [0, 1]"),
    ("dqn lr 0", lambda: OptionsDQNConfig(lr=0), ValueError, "lr must be in (0, inf)"),
    ("dqn lr nan", lambda: OptionsDQNConfig(lr=float("nan")), ValueError, "lr must be in"),
    ("dqn lr str", lambda: OptionsDQNConfig(lr="fast"), TypeError, "lr must be a number"),
    ("dqn batch_size 0", lambda: OptionsDQNConfig(batch_size=0), ValueError, "batch_size must be an int >= 1"),
    ("dqn frames_per_batch 2.5", lambda: OptionsDQNConfig(frames_per_batch=2.5), TypeError, "frames_per_batch must be an int"),
    ("dqn mode", lambda: OptionsDQNConfig(mode="primitive"), ValueError, "mode must be one of"),
    ("dqn hidden_sizes 0", lambda: OptionsDQNConfig(hidden_sizes=(0,)), ValueError, "hidden_sizes must be a list of ints >= 1"),
    ("dqn eps_init 2", lambda: OptionsDQNConfig(eps_init=2.0), ValueError, "eps_init must be in [0, 1]"),
    ("dqn max_grad_norm 0", lambda: OptionsDQNConfig(max_grad_norm=0), ValueError, "max_grad_norm must be None or > 0"),
    ("dqn loss_function", lambda: OptionsDQNConfig(loss_function="huber"), ValueError, "loss_function must be one of"),
    ("dqn target_update", lambda: OptionsDQNConfig(target_update="polyak"), ValueError, "target_update must be one of"),
    ("dqn max_decisions 0", lambda: OptionsDQNConfig(max_decisions=0), ValueError, "max_decisions must be an int >= 1"),
    ("dqn num_envs 0", lambda: OptionsDQNConfig(num_envs=0), ValueError, "num_envs must be an int >= 1"),
    ("dqn soft_update_eps 1", lambda: OptionsDQNConfig(soft_update_eps=1.0), ValueError, "soft_update_eps must be in (0, 1)"),
    ("OptionsDQN num_options 2.5", lambda: _dqn_with(num_options=2.5), TypeError, "num_options must be an int"),
    ("OptionsDQN num_options 0", lambda: _dqn_with(num_options=0), ValueError, "num_options must be an int >= 1"),
    ("OptionsDQN options not a module", lambda: _dqn_with(options=torch.nn.Linear(2, 2)), TypeError,
     "options must be a TensorDictModuleBase"),
    ("OptionsDQN without options", lambda: _dqn_with(options=None), ValueError, "needs `options` and `num_options`"),
    ("OptionsDQN env_factory not callable", lambda: _dqn_with(env_factory=3), TypeError, "env_factory must be a callable"),
    ("OptionsDQN config of another type", lambda: _dqn_with(config={"mode": "both"}), TypeError, "config must be an OptionsDQNConfig"),
    ("atari phase1_episodes -5", lambda: AtariConfig(phase1_episodes=-5), ValueError, "phase1_episodes must be an int >= 1"),
    ("atari gamma 2", lambda: AtariConfig(gamma=2.0), ValueError, "gamma must be in [0, 1], got 2.0"),
    ("atari ram_encoding", lambda: AtariConfig(ram_encoding="pixels"), ValueError, "ram_encoding must be one of ('one_hot', 'bytes'), got 'pixels'"),
    ("atari hidden_sizes empty", lambda: AtariConfig(hidden_sizes=()), ValueError, "hidden_sizes must be a non-empty list"),
    ("atari lr 0", lambda: AtariConfig(lr=0), ValueError, "lr must be in (0, inf)"),
    ("atari num_options 0", lambda: AtariConfig(num_options=0), ValueError, "num_options must be an int >= 1"),
    ("atari checkpoint_every -1", lambda: AtariConfig(checkpoint_every=-1), ValueError, "checkpoint_every must be an int >= 0"),
    ("atari frame_skip 1.5", lambda: AtariConfig(frame_skip=1.5), TypeError, "frame_skip must be an int"),
    ("atari unknown key", lambda: AtariConfig.from_dict({"phase2_episodes": 3}), ValueError, "unknown Atari settings"),
    ("atari ddo_m_steps 0", lambda: AtariConfig(ddo_m_steps=0), ValueError, "ddo_m_steps must be an int >= 1, got 0"),
]  # fmt: skip


@pytest.mark.parametrize("name, call, error, phrase", CONFIGS, ids=[c[0] for c in CONFIGS])
def test_configuration_bad_inputs(name, call, error, phrase):
    with pytest.raises(error) as info:
        call()
    assert phrase in str(info.value)


# ------------------------------------------------------------------------------------------ recipe settings
def _recipe_cfg(name, *overrides):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from torchrl_options.experiments.atari import store_atari_config

    store_atari_config()  # the schema of atari_ram's `atari` section (the recipe registers it when imported)
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        return OmegaConf.to_container(compose(name, overrides=list(overrides)), resolve=True)


_BASE = {}


def _changed(name, dotted, value, *overrides):
    key = (name, overrides)
    if key not in _BASE:
        _BASE[key] = _recipe_cfg(name, *overrides)
    cfg = copy.deepcopy(_BASE[key])
    *parents, last = dotted.split(".")
    node = cfg
    for p in parents:
        node = node[p]
    node[last] = value
    return cfg


GRIDWORLD = [
    ("episodes", -5, "episodes must be an int >= 1, got -5"),
    ("episodes", "ten", "episodes: Value 'ten' of type 'str' could not be converted to Integer"),
    ("seeds", 0, "seeds must be a count >= 1"),
    ("seeds", [0, 0], "seeds must not repeat a seed"),
    ("seeds", [-1], "seeds must be a count >= 1 or a non-empty list of ints >= 0"),
    ("num_envs", 0, "num_envs must be an int >= 1"),
    ("checkpoint_every", 0, "checkpoint_every must be an int >= 1"),
    ("stop_after_cells", -1, "stop_after_cells must be an int >= 0"),
    ("backend", "gpu", "backend must be one of ('serial', 'local', 'ray')"),
    ("num_workers", 0, "num_workers must be an int >= 1"),
    ("settings_to_run", ["nowhere"], "settings_to_run: unknown settings ['nowhere']"),
    ("conditions_to_run", [], "conditions_to_run must be a non-empty list"),
    ("conditions_to_run", ["Z"], "conditions_to_run: unknown conditions ['Z']"),
    ("conditions.A.mode", "primitive", "conditions.A.mode must be one of"),
    ("conditions.H1u.meta_control", "deep", "conditions.H1u.meta_control must be one of"),
    ("conditions.H1u.levels", 0, "conditions.H1u.levels must be an int >= 1"),
    ("settings.exploration.source", "oracle", "settings.exploration.source must be one of"),
    ("settings.exploration.pretrain_episodes", 0, "settings.exploration.pretrain_episodes must be an int >= 1"),
    ("settings.exploration.greedy.num", 0, "settings.exploration.greedy.num must be an int >= 1"),
    ("settings.exploration.greedy.epsilon", 1.5, "settings.exploration.greedy.epsilon must be 'agent' or a number in [0, 1], got 1.5"),
    ("settings.exploration.greedy.epsilon", "greedy", "settings.exploration.greedy.epsilon must be 'agent' or a number in [0, 1], got 'greedy'"),
    ("settings.exploration.greedy.keep", "best", "settings.exploration.greedy.keep must be one of ('all', 'rewarded')"),
    ("discovery.preset", "fast", "discovery.preset must be one of ('paper', 'defaults')"),
    ("discovery.m_steps", 0, "discovery.m_steps must be an int >= 1"),
    ("discovery.restarts", 0, "discovery.restarts must be an int >= 1"),
    ("discovery.tol", -1, "discovery.tol must be a number >= 0, got -1"),
    ("discovery.num_options", 0, "discovery.num_options must be an int >= 1"),
    ("discovery.num_iterations", -1, "discovery.num_iterations must be an int >= 0"),
    ("discovery.lr", 0, "discovery.lr must be a positive finite number, got 0"),
    ("discovery.batch_size", 0, "discovery.batch_size must be an int >= 1"),
    ("discovery.init", "zeros", "discovery.init must be one of"),
    ("discovery.activation", "swish", "discovery.activation must be one of"),
    ("discovery.num_cells", [0], "discovery.num_cells must be one positive int or a non-empty sequence of them"),
    ("demos.num", 0, "demos.num must be an int >= 1"),
    ("demos.length", -1, "demos.length must be an int >= 1"),
    ("env.noise", 2, "env.noise must be a number in [0, 1]"),
    ("env.max_steps", 0, "env.max_steps must be an int >= 1"),
    ("env.grid", "nowhere", "env: Unknown map 'nowhere'"),
    ("env.task", "chess", "env: "),
    ("dqn.gamma", 1.5, "dqn.gamma must be in [0, 1]"),
    ("dqn.lr", -1, "dqn.lr must be in (0, inf)"),
    ("dqn.batch_size", 0, "dqn.batch_size must be an int >= 1"),
    ("dqn.frames_per_batch", 100, "dqn.frames_per_batch must be a multiple of num_envs (16), got 100"),
    ("dqn.hidden_sizes", [0], "dqn.hidden_sizes must be a list of ints >= 1"),
    ("dqn.warp_speed", 9, "dqn.warp_speed: Key 'warp_speed' not in 'DQNSection'"),
    ("summary.final_window", 0, "summary.final_window must be an int >= 1"),
    ("pictures.num_starts", 0, "pictures.num_starts must be an int >= 1"),
    ("out_dir", "", "out_dir must be a folder name"),
    ("discovery.num_optons", 3, "discovery.num_optons: Key 'num_optons' not in 'DiscoverySection'"),
    ("dqn.lr", "abc", "dqn.lr: Value 'abc' of type 'str' could not be converted to Float"),
    ("conditions.H1u.levels", "two", "conditions.H1u.levels: Value 'two' of type 'str' could not be converted to Integer"),
    ("scale.four_rooms.epsiodes", 3, "scale.four_rooms.epsiodes: Key 'epsiodes' not in 'RecipeScale'"),
    ("log_file", "logs/run.log", "log_file must be a file name"),
]  # fmt: skip


@pytest.mark.parametrize("key, value, phrase", GRIDWORLD, ids=[f"{k}={v!r}" for k, v, _ in GRIDWORLD])
def test_gridworld_recipe_settings(key, value, phrase):
    """The schema (GridWorldRecipeConfig) refuses the key or the value, naming it, in one line."""
    cfg = _changed("four_rooms", key, value, "scale=tiny")
    with pytest.raises(Exception) as info:
        gridworld_settings(cfg)
    assert isinstance(info.value, (ValueError, TypeError, KeyError)), repr(info.value)
    line = setting_error_line(info.value)
    assert phrase in line and "\n" not in line, line


ATARI = [
    ("games", [], "games must be a non-empty list"),
    ("seeds", 0, "seeds must be a count >= 1"),
    ("conditions", ["H9"], "conditions must be one of"),
    ("final_window", 0, "final_window must be an int >= 1"),
    ("sweep.backend", "slurm", "sweep.backend must be one of"),
    ("sweep.num_workers", 0, "sweep.num_workers must be an int >= 1"),
    ("atari.phase1_episodes", 0, "atari.phase1_episodes must be an int >= 1"),
    ("atari.gamma", 1.5, "atari.gamma must be in [0, 1], got 1.5"),
    ("atari.warp", 1, "unknown Atari settings: ['warp']"),
]  # fmt: skip


@pytest.mark.parametrize("key, value, phrase", ATARI, ids=[f"{k}={v!r}" for k, v, _ in ATARI])
def test_atari_recipe_settings(key, value, phrase):
    cfg = _changed("atari_ram", key, value, "preset=smoke")
    with pytest.raises(ValueError) as info:
        check_atari_recipe_settings(cfg)
    assert phrase in str(info.value)


SEGMENT = [
    ("data.source", "camera", "data.source must be one of"),
    ("data.num_trajectories", 0, "data.num_trajectories must be an int >= 1"),
    ("data.format", "csv", "data.format must be one of"),
    ("discovery.num_options", 0, "discovery.num_options must be an int >= 1"),
    ("discovery.lr", -1, "discovery.lr must be a positive finite number, got -1"),
    ("discovery.num_cells", [0], "discovery.num_cells must be a non-empty list of ints >= 1, got [0]"),
    ("discovery.init_scale", 0.0, "discovery.init_scale must be a positive finite number, got 0"),
    ("discovery.init_scale", "one", "discovery.init_scale: Value 'one' of type 'str' could not be converted to Float"),
    ("segmentation.method", "greedy", "segmentation.method must be one of"),
    ("segmentation.boundary", "edge", "segmentation.boundary must be one of"),
    ("segmentation.baseline_samples", 0, "segmentation.baseline_samples must be an int >= 1"),
    ("plot.max_trajectories", 0, "plot.max_trajectories must be an int >= 1"),
]  # fmt: skip


@pytest.mark.parametrize("key, value, phrase", SEGMENT, ids=[f"{k}={v!r}" for k, v, _ in SEGMENT])
def test_segment_recipe_settings(key, value, phrase):
    cfg = _changed("segment", key, value)
    with pytest.raises(Exception) as info:
        segment_settings(cfg)
    assert isinstance(info.value, (ValueError, TypeError, KeyError)), repr(info.value)
    line = setting_error_line(info.value)
    assert phrase in line and "\n" not in line, line


def test_gridworld_discovery_init_is_the_librarys():
    """``discovery.init`` takes what discover_options takes (DiscoverySettings' INITS), nothing else."""
    from torchrl_options.discovery import INITS

    assert {"random", "kmeans", "segments", "auto"} <= set(INITS)
    for init in INITS:
        assert gridworld_settings(_changed("four_rooms", "discovery.init", init, "scale=tiny"))["discovery"]["init"] == init
        assert segment_settings(_changed("segment", "discovery.init", init)).discovery.init == init
    with pytest.raises(ValueError, match="discovery.init must be one of 'random', 'kmeans'"):
        gridworld_settings(_changed("four_rooms", "discovery.init", "spectral", "scale=tiny"))


@pytest.mark.parametrize(
    "override, phrase",
    [("+discovery.num_optons=3", "error: discovery.num_optons: Key 'num_optons' not in 'DiscoverySection'"),
     ("discovery.num_optons=3", "discovery.num_optons: Key 'num_optons' not in 'DiscoverySection'"),
     ("dqn.lr=abc", "error: Error merging override dqn.lr=abc: dqn.lr: Value 'abc' of type 'str' could not be "
                    "converted to Float"),
     ("env.grid=nope", "error: env: Unknown map 'nope'")],
)  # fmt: skip
def test_gridworld_recipe_refuses_on_the_command_line_in_one_line(tmp_path, override, phrase):
    """Hydra's refusals while composing (an unknown key, a wrong type) and the schema's value checks end the
    same way: status 2, one line through recipe_guard, no traceback, nothing run."""
    import subprocess
    import sys

    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "four_rooms.py"), "scale=tiny", f"out_dir={out}", override],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and phrase in lines[0], result.stderr
    assert not (out / "results.csv").exists()


def test_segment_file_source_needs_a_path():
    cfg = _changed("segment", "data.source", "file")
    with pytest.raises(ValueError, match="data.source=file needs data.path"):
        segment_settings(cfg)


def test_valid_recipe_settings_pass():
    for name, overrides in (("four_rooms", ["scale=tiny"]), ("four_rooms", ["scale=paper"]), ("two_rooms", []),
                            ("three_rooms", []), ("segment", [])):  # fmt: skip
        cfg = _recipe_cfg(name, *overrides)
        (segment_settings if name == "segment" else gridworld_settings)(cfg)
    check_atari_recipe_settings(_recipe_cfg("atari_ram", "preset=paper"))
