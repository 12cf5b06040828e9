"""Intra-option transitions: hand-computed rows, bad input, and the invariants of real collector batches."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector

from _tiny_envs import RIGHT, Corridor, checkpoint_options
from torchrl_options.data import SMDPTransitions, intra_option_transitions
from torchrl_options.transforms import OptionExecutor

pytestmark = pytest.mark.usefixtures("torch_single_thread")


def two_envs():
    """[2, 4] steps. Env 0: primitive 1, option 0 for two steps, primitive 0. Env 1: option 1 for all four steps
    (its first step is the decision). A = 2 primitive actions, so the augmented actions of options are 2 and 3."""
    return TensorDict(
        {
            "observation": torch.arange(8.0).reshape(2, 4),
            "action": torch.tensor([[1, 2, 3, 0], [3, 0, 1, 1]]),  # the policy's (ignored inside an option)
            "next": {
                "observation": torch.arange(1.0, 9.0).reshape(2, 4),
                "reward": torch.arange(8.0).reshape(2, 4, 1) / 10,
                "done": torch.tensor([[False, False, False, True], [False, True, False, False]]).unsqueeze(-1),
                "executed_action": torch.tensor([[1, 0, 0, 0], [1, 1, 0, 1]]),
                "executed_option": torch.tensor([[-1, 0, 0, -1], [1, 1, 1, 1]]),
                "option_decision": torch.tensor([[True, True, False, True], [True, False, True, False]]),
            },
        },
        [2, 4],
    )


def test_hand_computed_rows():
    out = intra_option_transitions(two_envs(), num_actions=2)
    # env 0's steps 1, 2 and all of env 1's, in env then time order
    assert out.shape == (6,)
    torch.testing.assert_close(out["observation"], torch.tensor([1.0, 2.0, 4.0, 5.0, 6.0, 7.0]))
    torch.testing.assert_close(out["action"], torch.tensor([0, 0, 1, 1, 0, 1]))  # the executed primitive actions
    torch.testing.assert_close(out["next", "observation"], torch.tensor([2.0, 3.0, 5.0, 6.0, 7.0, 8.0]))
    torch.testing.assert_close(out["next", "reward"], torch.tensor([[0.1], [0.2], [0.4], [0.5], [0.6], [0.7]]))
    torch.testing.assert_close(out["next", "done"].reshape(-1), torch.tensor([False, False, False, True, False, False]))
    assert out["steps_to_next_obs"].shape == (6, 1) and (out["steps_to_next_obs"] == 1).all()
    # the input is not modified
    assert two_envs()["action"].tolist() == [[1, 2, 3, 0], [3, 0, 1, 1]]


def test_custom_keys_and_no_option_steps():
    data = two_envs()
    data.rename_key_(("next", "executed_option"), ("next", "opt"))
    data.rename_key_("action", "act")
    out = intra_option_transitions(data, executed_option_key=("next", "opt"), action_key="act", steps_key="k")
    assert out["act"].tolist() == [0, 0, 1, 1, 0, 1] and (out["k"] == 1).all()
    data["next", "opt"] = torch.full((2, 4), -1)
    empty = intra_option_transitions(data, executed_option_key=("next", "opt"), action_key="act")
    assert empty.shape == (0,) and empty["steps_to_next_obs"].shape == (0, 1)


def test_bad_input():
    with pytest.raises(ValueError, match=r"executed_action.*\[0, 2\).*\[0, 5\]"):
        data = two_envs()
        data["next", "executed_action"][1, 2] = 5
        intra_option_transitions(data, num_actions=2)
    with pytest.raises(KeyError, match="executed_option"):
        intra_option_transitions(two_envs().exclude(("next", "executed_option")))
    with pytest.raises(KeyError, match="executed_action"):
        intra_option_transitions(two_envs().exclude(("next", "executed_action")))
    with pytest.raises(ValueError, match="time dimension"):
        intra_option_transitions(two_envs()[0, 0])
    with pytest.raises(ValueError, match="one .*executed_option.* per step"):
        data = two_envs()
        data["next", "executed_option"] = torch.zeros(2, 4, 3, dtype=torch.long)
        intra_option_transitions(data)


def test_collector_batches_with_executor():
    """Real batches: one transition per step an option controlled (first steps included), each carrying the action
    the env really received and a move of one cell; with the SMDP decisions they account for every option step."""
    torch.manual_seed(0)
    length = 10
    env = Corridor(length, max_steps=12, batch_size=[3]).append_transform(
        OptionExecutor(checkpoint_options(length), 2)
    )
    collector = Collector(env, None, frames_per_batch=36, total_frames=180)
    collector.set_seed(0)
    smdp = SMDPTransitions(0.9)
    option_steps_in_decisions, intra_total, controlled = 0, 0, 0
    for batch in collector:
        out = intra_option_transitions(batch, num_actions=2)
        controlled += int((batch["next", "executed_option"] >= 0).sum())
        intra_total += out.shape[0]
        assert (out["action"] == out["next", "received_action"]).all()  # what the env got
        move = torch.where(out["action"] == RIGHT, 1, -1).unsqueeze(-1)
        assert (out["next", "position"] == (out["position"] + move).clamp(0, length - 1)).all()
        assert (out["steps_to_next_obs"] == 1).all()
        decisions = smdp(batch)
        is_option = decisions["action"] >= 2
        option_steps_in_decisions += int(decisions["steps_to_next_obs"][is_option].sum())
    collector.shutdown()
    assert intra_total == controlled > 0
    # the option runs still pending at the end are the rest (a primitive decision lasts one step and never pends)
    pending = int(smdp._carry.steps[smdp._carry.valid & (smdp._carry.td["action"] >= 2)].sum())
    assert option_steps_in_decisions + pending == intra_total
