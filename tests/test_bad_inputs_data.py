"""Bad inputs of torchrl_options.data (issue 53): decision-level batches for PPO, SMDP transitions for DQN and the
intra-option transitions refuse colliding keys when they are set, refuse a change of batch layout while decisions
are carried over (instead of dropping them with a warning), and name what is missing. One row per case, controls
(inputs that must be accepted) included."""
import pytest
import torch
from tensordict import TensorDict

from _bad_inputs import check, ids, OK
from torchrl_options.data import (
    intra_option_transitions,
    OnPolicyDecisions,
    option_suffix_transitions,
    smdp_transitions,
    SMDPTransform,
    SMDPTransitions,
)

NAN = float("nan")


def steps(n_env: int = 2, T: int = 4, done: bool = True) -> TensorDict:
    """Step-level data of ``n_env`` envs: a decision at t = 0 and 2 (an option over t = 0, 1), nothing ends."""
    nxt = {
        "observation": torch.zeros(n_env, T, 1),
        "reward": torch.ones(n_env, T, 1),
        "terminated": torch.zeros(n_env, T, 1, dtype=torch.bool),
        "option_decision": torch.tensor([t % 2 == 0 for t in range(T)]).expand(n_env, T).clone(),
        "executed_option": torch.tensor([0, 0] + [-1] * (T - 2)).expand(n_env, T).clone(),
        "executed_action": torch.zeros(n_env, T, dtype=torch.long),
    }
    if done:
        nxt["done"] = torch.zeros(n_env, T, 1, dtype=torch.bool)
    return TensorDict(
        {"observation": torch.zeros(n_env, T, 1), "action": torch.zeros(n_env, T, dtype=torch.long),
         "action_log_prob": torch.zeros(n_env, T), "next": nxt},
        [n_env, T],
    )  # fmt: skip


def two_batches(make, first, second):
    def call():
        component = make()
        component(first())
        return component(second())

    return call


def with_entry(td, key, value):
    td = td.clone()
    td.set(key, value)
    return td


def _one_decision_then_batch(make, second):
    """A first batch whose decision is still running at its end, then ``second``."""

    def call():
        component = make()
        first = steps(2, 3)
        first["next", "option_decision"] = torch.tensor([True, False, False]).expand(2, 3).clone()
        component(first)
        assert component.num_pending == 2
        return component(second())

    return call


OPD = OnPolicyDecisions
CASES = [
    # ---- OnPolicyDecisions: colliding keys (each would overwrite an entry the component reads or writes)
    ("OnPolicyDecisions", "issue: steps_key=('next', 'reward') overwrites the summed rewards",
     lambda: OPD(0.9, steps_key=("next", "reward")), ValueError, "reward_key and steps_key are both ('next', 'reward')"),
    ("OnPolicyDecisions", "issue: end_of_batch_key=('next', 'terminated') turns cuts into terminations",
     lambda: OPD(0.9, end_of_batch_key=("next", "terminated")), ValueError,
     "terminated_key and end_of_batch_key are both ('next', 'terminated')"),
    ("OnPolicyDecisions", "done_key equal to terminated_key", lambda: OPD(0.9, done_key=("next", "terminated")),
     ValueError, "done_key and terminated_key are both"),
    ("OnPolicyDecisions", "truncated_key equal to end_of_batch_key", lambda: OPD(0.9, truncated_key=("next", "end_of_batch")),
     ValueError, "truncated_key and end_of_batch_key are both"),
    ("OnPolicyDecisions", "steps_key equal to decision_key", lambda: OPD(0.9, steps_key=("next", "option_decision")),
     ValueError, "decision_key and steps_key are both"),
    ("OnPolicyDecisions", "a nested key spelled two ways is one key", lambda: OPD(0.9, steps_key=("next", ("reward",))),
     ValueError, "reward_key and steps_key are both"),
    ("OnPolicyDecisions", "decision_key not a NestedKey", lambda: OPD(0.9, decision_key=3), TypeError,
     "decision_key must be a NestedKey"),
    ("OnPolicyDecisions", "steps_key an empty tuple", lambda: OPD(0.9, steps_key=()), TypeError, "steps_key must be a NestedKey"),
    ("OnPolicyDecisions", "control: decision_key=None and default keys", lambda: OPD(0.9, decision_key=None), OK, None),
    ("OnPolicyDecisions", "control: other distinct keys", lambda: OPD(0.9, steps_key="k", end_of_batch_key="cut")(steps()), OK, None),
    ("OnPolicyDecisions", "gamma above 1", lambda: OPD(1.5), ValueError, "gamma must be a number in [0, 1]"),
    ("OnPolicyDecisions", "gamma NaN", lambda: OPD(NAN), ValueError, "gamma must be a number in [0, 1]"),
    ("OnPolicyDecisions", "gamma a string", lambda: OPD("0.9"), TypeError, "gamma must be a number"),
    ("OnPolicyDecisions", "control: gamma 0 and 1", lambda: (OPD(0.0), OPD(1)), OK, None),
    # ---- OnPolicyDecisions: the data
    ("OnPolicyDecisions", "issue: a batch without ('next', 'done')", lambda: OPD(0.9)(steps(done=False)), ValueError,
     "data has no ('next', 'done') entry (done_key)"),
    ("OnPolicyDecisions", "a batch without the reward", lambda: OPD(0.9)(steps().exclude(("next", "reward"))),
     ValueError, "no ('next', 'reward') entry (reward_key)"),
    ("OnPolicyDecisions", "every step a decision, no reward", lambda: OPD(0.9, decision_key=None)(steps().exclude(("next", "reward"))),
     ValueError, "no ('next', 'reward') entry (reward_key)"),
    ("OnPolicyDecisions", "no decision record", lambda: OPD(0.9)(steps().exclude(("next", "option_decision"))),
     ValueError, "no ('next', 'option_decision') entry (decision_key)"),
    ("OnPolicyDecisions", "not a TensorDict", lambda: OPD(0.9)([1, 2]), TypeError, "expects a TensorDict"),
    ("OnPolicyDecisions", "no time dimension", lambda: OPD(0.9)(steps()[0, 0]), ValueError, "time dimension"),
    ("OnPolicyDecisions", "zero steps", lambda: OPD(0.9)(steps()[:, :0]), ValueError, "at least one step"),
    ("OnPolicyDecisions", "a decision flag per step of the wrong shape",
     lambda: OPD(0.9)(with_entry(steps(), ("next", "option_decision"), torch.ones(2, 4, 3, dtype=torch.bool))),
     ValueError, "per step"),
    ("OnPolicyDecisions", "the data already holds steps_key (it would be overwritten)",
     lambda: OPD(0.9)(with_entry(steps(), "steps_to_next_obs", torch.ones(2, 4, 1, dtype=torch.long))), ValueError,
     "already holds a 'steps_to_next_obs' entry (steps_key)"),
    ("OnPolicyDecisions", "the data already holds end_of_batch_key",
     lambda: OPD(0.9)(with_entry(steps(), ("next", "end_of_batch"), torch.zeros(2, 4, 1, dtype=torch.bool))), ValueError,
     "already holds a ('next', 'end_of_batch') entry (end_of_batch_key)"),
    ("OnPolicyDecisions", "control: a [T] batch of one env", lambda: OPD(0.9)(steps()[0]), OK, None),
    ("OnPolicyDecisions", "control: no terminated entry (taken from done)",
     lambda: OPD(0.9)(steps().exclude(("next", "terminated"))), OK, None),
    # ---- OnPolicyDecisions / SMDPTransitions: a change of batch layout mid-stream
    ("OnPolicyDecisions", "issue: 2 envs then 3 envs (the carried decisions would be lost)",
     _one_decision_then_batch(lambda: OPD(0.9), lambda: steps(3)), ValueError,
     "the batch has envs of shape [3] (leading dims), the previous batch [2], while 2 decision(s)"),
    ("OnPolicyDecisions", "[2, 3] envs then [3, 2] envs (same count, another layout)",
     two_batches(lambda: OPD(0.9), lambda: steps(6, 3).reshape(2, 3, 3), lambda: steps(6, 3).reshape(3, 2, 3)),
     ValueError, "has envs of shape [3, 2]"),
    ("OnPolicyDecisions", "a batch with other entries than the previous one",
     _one_decision_then_batch(lambda: OPD(0.9), lambda: steps(2).exclude("action_log_prob")), ValueError,
     "has other entries than the previous batch (missing ['action_log_prob']"),
    ("OnPolicyDecisions", "control: 2 envs, reset(), then 3 envs",
     lambda: (lambda d: (d(steps(2, 3)), d.reset(), d(steps(3))))(OPD(0.9)), OK, None),
    ("OnPolicyDecisions", "control: 2 envs twice", two_batches(lambda: OPD(0.9), steps, steps), OK, None),
    ("SMDPTransitions", "2 envs then 3 envs (the carried decisions would be lost)",
     _one_decision_then_batch(lambda: SMDPTransitions(0.9), lambda: steps(3)), ValueError,
     "SMDPTransitions: the batch has envs of shape [3]"),
    ("SMDPTransitions", "control: 2 envs, reset(), then 3 envs",
     lambda: (lambda d: (d(steps(2, 3)), d.reset(), d(steps(3))))(SMDPTransitions(0.9)), OK, None),
    # ---- SMDPTransitions / smdp_transitions: keys
    ("SMDPTransitions", "issue: steps_key=('next', 'reward') overwrites the summed rewards",
     lambda: SMDPTransitions(0.9, steps_key=("next", "reward")), ValueError,
     "SMDPTransitions: reward_key and steps_key are both ('next', 'reward')"),
    ("SMDPTransitions", "reward_key equal to done_key", lambda: SMDPTransitions(0.9, reward_key=("next", "done")),
     ValueError, "reward_key and done_key are both"),
    ("SMDPTransitions", "decision_key equal to steps_key", lambda: SMDPTransitions(0.9, decision_key="steps_to_next_obs"),
     ValueError, "decision_key and steps_key are both"),
    ("SMDPTransitions", "duration_key equal to steps_key",
     lambda: SMDPTransitions(0.9, discount_per="decision", duration_key="steps_to_next_obs"), ValueError,
     "duration_key and steps_key are both"),
    ("SMDPTransitions", "discount_per unknown", lambda: SMDPTransitions(0.9, discount_per="option"), ValueError,
     "discount_per must be 'step' or 'decision'"),
    ("SMDPTransitions", "the data already holds the duration key (per decision)",
     lambda: SMDPTransitions(0.9, discount_per="decision")(with_entry(steps(), "decision_steps", torch.ones(2, 4, 1))),
     ValueError, "already holds a 'decision_steps' entry (duration_key)"),
    ("SMDPTransitions", "control: a duration entry is only read per decision",
     lambda: SMDPTransitions(0.9)(with_entry(steps(), "decision_steps", torch.ones(2, 4, 1))), OK, None),
    ("smdp_transitions", "steps_key=('next', 'reward')", lambda: smdp_transitions(steps(), 0.9, steps_key=("next", "reward")),
     ValueError, "smdp_transitions: reward_key and steps_key are both"),
    ("smdp_transitions", "gamma above 1", lambda: smdp_transitions(steps(), 2.0), ValueError, "gamma must be a number in [0, 1]"),
    ("smdp_transitions", "not a TensorDict", lambda: smdp_transitions({"next": {}}, 0.9), TypeError, "expects a TensorDict"),
    ("smdp_transitions", "the data already holds steps_key",
     lambda: smdp_transitions(with_entry(steps(), "steps_to_next_obs", torch.ones(2, 4, 1)), 0.9), ValueError,
     "already holds a 'steps_to_next_obs' entry"),
    ("smdp_transitions", "control: default keys", lambda: smdp_transitions(steps(), 0.9), OK, None),
    # ---- SMDPTransform
    ("SMDPTransform", "marker_key equal to action_key", lambda: SMDPTransform(0.9, marker_key="action"), ValueError,
     "SMDPTransform: marker_key and action_key are both 'action'"),
    ("SMDPTransform", "marker_key equal to steps_key", lambda: SMDPTransform(0.9, marker_key="steps_to_next_obs"),
     ValueError, "marker_key and steps_key are both"),
    ("SMDPTransform", "executed_action_key equal to reward_key",
     lambda: SMDPTransform(0.9, executed_action_key=("next", "reward")), ValueError,
     "reward_key and executed_action_key are both"),
    ("SMDPTransform", "steps_key=('next', 'reward')", lambda: SMDPTransform(0.9, steps_key=("next", "reward")),
     ValueError, "reward_key and steps_key are both"),
    ("SMDPTransform", "a flag that is not a bool", lambda: SMDPTransform(0.9, option_suffixes=1), TypeError,
     "option_suffixes must be True or False"),
    ("SMDPTransform", "num_actions a float", lambda: SMDPTransform(0.9, num_actions=2.0), TypeError,
     "num_actions must be an int or None"),
    ("SMDPTransform", "control: intra-option transitions with their defaults",
     lambda: SMDPTransform(0.9, intra_option_actions=True, num_actions=2), OK, None),
    # ---- intra_option_transitions / option_suffix_transitions
    ("intra_option_transitions", "steps_key=('next', 'reward')",
     lambda: intra_option_transitions(steps(), steps_key=("next", "reward")), ValueError, "reward_key and steps_key are both"),
    ("intra_option_transitions", "action_key equal to executed_option_key",
     lambda: intra_option_transitions(steps(), action_key=("next", "executed_option")), ValueError,
     "action_key and executed_option_key are both"),
    ("intra_option_transitions", "num_actions negative", lambda: intra_option_transitions(steps(), num_actions=-1),
     ValueError, "num_actions must be an int >= 1"),
    ("intra_option_transitions", "num_actions a string", lambda: intra_option_transitions(steps(), num_actions="2"),
     TypeError, "num_actions must be an int or None"),
    ("intra_option_transitions", "not a TensorDict", lambda: intra_option_transitions([1]), TypeError, "expects a TensorDict"),
    ("intra_option_transitions", "no reward", lambda: intra_option_transitions(steps().exclude(("next", "reward"))),
     ValueError, "no ('next', 'reward') entry (reward_key)"),
    ("intra_option_transitions", "no executed option", lambda: intra_option_transitions(steps().exclude(("next", "executed_option"))),
     ValueError, "no ('next', 'executed_option') entry"),
    ("intra_option_transitions", "control: num_actions given", lambda: intra_option_transitions(steps(), num_actions=2), OK, None),
    ("option_suffix_transitions", "steps_key=('next', 'reward')",
     lambda: option_suffix_transitions(steps(), 0.9, action_offset=2, steps_key=("next", "reward")), ValueError,
     "reward_key and steps_key are both"),
    ("option_suffix_transitions", "decision_key equal to done_key",
     lambda: option_suffix_transitions(steps(), 0.9, action_offset=2, decision_key=("next", "done")), ValueError,
     "decision_key and done_key are both"),
    ("option_suffix_transitions", "action_offset negative", lambda: option_suffix_transitions(steps(), 0.9, action_offset=-1),
     ValueError, "action_offset must be an int >= 0"),
    ("option_suffix_transitions", "action_offset a float", lambda: option_suffix_transitions(steps(), 0.9, action_offset=1.5),
     TypeError, "action_offset must be an int"),
    ("option_suffix_transitions", "gamma NaN", lambda: option_suffix_transitions(steps(), NAN, action_offset=2), ValueError,
     "gamma must be a number in [0, 1]"),
    ("option_suffix_transitions", "not a TensorDict", lambda: option_suffix_transitions([1], 0.9, action_offset=2),
     TypeError, "expects a TensorDict"),
    ("option_suffix_transitions", "control: options only (offset 0)",
     lambda: option_suffix_transitions(steps(), 0.9, action_offset=0), OK, None),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_data_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)


def test_layout_change_keeps_the_carried_decisions():
    """After the refused batch the running decisions are still there: the right batch completes them."""
    decisions = OnPolicyDecisions(0.5)
    first = steps(2, 3)
    first["next", "option_decision"] = torch.tensor([True, False, False]).expand(2, 3).clone()
    assert decisions(first).shape[0] == 0 and decisions.num_pending == 2
    with pytest.raises(ValueError, match="would be lost"):
        decisions(steps(3))
    assert decisions.num_pending == 2
    second = steps(2, 2)
    second["next", "option_decision"] = torch.tensor([True, False]).expand(2, 2).clone()
    out = decisions(second)
    # each env's 3-step decision (1 + 0.5 + 0.25) comes out first
    assert out["steps_to_next_obs"].reshape(-1).tolist()[:1] == [3]
    assert out["next", "reward"].reshape(-1)[0].item() == pytest.approx(1.75)
