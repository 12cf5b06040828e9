"""DecisionCounter: episode limits in decisions, step by step, in every env layout, nesting and bad input."""
from __future__ import annotations

from functools import partial

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import Compose, ParallelEnv, SerialEnv, StepCounter, TransformedEnv, check_env_specs

from _tiny_envs import RIGHT, Corridor, checkpoint_options
from test_option_executor import nested_env, scripted_policy
from torchrl_options.transforms import DecisionCounter, OptionExecutor

pytestmark = pytest.mark.usefixtures("torch_single_thread")

L, EVERY, A, K = 8, 3, 2, 2  # corridor length, checkpoint spacing (checkpoints 0, 3, 6 and the end 7), actions, options
GO_RIGHT = A + 0  # starts option 0: right until the next checkpoint


def counted_corridor(max_decisions, batch_size=(), length=L, max_steps=None, **executor_kwargs):
    """Corridor -> OptionExecutor (checkpoint options) -> DecisionCounter. ``max_steps=None``: every truncation
    comes from the counter."""
    env = Corridor(length, max_steps=max_steps, batch_size=batch_size)
    env = env.append_transform(OptionExecutor(checkpoint_options(length, EVERY), num_options=K, **executor_kwargs))
    return env.append_transform(DecisionCounter(max_decisions))


def check_counts(data: TensorDict, max_decisions: int, option_keys=("option",), decision_key="option_decision"):
    """Recomputes the count, truncation and done of every step, env by env (``data`` is [T] or [N, T]).

    Returns the number of truncations and of steps at which ``max_decisions`` decisions were made but the last
    one's option still ran (the episode had to go on).
    """
    data = data.reshape(-1, data.shape[-1]).cpu()
    truncations = waits = 0
    for row in data.unbind(0):
        nxt = row["next"]
        count_in = row["decision_count"].reshape(-1)
        count_out = nxt["decision_count"].reshape(-1)
        decision = nxt[decision_key].reshape(-1)
        over = torch.stack([nxt[k].reshape(-1) < 0 for k in option_keys]).all(0)
        truncated, done = nxt["truncated"].reshape(-1), nxt["done"].reshape(-1)
        terminated = nxt["terminated"].reshape(-1)
        for t in range(row.shape[0]):
            if t > 0:
                # the count is the state carried to the next step, and a new episode starts from 0 with a decision
                assert int(count_in[t]) == (0 if done[t - 1] else int(count_out[t - 1])), f"step {t}"
                if done[t - 1]:
                    assert decision[t], f"step {t}: the first step of an episode is a decision"
            if decision[t]:
                assert int(count_in[t]) < max_decisions, f"step {t}: a decision past the limit"
            assert int(count_out[t]) == int(count_in[t]) + int(decision[t]), f"step {t}"
            expected = bool(count_out[t] >= max_decisions and over[t])
            assert bool(truncated[t]) == expected, f"step {t}: truncated {bool(truncated[t])}"
            assert bool(done[t]) == (expected or bool(terminated[t])), f"step {t}"
            truncations += expected
            waits += bool(count_out[t] == max_decisions and not over[t])
    return truncations, waits


# ------------------------------------------------------------------------------------- episode limits
def test_episode_ends_once_the_last_option_terminates():
    env = counted_corridor(2, length=20)
    check_env_specs(env)
    # decision 1: "right" (cell 1); decision 2: option 0 runs right until the checkpoint cell 3 (2 steps)
    data = env.rollout(10, policy=scripted_policy([RIGHT, GO_RIGHT, 0, 0]))
    assert data.shape == (3,)  # the episode ended when option 0 terminated, not after the 2nd step
    assert data["next", "position"].reshape(-1).tolist() == [1, 2, 3]
    assert data["next", "decision_count"].reshape(-1).tolist() == [1, 2, 2]
    assert data["next", "truncated"].reshape(-1).tolist() == [False, False, True]
    assert data["next", "done"].reshape(-1).tolist() == [False, False, True]
    assert not data["next", "terminated"].any()


def test_options_only_episodes_run_max_decisions_options():
    env = counted_corridor(3, length=20, primitive_actions=False)
    data = env.rollout(20, policy=lambda td: td.set("action", torch.tensor(0)))  # always option 0
    # three options, checkpoint to checkpoint: 0 -> 3 -> 6 -> 9
    assert data.shape == (9,)
    assert data["next", "position"].reshape(-1)[-1] == 9
    assert data["next", "option_decision"].reshape(-1).nonzero().reshape(-1).tolist() == [0, 3, 6]
    check_counts(data, 3)


def test_collector_random_policy_invariants():
    env = counted_corridor(4, batch_size=[3])
    env.set_seed(0)
    torch.manual_seed(0)
    collector = Collector(env, None, frames_per_batch=240, total_frames=480)  # uniform random augmented actions
    truncations = waits = 0
    try:
        for batch in collector:
            n, w = check_counts(batch, 4)
            truncations, waits = truncations + n, waits + w
    finally:
        collector.shutdown()
    assert truncations > 20
    assert waits > 5  # 4 decisions made while an option still ran: the episode waited for it to terminate


@pytest.mark.parametrize("executor", [False, True])
def test_primitive_only_episodes_last_exactly_max_decisions_steps(executor):
    N = 5
    env = Corridor(30, max_steps=None, batch_size=[2])  # the end is out of reach in 5 steps
    if executor:
        env = env.append_transform(OptionExecutor(checkpoint_options(30, EVERY), num_options=K))
        env = env.append_transform(DecisionCounter(N))
    else:
        env = env.append_transform(DecisionCounter(N, level=None))
    reference = TransformedEnv(Corridor(30, max_steps=None, batch_size=[2]), StepCounter(N))
    check_env_specs(env)
    policy = lambda td: td.set("action", torch.randint(0, A, td.batch_size))  # primitive actions only
    data = env.rollout(23, policy, break_when_any_done=False)
    expected = reference.rollout(23, policy, break_when_any_done=False)
    assert data["next", "truncated"].reshape(2, -1).nonzero()[:, 1].tolist() == [4, 9, 14, 19] * 2
    assert (data["next", "done"] == expected["next", "done"]).all()
    assert (data["next", "decision_count"] == expected["next", "step_count"]).all()
    if executor:
        check_counts(data, N)


def test_env_step_limit_stays_a_hard_cap():
    # an option that never reaches its checkpoint within the env's max_steps: the env's truncation ends it
    env = counted_corridor(3, length=40, max_steps=4, primitive_actions=False)
    data = env.rollout(10, policy=lambda td: td.set("action", torch.tensor(0)))
    assert data.shape == (4,)
    assert data["next", "decision_count"].reshape(-1).tolist() == [1, 1, 1, 2]  # 0 -> 3 is one option
    assert data["next", "truncated"].reshape(-1).tolist() == [False, False, False, True]


def test_partial_reset_in_batched_env():
    env = counted_corridor(2, batch_size=[3], length=20)
    td = env.reset()
    td["action"] = torch.tensor([GO_RIGHT, RIGHT, RIGHT])
    td = env.step_mdp(env.step(td))
    assert td["decision_count"].reshape(-1).tolist() == [1, 1, 1]
    td["_reset"] = torch.tensor([[False], [True], [False]])
    td = env.reset(td)
    assert td["decision_count"].reshape(-1).tolist() == [1, 0, 1]
    assert td["option"].tolist() == [0, -1, -1]
    # env 0 keeps running its option, then decides again; envs 1 and 2 take primitive steps
    td["action"] = torch.tensor([RIGHT, RIGHT, RIGHT])
    td = env.step(td)
    assert td["next", "decision_count"].reshape(-1).tolist() == [1, 1, 2]
    assert td["next", "truncated"].reshape(-1).tolist() == [False, False, True]
    td = env.step_mdp(td)
    td = env.reset(td.set("_reset", td["done"].clone()))
    assert td["decision_count"].reshape(-1).tolist() == [1, 1, 0]
    # rollouts reset the done envs only (partial resets): every env keeps its own count
    data = env.rollout(30, policy=lambda td: td.set("action", torch.tensor([GO_RIGHT, RIGHT, GO_RIGHT])),
                       break_when_any_done=False, auto_reset=False, tensordict=td)  # fmt: skip
    truncations, waits = check_counts(data, 2)
    assert truncations > 10 and waits > 0
    ends = data["next", "done"].squeeze(-1)
    assert ends[1].nonzero().reshape(-1).tolist()[:3] == [0, 2, 4]  # primitive: 2 steps per episode
    # env 0: its first option reaches cell 3 at t=0, its 2nd (3 -> 6) ends the episode at t=3; then 0 -> 3 -> 6
    assert ends[0].nonzero().reshape(-1).tolist()[:3] == [3, 9, 15]


# ------------------------------------------------------------------------------------------ layouts
def _executor():
    return OptionExecutor(checkpoint_options(L, EVERY), num_options=K)


def test_serial_env_outside():
    env = TransformedEnv(SerialEnv(2, partial(Corridor, L, None)), Compose(_executor(), DecisionCounter(3)))
    check_env_specs(env)
    env.set_seed(0)
    check_counts(env.rollout(60, break_when_any_done=False), 3)


def test_inside_parallel_workers():
    env = ParallelEnv(2, partial(counted_corridor, 3), mp_start_method="fork")
    try:
        check_env_specs(env)
        env.set_seed(0)
        data = env.rollout(60, break_when_any_done=False)
    finally:
        env.close()
    truncations, _ = check_counts(data, 3)
    assert truncations > 5


def test_level_two_counts_the_top_level_decisions():
    # level-2 option -> level-1 option 0 runs 0..3, returns, level 2 continues -> option 0 runs 3..6, level 2
    # terminates at 6 (see test_option_executor.test_nested_call_and_return)
    env = nested_env("compose", max_steps=None).append_transform(DecisionCounter(1, level=2))
    check_env_specs(env)
    data = env.rollout(20, policy=scripted_policy([A + K + 0] + [0] * 19))
    assert data.shape == (6,)
    assert data["next", "truncated"].reshape(-1).tolist() == [False] * 5 + [True]
    check_counts(data, 1, option_keys=("option", "option_2"), decision_key="option_decision_2")
    # a level-2 decision that calls a level-1 option directly is over when that option returns (cell 3)
    data = env.rollout(20, policy=scripted_policy([A + 0] + [0] * 19))
    assert data.shape == (3,)
    assert data["next", "option_2"].reshape(-1).tolist() == [-1, -1, -1]
    # counting level-1 decisions instead: the level-2 option's first level-1 option is one decision
    env = nested_env("compose", max_steps=None).append_transform(DecisionCounter(1, level=1))
    data = env.rollout(20, policy=scripted_policy([A + K + 0] + [0] * 19))
    assert data.shape == (3,)


# ---------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("value", [0, -1, 2.5, True, None])
def test_bad_max_decisions(value):
    with pytest.raises(ValueError, match="max_decisions"):
        DecisionCounter(value)


def test_bad_level_and_keys():
    with pytest.raises(ValueError, match="level"):
        DecisionCounter(3, level=0)
    with pytest.raises(ValueError, match="decision_key"):
        DecisionCounter(3, level=None, decision_key="option_decision")
    with pytest.raises(ValueError, match="option_keys"):
        DecisionCounter(3, option_keys=[])


def test_without_an_executor_upstream():
    with pytest.raises(ValueError, match="decision_key.*OptionExecutor"):
        Corridor(L).append_transform(DecisionCounter(3))
    with pytest.raises(ValueError, match="decision_key"):
        TransformedEnv(Corridor(L), Compose(DecisionCounter(3), _executor()))  # before the executor
    with pytest.raises(ValueError, match="option_keys"):
        Corridor(L).append_transform(_executor()).append_transform(
            DecisionCounter(3, level=2, decision_key="option_decision")
        )
    with pytest.raises(ValueError, match="done_key"):
        Corridor(L).append_transform(_executor()).append_transform(DecisionCounter(3, done_key="finished"))


def test_no_forward_mode():
    with pytest.raises(NotImplementedError, match="environment step"):
        DecisionCounter(3)(TensorDict({}, []))


# ------------------------------------------------------------------------- nested and multi-agent done entries
def test_two_agents_count_at_the_root_and_truncate_every_done_entry():
    """A root count [N, 1] over per-agent decisions [N, 2]: a step is a decision when an agent decides, over once
    no agent's option runs; the truncation is written at the root and carried to ("agents", "done" / "truncated")."""
    from test_option_executor_done_keys import two_agent_env

    env = two_agent_env(num_envs=3, end_prob=0.05).append_transform(
        DecisionCounter(3, decision_key=("agents", "option_decision"), option_keys=[("agents", "option")])
    )
    check_env_specs(env)
    counter = env.transform[-1]
    assert counter.done_keys == ["done", ("agents", "done")] and counter.truncated_key == "truncated"
    torch.manual_seed(0)
    collector = Collector(env, None, frames_per_batch=3 * 80, total_frames=3 * 80)
    data = next(iter(collector))
    collector.shutdown()
    truncations = 0
    for row in data.unbind(0):
        nxt = row["next"]
        count_in, count_out = row["decision_count"].reshape(-1), nxt["decision_count"].reshape(-1)
        decision = nxt["agents", "option_decision"].any(-1)
        over = (nxt["agents", "option"] < 0).all(-1)
        truncated, done = nxt["truncated"].reshape(-1), nxt["done"].reshape(-1)
        for t in range(row.shape[0]):
            if t > 0:
                assert int(count_in[t]) == (0 if done[t - 1] else int(count_out[t - 1])), f"step {t}"
            assert int(count_out[t]) == int(count_in[t]) + int(decision[t]), f"step {t}"
            assert bool(truncated[t]) == bool(count_out[t] >= 3 and over[t]), f"step {t}"
            truncations += bool(truncated[t])
        # the truncation reached every agent's done and truncated entries
        assert (nxt["agents", "truncated"].reshape(-1, 2) == truncated.unsqueeze(-1)).all()
        assert (nxt["agents", "done"].reshape(-1, 2)[truncated]).all()
    assert truncations > 10


def test_nested_done_key_count_next_to_it():
    from test_option_executor_done_keys import nested_env

    env = nested_env(num_envs=2, end_prob=0.0).append_transform(
        DecisionCounter(
            2,
            decision_key=("agent", "option_decision"),
            option_keys=[("agent", "option")],
            count_key=("agent", "decision_count"),
        )
    )
    check_env_specs(env)
    assert env.transform[-1].truncated_key == ("agent", "truncated")
    data = env.rollout(4, lambda td: td.set(("agent", "action"), torch.tensor([0, 1])), break_when_any_done=False)
    # primitive actions only: every step is a decision, truncated after 2 steps, then a new episode
    assert data["next", "agent", "decision_count"].reshape(2, -1).tolist() == [[1, 2, 1, 2]] * 2
    assert data["next", "agent", "truncated"].reshape(2, -1).tolist() == [[False, True, False, True]] * 2
    assert data["next", "agent", "done"].reshape(2, -1).tolist() == [[False, True, False, True]] * 2
