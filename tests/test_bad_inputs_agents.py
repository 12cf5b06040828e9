"""Bad inputs of torchrl_options.agents (issue 53): OptionsPPO / OptionsDQN and their configs refuse an env where a
factory is expected, options the mode would ignore, collector batches the envs cannot fill exactly (which overran
the budget: 3 envs and frames_per_batch=10 trained 24 frames for total_frames=20), bad train / evaluate / checkpoint
arguments, and name the file of a checkpoint that is not one. One row per case, controls included."""
import math

import pytest
import torch
from torch import nn

from _bad_inputs import check, ids, OK
from _tiny_envs import Corridor
from torchrl_options import OptionsMLP, save_options
from torchrl_options.agents import (
    DQNHyperParameters,
    OptionsDQN,
    OptionsDQNConfig,
    OptionsPPO,
    OptionsPPOConfig,
    TrainingLog,
    widen_action_rows,
    widen_action_values,
)

NAN = float("nan")
pytestmark = pytest.mark.usefixtures("torch_single_thread")


def corridor():
    return Corridor(8)


def ppo(env=corridor, **kw):
    config = dict(mode="actions", frames_per_batch=8, minibatch_size=None, num_epochs=1, hidden_sizes=(8,))
    config.update(kw.pop("config", {}))
    return OptionsPPO(env, OptionsPPOConfig(**config), **kw)


def dqn(env=corridor, **kw):
    config = dict(mode="actions", frames_per_batch=8, hidden_sizes=(8,), buffer_size=64)
    config.update(kw.pop("config", {}))
    return OptionsDQN(env, OptionsDQNConfig(**config), **kw)


def options(k=2):
    return OptionsMLP(8, 2, k, in_keys=["observation"])


def both(make, **kw):
    return make(config={"mode": "both"}, options=options(), num_options=2, **kw)


def frames_after(make, total):
    agent = make()
    agent.train(total_frames=total)
    return agent.frames


def trained_frames_are(make, total, expected):
    def call():
        assert frames_after(make, total) == expected

    return call


def state_with(make, **entries):
    def call():
        agent = make()
        agent.load_state_dict({**agent.state_dict(), **entries})

    return call


def loads_and_is_unchanged(make, **entries):
    """A refused checkpoint leaves the agent as it was (nothing half-restored)."""

    def call():
        agent = make()
        before = {k: v.clone() for k, v in agent.loss_module.state_dict().items()}
        bad = make(config={"hidden_sizes": (8,)})
        for p in bad.loss_module.parameters():
            p.data.add_(1.0)
        state = {**bad.state_dict(), **entries}
        with pytest.raises(ValueError):
            agent.load_state_dict(state)
        after = agent.loss_module.state_dict()
        assert all(torch.equal(before[k], after[k]) for k in before), "a refused checkpoint changed the networks"

    return call


def file_call(path_of, method):
    def call(tmp_path):
        return method(path_of(tmp_path))

    return call


def _options_file(tmp_path):
    save_options(OptionsMLP(2, 3, 2), tmp_path / "options.pt")
    return tmp_path / "options.pt"


def _dqn_file(tmp_path):
    dqn().save(tmp_path / "dqn.pt")
    return tmp_path / "dqn.pt"


def _ppo_file(tmp_path):
    ppo().save(tmp_path / "ppo.pt")
    return tmp_path / "ppo.pt"


CASES = [
    # ---- OptionsPPOConfig / OptionsDQNConfig / DQNHyperParameters
    ("OptionsPPOConfig", "issue: num_envs=3, frames_per_batch=10 (the collector makes 12-frame batches)",
     lambda: OptionsPPOConfig(num_envs=3, frames_per_batch=10), ValueError,
     "frames_per_batch must be a multiple of the number of envs (num_envs=3)"),
    ("OptionsPPOConfig", "control: num_envs=3, frames_per_batch=9", lambda: OptionsPPOConfig(num_envs=3, frames_per_batch=9), OK, None),
    ("OptionsPPOConfig", "observation_key not a key", lambda: OptionsPPOConfig(observation_key=3), TypeError,
     "observation_key must be a NestedKey"),
    ("OptionsPPOConfig", "device unknown", lambda: OptionsPPOConfig(device="tpu"), ValueError, "device must be a device name"),
    ("OptionsPPOConfig", "max_grad_norm a string", lambda: OptionsPPOConfig(max_grad_norm="1"), TypeError,
     "max_grad_norm must be None or a number > 0"),
    ("OptionsPPOConfig", "max_grad_norm NaN", lambda: OptionsPPOConfig(max_grad_norm=NAN), ValueError, "max_grad_norm must be None or > 0"),
    ("OptionsPPOConfig", "max_grad_norm inf", lambda: OptionsPPOConfig(max_grad_norm=math.inf), ValueError, "max_grad_norm must be None or > 0"),
    ("OptionsPPOConfig", "minibatch_size 0", lambda: OptionsPPOConfig(minibatch_size=0), ValueError, "minibatch_size must be an int >= 1"),
    ("OptionsPPOConfig", "gamma a string", lambda: OptionsPPOConfig(gamma="0.9"), TypeError, "gamma must be a number"),
    ("OptionsPPOConfig", "total_frames negative", lambda: OptionsPPOConfig(total_frames=-1), ValueError, "total_frames must be an int >= 0"),
    ("OptionsPPOConfig", "control: max_grad_norm None, device 'cpu:0'",
     lambda: OptionsPPOConfig(max_grad_norm=None, device="cpu:0"), OK, None),
    ("OptionsDQNConfig", "num_envs=3, frames_per_batch=10", lambda: OptionsDQNConfig(num_envs=3, frames_per_batch=10),
     ValueError, "frames_per_batch must be a multiple of the number of envs (num_envs=3)"),
    ("OptionsDQNConfig", "observation_key not a key", lambda: OptionsDQNConfig(observation_key=3), TypeError,
     "observation_key must be a NestedKey"),
    ("OptionsDQNConfig", "device unknown", lambda: OptionsDQNConfig(device="tpu"), ValueError, "device must be a device name"),
    ("OptionsDQNConfig", "parallel a string", lambda: OptionsDQNConfig(parallel="no"), TypeError, "parallel must be True or False"),
    ("OptionsDQNConfig", "double_dqn an int", lambda: OptionsDQNConfig(double_dqn=1), TypeError, "double_dqn must be True or False"),
    ("OptionsDQNConfig", "greedy_options an int", lambda: OptionsDQNConfig(greedy_options=1), TypeError,
     "greedy_options must be True or False"),
    ("OptionsDQNConfig", "intra_option_actions a string", lambda: OptionsDQNConfig(intra_option_actions="yes"), TypeError,
     "intra_option_actions must be True or False"),
    ("OptionsDQNConfig", "max_grad_norm a string", lambda: OptionsDQNConfig(max_grad_norm="1"), TypeError,
     "max_grad_norm must be None or a number > 0"),
    ("DQNHyperParameters", "frames_per_batch below num_envs", lambda: DQNHyperParameters(num_envs=4, frames_per_batch=2),
     ValueError, "frames_per_batch must be a multiple of the number of envs (num_envs=4)"),
    ("DQNHyperParameters", "control: the defaults", lambda: DQNHyperParameters(), OK, None),
    # ---- OptionsPPO / OptionsDQN construction
    ("OptionsPPO", "issue: an env instance where a factory is expected", lambda: ppo(env=Corridor(8)), TypeError,
     "env_factory must be a callable that makes an env (e.g. `lambda: GridWorldEnv(...)`), got an env instance (Corridor)"),
    ("OptionsDQN", "an env instance where a factory is expected", lambda: dqn(env=Corridor(8)), TypeError,
     "got an env instance (Corridor)"),
    ("OptionsPPO", "a factory that returns no env", lambda: ppo(env=lambda: 3), TypeError,
     "env_factory must return a torchrl EnvBase, it returned int"),
    ("OptionsDQN", "a factory that returns no env, batched", lambda: dqn(env=lambda: 3, config={"num_envs": 2}), TypeError,
     "env_factory must be a callable that returns a torchrl EnvBase"),
    ("OptionsPPO", "issue: mode='actions' with options (they would be ignored)",
     lambda: ppo(options=options(), num_options=2), ValueError, "mode='actions' learns over primitive actions only and would ignore the options"),
    ("OptionsDQN", "mode='actions' with options", lambda: dqn(options=options(), num_options=2), ValueError,
     "would ignore the options"),
    ("OptionsPPO", "mode='actions' with num_options only", lambda: ppo(num_options=2), ValueError, "would ignore the options"),
    ("OptionsPPO", "mode='both' without options", lambda: ppo(config={"mode": "both"}), ValueError, "needs `options` and `num_options`"),
    ("OptionsPPO", "num_options differs from the module's", lambda: ppo(config={"mode": "both"}, options=options(2), num_options=3),
     ValueError, "num_options=3 but the options module has num_options=2"),
    ("OptionsDQN", "num_options differs from the module's", lambda: dqn(config={"mode": "both"}, options=options(2), num_options=3),
     ValueError, "num_options=3 but the options module has num_options=2"),
    ("OptionsPPO", "options over another number of actions",
     lambda: ppo(config={"mode": "both"}, options=OptionsMLP(8, 5, 2), num_options=2), ValueError,
     "the options choose among num_actions=5 actions, but the env below the executor has 2"),
    ("OptionsPPO", "config of another type", lambda: OptionsPPO(corridor, OptionsDQNConfig()), TypeError,
     "config must be an OptionsPPOConfig"),
    ("OptionsPPO", "policy_network not a module", lambda: ppo(policy_network=3), TypeError, "policy_network must be a torch.nn.Module"),
    ("OptionsPPO", "value_network a function", lambda: ppo(value_network=lambda x: x), TypeError, "value_network must be a torch.nn.Module"),
    ("OptionsDQN", "q_network not a module", lambda: dqn(q_network=3), TypeError, "q_network must be a torch.nn.Module"),
    ("OptionsDQN", "an optimizer instance where a factory is expected",
     lambda: dqn(optimizer=torch.optim.Adam([nn.Parameter(torch.zeros(1))])), TypeError,
     "optimizer must be a factory called as optimizer(params, lr=config.lr)"),
    ("OptionsPPO", "observation_key the env does not have", lambda: ppo(config={"observation_key": "pixels"}), ValueError,
     "config.observation_key='pixels' is not an observation of the env"),
    ("OptionsDQN", "observation_key the env does not have", lambda: dqn(config={"observation_key": "pixels"}), ValueError,
     "is not an observation of the env"),
    ("OptionsPPO", "a natively batched env of 3 with frames_per_batch=10",
     lambda: ppo(env=lambda: Corridor(8, batch_size=[3]), config={"frames_per_batch": 10}), ValueError,
     "frames_per_batch must be a multiple of the number of envs (the env's batch size=3)"),
    ("OptionsDQN", "a natively batched env of 3 with frames_per_batch=10",
     lambda: dqn(env=lambda: Corridor(8, batch_size=[3]), config={"frames_per_batch": 10}), ValueError,
     "the env's batch size=3"),
    ("OptionsPPO", "control: options over actions and options", lambda: both(ppo), OK, None),
    ("OptionsDQN", "control: options over actions and options", lambda: both(dqn), OK, None),
    # ---- the budget is exact once the batches are
    ("OptionsPPO.train", "control: 2 envs, 8-frame batches: 16 frames for total_frames=16",
     trained_frames_are(lambda: ppo(config={"num_envs": 2}), 16, 16), OK, None),
    ("OptionsDQN.train", "control: a batched env of 2, 8-frame batches: 16 frames for total_frames=16",
     trained_frames_are(lambda: dqn(env=lambda: Corridor(8, batch_size=[2])), 16, 16), OK, None),
    # ---- train / evaluate / update arguments
    ("OptionsPPO.train", "issue: total_frames a string", lambda: ppo().train(total_frames="16"), TypeError,
     "total_frames must be an int or None, got '16' (str)"),
    ("OptionsPPO.train", "total_frames negative", lambda: ppo().train(total_frames=-5), ValueError, "total_frames must be an int >= 0"),
    ("OptionsPPO.train", "total_frames a float", lambda: ppo().train(total_frames=2.5), TypeError, "total_frames must be an int"),
    ("OptionsPPO.train", "total_frames NaN", lambda: ppo().train(total_frames=NAN), TypeError, "total_frames must be an int"),
    ("OptionsPPO.train", "callback not callable", lambda: ppo().train(total_frames=8, callback=3), TypeError,
     "callback must be a callable or None"),
    ("OptionsDQN.train", "total_frames a string", lambda: dqn().train(total_frames="16"), TypeError, "total_frames must be an int or None"),
    ("OptionsDQN.train", "callback not callable", lambda: dqn().train(total_frames=8, callback=3), TypeError,
     "callback must be a callable or None"),
    ("OptionsPPO.evaluate", "num_episodes 0", lambda: ppo().evaluate(num_episodes=0), ValueError, "num_episodes must be an int >= 1"),
    ("OptionsPPO.evaluate", "num_episodes a string", lambda: ppo().evaluate(num_episodes="2"), TypeError, "num_episodes must be an int"),
    ("OptionsDQN.evaluate", "max_steps negative", lambda: dqn().evaluate(max_steps=-1), ValueError, "max_steps must be an int >= 1"),
    ("OptionsDQN.record_evaluation", "num_episodes 0", lambda: dqn().record_evaluation(num_episodes=0), ValueError,
     "num_episodes must be an int >= 1"),
    ("OptionsPPO.update", "a list", lambda: ppo().update([1]), TypeError, "update expects a decision-level TensorDict of shape [M]"),
    ("OptionsPPO.update", "step-level [B, T] data",
     lambda: ppo().update(Corridor(8).rollout(3).unsqueeze(0)), TypeError, "of shape [1, 3]"),
    ("OptionsDQN.state_dict", "include_buffer a string", lambda: dqn().state_dict(include_buffer="yes"), TypeError,
     "include_buffer must be True or False"),
    ("OptionsPPO.state_dict", "include_buffer an int", lambda: ppo().state_dict(include_buffer=1), TypeError,
     "include_buffer must be True or False"),
    ("OptionsDQN.warm_start_from", "source not an agent", lambda: both(dqn).warm_start_from(3), TypeError,
     "source must be an OptionsDQN, got int"),
    ("OptionsDQN.warm_start_from", "copy_buffer a string", lambda: both(dqn).warm_start_from(dqn(), copy_buffer="no"),
     TypeError, "copy_buffer must be True or False"),
    # ---- load_state_dict: the whole checkpoint is checked before anything is restored
    ("OptionsPPO.load_state_dict", "a list", lambda: ppo().load_state_dict([1]), TypeError, "expected a dict from OptionsPPO.state_dict"),
    ("OptionsPPO.load_state_dict", "a DQN checkpoint", lambda: ppo().load_state_dict(dqn().state_dict()), ValueError,
     "not an OptionsPPO checkpoint"),
    ("OptionsDQN.load_state_dict", "a PPO checkpoint", lambda: dqn().load_state_dict(ppo().state_dict()), ValueError,
     "not an OptionsDQN checkpoint"),
    ("OptionsPPO.load_state_dict", "frames a string", state_with(ppo, frames="x"), ValueError, "'frames' must be an int >= 0, got 'x'"),
    ("OptionsDQN.load_state_dict", "gradient_steps negative", state_with(dqn, gradient_steps=-1), ValueError,
     "'gradient_steps' must be an int >= 0"),
    ("OptionsPPO.load_state_dict", "a log with an unknown field", state_with(ppo, log={"bogus": [1]}), ValueError,
     "'log' must be a dict of lists"),
    ("OptionsDQN.load_state_dict", "a log that is not a dict", state_with(dqn, log=3), ValueError, "'log' must be a dict of lists"),
    ("OptionsPPO.load_state_dict", "a random state without torch's", state_with(ppo, rng={"numpy": 1}), ValueError,
     "'rng' must hold the 'torch', 'numpy' and 'python' random states"),
    ("OptionsPPO.load_state_dict", "optimizer state of another model",
     state_with(ppo, optimizer={"state": {}, "param_groups": []}), ValueError, "the checkpoint's optimizer state does not fit"),
    ("OptionsPPO.load_state_dict", "a refused optimizer leaves the networks as they were",
     loads_and_is_unchanged(ppo, optimizer={"state": {}, "param_groups": []}), OK, None),
    ("OptionsDQN.load_state_dict", "a refused exploration state leaves the networks as they were",
     loads_and_is_unchanged(dqn, exploration={"bogus": torch.zeros(1)}), OK, None),
    ("OptionsPPO.load_state_dict", "other hidden sizes", lambda: ppo().load_state_dict(ppo(config={"hidden_sizes": (3,)}).state_dict()),
     ValueError, "the checkpoint's networks do not fit"),
    ("OptionsPPO.load_state_dict", "control: its own state", state_with(ppo), OK, None),
    # ---- widen_action_rows / widen_action_values
    ("widen_action_rows", "num_actions 0", lambda: widen_action_rows({}, {}, 0), ValueError, "num_actions must be an int >= 1"),
    ("widen_action_rows", "not state dicts", lambda: widen_action_rows(3, {}, 2), TypeError, "source must be a state dict"),
    ("widen_action_values", "num_outputs 0", lambda: widen_action_values(TensorDictLike(), 0), ValueError,
     "num_outputs must be an int >= 1"),
    ("widen_action_values", "not a TensorDict", lambda: widen_action_values({"action_value": 1}, 3), TypeError,
     "data must be a TensorDict"),
    ("widen_action_values", "control: data without the key", lambda: widen_action_values(TensorDictLike(), 3), OK, None),
    ("TrainingLog", "control: empty log", lambda: TrainingLog(), OK, None),
]  # fmt: skip


def TensorDictLike():
    from tensordict import TensorDict

    return TensorDict({}, [2])


FILES = [
    ("OptionsPPO.load", "issue: an options file (the message names the file)", file_call(_options_file, lambda p: ppo().load(p)),
     ValueError, "options.pt: not an OptionsPPO checkpoint: this is an options file written by save_options"),
    ("OptionsDQN.load", "an options file", file_call(_options_file, lambda p: dqn().load(p)), ValueError,
     "options.pt: not an OptionsDQN checkpoint: this is an options file"),
    ("OptionsPPO.load", "a DQN checkpoint", file_call(_dqn_file, lambda p: ppo().load(p)), ValueError,
     "dqn.pt: not an OptionsPPO checkpoint"),
    ("OptionsDQN.load", "a PPO checkpoint", file_call(_ppo_file, lambda p: dqn().load(p)), ValueError,
     "ppo.pt: not an OptionsDQN checkpoint"),
    ("OptionsPPO.load", "a checkpoint of another mode", file_call(_ppo_file, lambda p: both(ppo).load(p)), ValueError,
     "ppo.pt: the checkpoint is of mode='actions', this agent has mode='both'"),
    ("OptionsPPO.load", "a directory (cosmetic: 'an OptionsPPO checkpoint file')", file_call(lambda t: t, lambda p: ppo().load(p)),
     ValueError, "expected an OptionsPPO checkpoint file, got a directory"),
    ("OptionsPPO.load", "a missing file", file_call(lambda t: t / "nope.pt", lambda p: ppo().load(p)), FileNotFoundError,
     "nope.pt: no such OptionsPPO checkpoint file"),
    ("OptionsPPO.load", "a path of another type", file_call(lambda t: 3, lambda p: ppo().load(p)), TypeError,
     "path must be a str or a path"),
    ("OptionsPPO.load", "control: its own checkpoint", file_call(_ppo_file, lambda p: ppo().load(p)), OK, None),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_agents_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)


@pytest.mark.parametrize("api, case, call, error, phrase", FILES, ids=ids(FILES))
def test_agent_files(tmp_path, api, case, call, error, phrase):
    check(call, error, phrase, tmp_path)


def test_rounded_budget_is_documented_and_whole_batches():
    """total_frames not a multiple of frames_per_batch: rounded up to whole batches (one PPO update each), as
    documented; with batches the envs fill, never more than one batch over."""
    assert frames_after(lambda: ppo(config={"num_envs": 2}), 20) == 24
    assert frames_after(lambda: dqn(config={"num_envs": 2}), 17) == 24
