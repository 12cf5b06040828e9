"""Bad inputs of torchrl_options.modules, .transforms and .objectives (issue 53): sizes of the wrong type, outputs
written over inputs, an input of another width or device (a "meta" tensor stands in for a GPU one), executors and
counters whose keys collide or whose options do not fit. One row per case, controls included."""
import pytest
import torch
from tensordict import TensorDict

from _bad_inputs import check, ids, OK
from _tiny_envs import Corridor
from torchrl_options import DDOLoss, GaussianOptionsMLP, MetaControlMLP, OptionsMLP, UniformMetaControl
from torchrl_options.modules import GridConvOptions, OneHotByteOptions
from torchrl_options.objectives import guard_decision_level, is_step_level_option_data, option_log_probs
from torchrl_options.transforms import DecisionCounter, OptionExecutor

NAN = float("nan")


def obs(n=4, d=2, device="cpu"):
    return TensorDict({"observation": torch.zeros(n, d, device=device)}, [n])


CASES = [
    # ---- modules
    ("GridConvOptions", "num_actions a float", lambda: GridConvOptions(7.0, 2), TypeError, "num_actions must be an int"),
    ("GridConvOptions", "num_options 0", lambda: GridConvOptions(7, 0), ValueError, "num_options must be an int >= 1"),
    ("GridConvOptions", "an unknown architecture", lambda: GridConvOptions(7, 2, architecture="tied"), ValueError,
     "architecture must be one of ('separate', 'shared')"),
    ("GridConvOptions", "an input of another width", lambda: GridConvOptions(7, 2)(obs(d=10)), ValueError,
     "GridConvOptions expects 984 features (20 x 7 x 7 grid + 4) in ['observation'], got 10"),
    ("OptionsMLP", "in_features a float", lambda: OptionsMLP(2.0, 3, 2), TypeError, "in_features must be an int"),
    ("OptionsMLP", "num_options 0", lambda: OptionsMLP(2, 3, 0), ValueError, "num_options must be a positive int"),
    ("OptionsMLP", "two outputs on one entry", lambda: OptionsMLP(2, 3, 2, out_keys=["x", "x"]), ValueError,
     "out_keys[0] and out_keys[1] are both 'x'"),
    ("OptionsMLP", "an output written over its input", lambda: OptionsMLP(2, 3, 2, in_keys=["option_logits"]), ValueError,
     "out_keys[0] and in_keys[0] are both 'option_logits'"),
    ("OptionsMLP", "in_keys not keys", lambda: OptionsMLP(2, 3, 2, in_keys=[3]), TypeError, "in_keys[0] must be a NestedKey"),
    ("OptionsMLP", "an input of another width", lambda: OptionsMLP(2, 3, 2)(obs(d=5)), ValueError,
     "OptionsMLP was built for in_features=2, got 5 features"),
    ("OptionsMLP", "an input on another device", lambda: OptionsMLP(2, 3, 2)(obs(device="meta")), ValueError,
     "the input ['observation'] is on device meta, the module's parameters on cpu"),
    ("OptionsMLP", "control: two inputs concatenated", lambda: OptionsMLP(3, 3, 2, in_keys=["a", "b"])(
        TensorDict({"a": torch.zeros(4, 2), "b": torch.zeros(4, 1)}, [4])), OK, None),
    ("GaussianOptionsMLP", "init_scale NaN", lambda: GaussianOptionsMLP(2, 3, 2, init_scale=NAN), ValueError,
     "init_scale must be a number > 0"),
    ("GaussianOptionsMLP", "min_scale negative", lambda: GaussianOptionsMLP(2, 3, 2, min_scale=-1.0), ValueError,
     "min_scale must be a number > 0"),
    ("GaussianOptionsMLP", "state_dependent_scale an int", lambda: GaussianOptionsMLP(2, 3, 2, state_dependent_scale=1), TypeError,
     "state_dependent_scale must be True or False"),
    ("GaussianOptionsMLP", "an input of another width", lambda: GaussianOptionsMLP(2, 1, 2)(obs(d=3)), ValueError,
     "built for in_features=2, got 3"),
    ("GaussianOptionsMLP", "control: defaults", lambda: GaussianOptionsMLP(2, 1, 2)(obs()), OK, None),
    ("MetaControlMLP", "num_options a string", lambda: MetaControlMLP(2, "2"), TypeError, "num_options must be an int"),
    ("MetaControlMLP", "out_key equal to its input", lambda: MetaControlMLP(2, 2, out_key="observation"), ValueError,
     "out_keys[0] and in_keys[0] are both 'observation'"),
    ("MetaControlMLP", "an input of another width", lambda: MetaControlMLP(2, 2)(obs(d=4)), ValueError, "built for in_features=2, got 4"),
    ("UniformMetaControl", "num_options True", lambda: UniformMetaControl(True), TypeError, "num_options must be an int"),
    ("UniformMetaControl", "num_options 0", lambda: UniformMetaControl(0), ValueError, "num_options must be a positive int"),
    ("UniformMetaControl", "control: any width", lambda: UniformMetaControl(3)(obs(d=7)), OK, None),
    ("OneHotByteOptions", "num_bytes 0", lambda: OneHotByteOptions(0, 3, 2), ValueError, "num_bytes must be an int >= 1"),
    ("OneHotByteOptions", "value_scale 0", lambda: OneHotByteOptions(4, 3, 2, value_scale=0.0), ValueError, "value_scale must be a positive finite number"),
    ("OneHotByteOptions", "an output over its input", lambda: OneHotByteOptions(4, 3, 2, out_keys=["observation", "t"]), ValueError,
     "out_keys[0] and in_keys[0] are both 'observation'"),
    ("OneHotByteOptions", "observations that are not bytes", lambda: OneHotByteOptions(4, 3, 2)(obs(d=4).apply(lambda x: x + 0.5)),
     ValueError, "must hold bytes"),
    # ---- transforms
    ("OptionExecutor", "num_options differs from the module's", lambda: OptionExecutor(OptionsMLP(8, 2, 2), 3), ValueError,
     "num_options=3 but the options module has num_options=2"),
    ("OptionExecutor", "action_key equal to done_key", lambda: OptionExecutor(OptionsMLP(8, 2, 2), 2, action_key="done"), ValueError,
     "action_key and done_key are both 'done'"),
    ("OptionExecutor", "a record written over the action", lambda: OptionExecutor(OptionsMLP(8, 2, 2), 2, option_key="action"),
     ValueError, "option_key and action_key are both 'action'"),
    ("OptionExecutor", "a record over the options' output",
     lambda: OptionExecutor(OptionsMLP(8, 2, 2), 2, decision_key="option_logits"), ValueError,
     "decision_key and option_logits_key are both 'option_logits'"),
    ("OptionExecutor", "options over another number of actions than the env's",
     lambda: Corridor(8).append_transform(OptionExecutor(OptionsMLP(8, 5, 2, in_keys=["observation"]), 2)), ValueError,
     "the options choose among num_actions=5 actions, but the env below the executor has 2"),
    ("OptionExecutor", "options for another observation width, at the first step",
     lambda: Corridor(8).append_transform(OptionExecutor(OptionsMLP(3, 2, 2, in_keys=["observation"]), 2)).rollout(2),
     ValueError, "the options module failed on the env's observations"),
    ("OptionExecutor", "num_options 0", lambda: OptionExecutor(OptionsMLP(8, 2, 2), 0), ValueError, "num_options must be a positive int"),
    ("OptionExecutor", "greedy a string", lambda: OptionExecutor(OptionsMLP(8, 2, 2), 2, greedy="yes"), TypeError, "greedy must be a bool"),
    ("OptionExecutor", "control: on the corridor",
     lambda: Corridor(8).append_transform(OptionExecutor(OptionsMLP(8, 2, 2, in_keys=["observation"]), 2)).rollout(2), OK, None),
    ("DecisionCounter", "count_key equal to done_key", lambda: DecisionCounter(3, count_key="done"), ValueError,
     "count_key and done_key are both 'done'"),
    ("DecisionCounter", "count_key over the decision record", lambda: DecisionCounter(3, count_key="option_decision"), ValueError,
     "count_key and decision_key are both 'option_decision'"),
    ("DecisionCounter", "max_decisions 0", lambda: DecisionCounter(0), ValueError, "max_decisions must be an int >= 1"),
    ("DecisionCounter", "max_decisions a float", lambda: DecisionCounter(2.0), ValueError, "max_decisions must be an int >= 1"),
    ("DecisionCounter", "control: every step a decision", lambda: DecisionCounter(3, level=None), OK, None),
    # ---- objectives
    ("DDOLoss", "options not a module", lambda: DDOLoss(3), TypeError, "options must be a TensorDictModuleBase"),
    ("DDOLoss", "reduction unknown", lambda: DDOLoss(OptionsMLP(2, 3, 2), reduction="max"), ValueError, "reduction must be"),
    ("DDOLoss", "meta_control of another K", lambda: DDOLoss(OptionsMLP(2, 3, 2), MetaControlMLP(2, 3)), ValueError,
     "options has num_options=2 but meta_control has num_options=3"),
    ("option_log_probs", "action_space unknown", lambda: option_log_probs(TensorDict({}, []), torch.zeros(2), action_space="x"),
     ValueError, "action_space must be"),
    ("guard_decision_level", "not a module", lambda: guard_decision_level(3), TypeError, "expects a loss module"),
    ("is_step_level_option_data", "not a TensorDict", lambda: is_step_level_option_data([1]), TypeError,
     "is_step_level_option_data expects a TensorDict"),
    ("is_step_level_option_data", "steps_key not a key", lambda: is_step_level_option_data(obs(), steps_key=3), TypeError,
     "steps_key must be a NestedKey"),
    ("is_step_level_option_data", "control: plain data", lambda: is_step_level_option_data(obs()), OK, None),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_modules_transforms_objectives_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)
