"""Intra-option transitions: hand-computed rows, bad input, and the invariants of real collector batches."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector

from _tiny_envs import RIGHT, Corridor, checkpoint_options
from torchrl_options.data import SMDPTransitions, intra_option_transitions, option_suffix_transitions
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
    with pytest.raises(ValueError, match="no .*executed_option.* entry"):
        intra_option_transitions(two_envs().exclude(("next", "executed_option")))
    with pytest.raises(ValueError, match="no .*executed_action.* entry"):
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


def random_runs(n_envs: int, T: int, num_options: int, seed: int):
    """Random step-level records obeying the executor's rules: a decision starts each episode and follows each run's
    end; a decision picks a primitive action (-1) or an option, which goes on for a random number of steps."""
    g = torch.Generator().manual_seed(seed)
    option = torch.full((n_envs, T), -1)
    decision = torch.zeros(n_envs, T, dtype=torch.bool)
    done = torch.rand(n_envs, T, generator=g) < 0.08
    for n in range(n_envs):
        running = int(torch.randint(-1, num_options, (1,), generator=g))  # the row may start inside a run
        for t in range(T):
            if running < 0 or (t > 0 and done[n, t - 1]) or torch.rand(1, generator=g) < 0.3:
                decision[n, t] = t > 0 or running < 0 or bool(torch.rand(1, generator=g) < 0.5)
                if decision[n, t]:
                    running = int(torch.randint(-1, num_options, (1,), generator=g))
            option[n, t] = running
            if running < 0:  # a primitive action lasts one step
                running = -1
    return TensorDict(
        {
            "observation": torch.arange(n_envs * T, dtype=torch.float).reshape(n_envs, T),
            "action": torch.zeros(n_envs, T, dtype=torch.long),
            "next": {
                "observation": torch.arange(1, n_envs * T + 1, dtype=torch.float).reshape(n_envs, T),
                "reward": torch.rand(n_envs, T, 1, generator=g),
                "done": done.unsqueeze(-1),
                "executed_option": option,
                "option_decision": decision,
            },
        },
        [n_envs, T],
    )


def suffix_reference(data: TensorDict, gamma: float):
    """Step by step: (observation, augmented action, discounted return, k, next observation) of every suffix."""
    out = []
    for row in data.unbind(0):
        opt, dec = row["next", "executed_option"].tolist(), row["next", "option_decision"].tolist()
        done, rew = row["next", "done"].reshape(-1).tolist(), row["next", "reward"].reshape(-1).tolist()
        T = len(opt)
        for t in range(T):
            if opt[t] < 0 or dec[t]:
                continue
            ret, k, j = 0.0, 0, t
            while True:
                ret += gamma**k * rew[j]
                k += 1
                if done[j] or (j + 1 < T and dec[j + 1]):
                    out.append((float(row["observation"][t]), 2 + opt[t], ret, k, float(row["next", "observation"][j])))
                    break
                if j + 1 == T:  # the run is still going: no suffix
                    break
                j += 1
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_option_suffixes_match_reference(seed):
    data = random_runs(5, 30, 3, seed)
    out = option_suffix_transitions(data, 0.8, action_offset=2)
    got = list(zip(out["observation"].tolist(), out["action"].tolist(), out["next", "reward"].reshape(-1).tolist(),
                   out["steps_to_next_obs"].reshape(-1).tolist(), out["next", "observation"].tolist()))
    want = suffix_reference(data, 0.8)
    assert len(got) == len(want) > 10
    for g_, w in zip(got, want):
        assert g_[0] == w[0] and g_[1] == w[1] and g_[3] == w[3] and g_[4] == w[4]
        assert g_[2] == pytest.approx(w[2], rel=1e-5)


def test_option_suffixes_long_run_stays_finite():
    """A 5000-step run: the returns are accumulated backwards, never divided by gamma ** t (which underflows)."""
    T = 5000
    data = TensorDict(
        {
            "observation": torch.arange(T, dtype=torch.float),
            "action": torch.zeros(T, dtype=torch.long),
            "next": {
                "observation": torch.arange(1, T + 1, dtype=torch.float),
                "reward": torch.ones(T, 1),
                "done": torch.arange(T).eq(T - 1).unsqueeze(-1),
                "executed_option": torch.zeros(T, dtype=torch.long),
                "option_decision": torch.arange(T).eq(0),
            },
        },
        [T],
    )
    out = option_suffix_transitions(data, 0.85, action_offset=0)
    assert out.shape == (T - 1,) and torch.isfinite(out["next", "reward"]).all()
    k = out["steps_to_next_obs"].reshape(-1).double()
    torch.testing.assert_close(out["next", "reward"].reshape(-1).double(), (1 - 0.85**k) / (1 - 0.85), rtol=1e-5, atol=1e-5)


def test_option_suffixes_bad_input():
    with pytest.raises(ValueError, match="no .*option_decision.* entry"):
        option_suffix_transitions(two_envs().exclude(("next", "option_decision")), 0.9, action_offset=2)
    with pytest.raises(ValueError, match="gamma must be a number in"):
        option_suffix_transitions(two_envs(), 1.5, action_offset=2)
    with pytest.raises(ValueError, match="time dimension"):
        option_suffix_transitions(two_envs()[0, 0], 0.9, action_offset=2)


def test_option_suffixes_in_collector_batches():
    """Deterministic checkpoint options in the corridor: started anywhere, option 0 (right) stops at the next
    checkpoint, option 1 (left) at the previous one; every suffix ends there, after as many steps as cells."""
    torch.manual_seed(0)
    length, every = 10, 3
    env = Corridor(length, max_steps=30, batch_size=[3]).append_transform(
        OptionExecutor(checkpoint_options(length, every), 2)
    )
    collector = Collector(env, None, frames_per_batch=45, total_frames=225)
    collector.set_seed(0)
    seen = 0
    for batch in collector:
        out = option_suffix_transitions(batch, 0.9, action_offset=2)
        seen += out.shape[0]
        pos, end = out["position"].reshape(-1), out["next", "position"].reshape(-1)
        right = out["action"] == 2
        ended = ~out["next", "truncated"].reshape(-1)
        checkpoint = (end % every == 0) | (end == length - 1)
        assert (checkpoint | ~ended).all()
        assert (torch.where(right, end - pos, pos - end) == out["steps_to_next_obs"].reshape(-1))[ended].all()
        # no checkpoint strictly between start and end
        for p, e, r in zip(pos[ended].tolist(), end[ended].tolist(), right[ended].tolist()):
            between = range(p + 1, e) if r else range(e + 1, p)
            assert not any(c % every == 0 for c in between)
    collector.shutdown()
    assert seen > 10
