"""Decision-level (SMDP) transitions: hand-computed cases, a brute-force reference, batches, DQNLoss."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, ValueEstimators

from _tiny_envs import Corridor, checkpoint_options
from torchrl_options.data import SMDPTransitions, smdp_transitions
from torchrl_options.transforms import OptionExecutor

pytestmark = pytest.mark.usefixtures("torch_single_thread")


def steps(decision, done, reward=None, terminated=None, observation=None):
    """A [T] step-level batch; observation t is t (next observation t + 1) unless given."""
    T = len(decision)
    done = torch.tensor(done).unsqueeze(-1)
    obs = torch.arange(T, dtype=torch.float) if observation is None else observation
    return TensorDict(
        {
            "observation": obs,
            "action": torch.arange(10, 10 + T),
            "next": {
                "observation": obs + 1,
                "reward": (torch.ones(T) if reward is None else torch.tensor(reward, dtype=torch.float)).unsqueeze(-1),
                "done": done,
                "terminated": done.clone() if terminated is None else torch.tensor(terminated).unsqueeze(-1),
                "truncated": done & ~(done.clone() if terminated is None else torch.tensor(terminated).unsqueeze(-1)),
                "option_decision": torch.tensor(decision),
            },
        },
        [T],
    )


def reference(data: TensorDict, gamma: float):
    """Brute force, env by env, step by step: (env, start, end, discounted return, k) of complete decisions."""
    data = data.reshape(-1, data.shape[-1])
    out = []
    for n, env_data in enumerate(data.unbind(0)):
        dec = env_data["next", "option_decision"].tolist()
        done = env_data["next", "done"].reshape(-1).tolist()
        rew = env_data["next", "reward"].reshape(-1).tolist()
        T = len(dec)
        t = 0
        while t < T:
            if not dec[t]:  # started before the batch
                t += 1
                continue
            s, ret, k = t, 0.0, 0
            while True:
                ret += gamma**k * rew[t]
                k += 1
                if done[t] or (t + 1 < T and dec[t + 1]):
                    out.append((n, s, t, ret, k))
                    t += 1
                    break
                if t + 1 == T:  # unfinished
                    t += 1
                    break
                t += 1
    return out


def test_hand_computed_option_and_episode_end():
    gamma = 0.9
    # t:        0     1      2      3     4      5      6
    decision = [True, False, False, True, True, False, True]
    done = [False, False, False, False, False, True, False]  # a 2-step option cut by the episode end at t=5
    reward = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    out = smdp_transitions(steps(decision, done, reward), gamma)
    assert out["action"].tolist() == [10, 13, 14]  # the decision steps' actions; the last decision is unfinished
    assert out["observation"].tolist() == [0.0, 3.0, 4.0]
    assert out["next", "observation"].tolist() == [3.0, 4.0, 6.0]  # s at the next decision / end of episode
    assert out["steps_to_next_obs"].reshape(-1).tolist() == [3, 1, 2]
    expected = torch.tensor([1 + gamma * 2 + gamma**2 * 3, 4.0, 5 + gamma * 6])
    torch.testing.assert_close(out["next", "reward"].reshape(-1), expected)
    assert out["next", "done"].reshape(-1).tolist() == [False, False, True]
    assert out["next", "terminated"].reshape(-1).tolist() == [False, False, True]


def test_discount_per_decision_hand_computed():
    """Every decision one time-step: rewards of a decision summed, k = 1 (the bootstrap uses gamma once)."""
    decision = [True, False, False, True, True, False, True]
    done = [False, False, False, False, False, True, False]
    reward = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    out = smdp_transitions(steps(decision, done, reward), 0.9, discount_per="decision")
    assert out["steps_to_next_obs"].reshape(-1).tolist() == [1, 1, 1]
    # the decisions' true lengths are kept apart from the bootstrap's k (3 steps, 1 step, 2 steps)
    assert out["decision_steps"].reshape(-1).tolist() == [3, 1, 2]
    assert out["decision_steps"].shape == out["steps_to_next_obs"].shape
    torch.testing.assert_close(out["next", "reward"].reshape(-1), torch.tensor([6.0, 4.0, 11.0]))
    assert out["next", "observation"].tolist() == [3.0, 4.0, 6.0]
    # per step, the length is steps_to_next_obs itself: no second key
    assert "decision_steps" not in smdp_transitions(steps(decision, done, reward), 0.9).keys()
    # an option running over a batch boundary: its partial sum is carried, still undiscounted
    smdp = SMDPTransitions(0.5, discount_per="decision", duration_key=("stats", "length"))
    first = smdp(steps([True, False, False], [False] * 3, [1.0, 1.0, 1.0]))
    assert first.shape[0] == 0
    second = smdp(steps([False, True], [False, False], [1.0, 1.0]))
    assert second["steps_to_next_obs"].reshape(-1).tolist() == [1]
    assert second["stats", "length"].reshape(-1).tolist() == [4]  # 3 steps carried over + 1
    torch.testing.assert_close(second["next", "reward"].reshape(-1), torch.tensor([4.0]))
    with pytest.raises(ValueError, match="discount_per"):
        SMDPTransitions(0.9, discount_per="episode")
    with pytest.raises(ValueError, match="duration_key and steps_key are both 'steps_to_next_obs'"):
        SMDPTransitions(0.9, discount_per="decision", duration_key="steps_to_next_obs")
    with pytest.raises(TypeError, match="duration_key must be a NestedKey .* got 3"):
        smdp_transitions(steps(decision, done, reward), 0.9, duration_key=3)


def test_truncated_episode_is_not_terminal():
    out = smdp_transitions(steps([True, False], [False, True], terminated=[False, False]), 0.5)
    assert out["next", "done"].item() and not out["next", "terminated"].item() and out["next", "truncated"].item()
    assert out["steps_to_next_obs"].item() == 2


def test_without_decisions_every_step_is_one():
    data = steps([True] * 4, [False, True, False, False])
    del data["next", "option_decision"]
    out = smdp_transitions(data, 0.9)
    assert out["steps_to_next_obs"].reshape(-1).tolist() == [1, 1, 1]  # the last step's end is unknown
    torch.testing.assert_close(out["next", "reward"], data["next", "reward"][:3])


def test_option_spanning_two_batches():
    gamma = 0.5
    decision = [True, False, False, False, True, False]
    done = [False] * 6
    reward = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    data = steps(decision, done, reward)
    smdp = SMDPTransitions(gamma)
    first = smdp(data[:2])
    assert first.shape[0] == 0 and smdp.num_pending == 1
    second = smdp(data[2:])
    # the 4-step option started in the first batch ends in the second one
    assert second["action"].tolist() == [10]
    assert second["observation"].tolist() == [0.0]
    assert second["next", "observation"].tolist() == [4.0]
    assert second["steps_to_next_obs"].item() == 4
    torch.testing.assert_close(second["next", "reward"].reshape(-1), torch.tensor([1 + 0.5 + 0.25 + 0.125]))
    # and a decision ending exactly at a batch boundary is completed by the next batch's first decision
    smdp = SMDPTransitions(gamma)
    assert smdp(data[:4]).shape[0] == 0
    out = smdp(data[4:])
    assert out["steps_to_next_obs"].reshape(-1).tolist() == [4]


@pytest.mark.parametrize("chunks", [1, 3, 7])
def test_random_batches_match_reference(chunks):
    g = torch.Generator().manual_seed(0)
    N, T, gamma = 5, 60, 0.8
    decision = torch.rand(N, T, generator=g) < 0.4
    done = torch.rand(N, T, generator=g) < 0.08
    decision[:, 0] = True
    decision[:, 1:] |= done[:, :-1]  # the executor: a decision after every episode end
    data = TensorDict(
        {
            "observation": torch.randn(N, T, 3, generator=g),
            "action": torch.randint(0, 6, (N, T), generator=g),
            "next": {
                "observation": torch.randn(N, T, 3, generator=g),
                "reward": torch.randn(N, T, 1, generator=g),
                "done": done.unsqueeze(-1),
                "terminated": done.unsqueeze(-1),
                "option_decision": decision,
            },
        },
        [N, T],
    )
    expected = reference(data, gamma)
    smdp = SMDPTransitions(gamma)
    bounds = torch.linspace(0, T, chunks + 1).long().tolist()
    out = torch.cat([smdp(data[:, a:b]) for a, b in zip(bounds[:-1], bounds[1:])])
    # the stateful version finds every complete decision whatever the batch boundaries (batch order, so
    # compare sorted by the start observation, unique random numbers)
    start_obs = torch.stack([data["observation"][e[0], e[1]] for e in expected])
    end_obs = torch.stack([data["next", "observation"][e[0], e[2]] for e in expected])
    assert out.shape[0] == len(expected)
    out = out[out["observation"][:, 0].argsort()]
    order = start_obs[:, 0].argsort()
    torch.testing.assert_close(out["observation"], start_obs[order])
    torch.testing.assert_close(out["next", "observation"], end_obs[order])
    assert out["steps_to_next_obs"].reshape(-1).tolist() == [expected[i][4] for i in order]
    torch.testing.assert_close(out["next", "reward"].reshape(-1), torch.tensor([expected[i][3] for i in order]))
    if chunks == 1:
        assert out.shape[0] == smdp_transitions(data, gamma).shape[0]


def test_collector_batches_with_executor():
    """End to end: every collected step belongs to exactly one decision (complete or still pending)."""
    torch.manual_seed(1)  # Collector(policy=None) draws from the global generator; seed 1 ends inside an option
    env = Corridor(8, max_steps=10, batch_size=[3]).append_transform(OptionExecutor(checkpoint_options(8), 2))
    collector = Collector(env, None, frames_per_batch=30, total_frames=90)
    collector.set_seed(0)
    smdp = SMDPTransitions(0.9)
    total_k, frames, decisions, outputs = 0, 0, 0, 0
    for batch in collector:
        out = smdp(batch)
        outputs += out.shape[0]
        total_k += int(out["steps_to_next_obs"].sum())
        frames += batch.numel()
        decisions += int(batch["next", "option_decision"].sum())
        assert (out["action"] >= 0).all()
    collector.shutdown()
    pending_steps = int(smdp._carry.steps[smdp._carry.valid].sum())
    assert 0 < pending_steps and total_k + pending_steps == frames
    assert outputs + smdp.num_pending == decisions


def test_dqn_loss_bootstraps_with_gamma_k():
    """DQNLoss (TD(0) estimator) reads steps_to_next_obs: target = R + gamma^k (1 - terminated) max Q'."""
    gamma, num_actions = 0.9, 3
    net = torch.nn.Linear(1, num_actions)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor([1.0, 2.0, 5.0]))  # Q(s, .) = [1, 2, 5] everywhere
    actor = QValueActor(net, in_keys=["observation"], spec=Categorical(num_actions))
    loss = DQNLoss(actor, action_space=Categorical(num_actions), delay_value=True, reduction="none")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    k = torch.tensor([[1], [3], [3]])
    terminated = torch.tensor([[False], [False], [True]])
    td = TensorDict(
        {
            "observation": torch.zeros(3, 1),
            "action": torch.tensor([0, 1, 1]),
            "steps_to_next_obs": k,
            "next": {
                "observation": torch.zeros(3, 1),
                "reward": torch.tensor([[0.5], [0.5], [0.5]]),
                "done": terminated.clone(),
                "terminated": terminated,
            },
        },
        [3],
    )
    target = 0.5 + gamma ** k.squeeze(-1).float() * 5.0 * (~terminated.squeeze(-1)).float()
    pred = torch.tensor([1.0, 2.0, 2.0])
    value = loss(td)["loss"]
    torch.testing.assert_close(value, (pred - target) ** 2)
    # without the key every transition is one step long
    del td["steps_to_next_obs"]
    torch.testing.assert_close(loss(td)["loss"][1], torch.tensor((2.0 - (0.5 + gamma * 5.0)) ** 2))


@pytest.mark.parametrize("discount_per", ["step", "decision"])
def test_dqn_target_of_a_three_step_option_by_hand(discount_per):
    """Step-level data through the SMDP transitions into DQNLoss: a 3-step option with rewards 1, 2, 4, then a
    1-step action, Q'(s, .) = [1, 2, 5]. Per step (SMDP): y = 1 + g 2 + g^2 4 + g^3 5; per decision (the authors'
    HDQN): y = (1 + 2 + 4) + g 5."""
    g = 0.5
    data = steps([True, False, False, True, True], [False] * 5, [1.0, 2.0, 4.0, 8.0, 0.0])
    out = smdp_transitions(data, g, discount_per=discount_per)
    net = torch.nn.Linear(1, 3)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor([1.0, 2.0, 5.0]))
    actor = QValueActor(net, in_keys=["observation"], spec=Categorical(3))
    loss = DQNLoss(actor, action_space=Categorical(3), delay_value=True, reduction="none")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=g)
    td = out.select("observation", "action", "steps_to_next_obs", ("next", "reward"), ("next", "done"),
                    ("next", "terminated"), ("next", "observation"))  # fmt: skip
    td["observation"] = td["observation"].unsqueeze(-1)
    td["next", "observation"] = td["next", "observation"].unsqueeze(-1)
    td["action"] = torch.tensor([0, 2])  # Q(s, a) = 1 and 5
    if discount_per == "step":
        target = torch.tensor([1 + g * 2 + g**2 * 4 + g**3 * 5, 8 + g * 5])
    else:
        target = torch.tensor([(1 + 2 + 4) + g * 5, 8 + g * 5])
    torch.testing.assert_close(loss(td)["loss"], (torch.tensor([1.0, 5.0]) - target) ** 2)


# ---------------------------------------------------------------------------------- bad input
NAN = float("nan")


@pytest.mark.parametrize("gamma", [1.5, -0.5, NAN, True, "0.9", None])
def test_gamma_outside_unit_interval_refused(gamma):
    data = steps([True, False], [False, False])
    error = ValueError if isinstance(gamma, float) else TypeError  # a wrong type (True, "0.9", None): TypeError
    with pytest.raises(error, match=r"gamma must be a number in \[0, 1\], got|gamma must be a number, got"):
        smdp_transitions(data, gamma)
    with pytest.raises(error, match="gamma"):
        SMDPTransitions(gamma)
    with pytest.raises(error, match="gamma"):
        SMDPTransform(gamma)


@pytest.mark.parametrize("key, name", [(("next", "done"), "done_key"), (("next", "reward"), "reward_key")])
def test_missing_done_or_reward_named(key, name):
    data = steps([True, False, True], [False, False, False]).exclude(key)
    with pytest.raises(ValueError, match=rf"no \({key[0]!r}, {key[1]!r}\) entry \({name}\)"):
        smdp_transitions(data, 0.9)
    with pytest.raises(ValueError, match=name):
        SMDPTransitions(0.9)(data)


def test_other_bad_data():
    with pytest.raises(ValueError, match="at least one step"):
        smdp_transitions(steps([True], [False])[:0], 0.9)
    with pytest.raises(ValueError, match="time dimension"):
        smdp_transitions(steps([True], [False])[0], 0.9)
    with pytest.raises(TypeError, match="TensorDict"):
        smdp_transitions({"next": {}}, 0.9)
    data = steps([True, False], [False, False])
    data["next", "option_decision"] = torch.ones(2, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="one .*option_decision.* per step"):
        smdp_transitions(data, 0.9)


# ------------------------------------------------------------------------- replay-buffer transform
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer  # noqa: E402

from torchrl_options.data import SMDPTransform, intra_option_transitions, option_suffix_transitions  # noqa: E402


def _collector_batches(frames_per_batch=30, total_frames=150, length=8):
    torch.manual_seed(1)
    env = Corridor(length, max_steps=10, batch_size=[3]).append_transform(OptionExecutor(checkpoint_options(length), 2))
    collector = Collector(env, None, frames_per_batch=frames_per_batch, total_frames=total_frames)
    collector.set_seed(0)
    batches = [batch.clone() for batch in collector]
    collector.shutdown()
    return batches


@pytest.mark.parametrize("extras", [False, True])
def test_replay_buffer_transform_equals_function_path(extras):
    """rb.append_transform(SMDPTransform(...)) stores exactly what the function-based path gives, over a collector run
    split into batches (options spanning batch boundaries included)."""
    gamma = 0.9
    batches = _collector_batches()
    smdp = SMDPTransitions(gamma)
    expected = []
    for batch in batches:
        parts = [smdp(batch)]
        if extras:
            parts.append(intra_option_transitions(batch, num_actions=2))
            parts.append(option_suffix_transitions(batch, gamma, action_offset=2))
            for i, part in enumerate(parts):
                part["intra_option"] = torch.full(part.shape, i > 0)
        expected.append(torch.cat(parts))
    expected = torch.cat(expected)
    assert (expected["steps_to_next_obs"] > 1).any()  # options ran
    transform = SMDPTransform(
        gamma, intra_option_actions=extras, option_suffixes=extras, num_actions=2 if extras else None
    )
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=8)
    rb.append_transform(transform)
    for batch in batches:
        rb.extend(batch)
    stored = rb[:]
    assert len(rb) == expected.shape[0] > 0
    assert transform.num_pending == smdp.num_pending > 0  # decisions still running at the end of the run
    for key in expected.keys(True, True):
        torch.testing.assert_close(stored[key], expected[key], msg=str(key))
    sample = rb.sample()  # sampling returns stored transitions unchanged
    assert sample.shape == (8,) and "steps_to_next_obs" in sample.keys()
    transform.reset()
    assert transform.num_pending == 0


def test_replay_buffer_transform_per_decision_keeps_lengths_beside_intra_option_steps():
    """Per decision, the stored decisions have k = 1 and their true lengths in "decision_steps" (those of the
    per-step path's k); the intra-option transitions stored beside them get "decision_steps" = 1, so both fit one
    buffer."""
    batches = _collector_batches()
    per_step = SMDPTransitions(0.9)
    lengths = torch.cat([per_step(b)["steps_to_next_obs"] for b in batches])
    transform = SMDPTransform(0.9, discount_per="decision", intra_option_actions=True, num_actions=2)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=8)
    rb.append_transform(transform)
    for batch in batches:
        rb.extend(batch)
    stored = rb[:]
    intra = stored["intra_option"].reshape(-1)
    decisions, one_step = stored[~intra], stored[intra]
    assert one_step.shape[0] > 0 and (decisions["steps_to_next_obs"] == 1).all()
    assert (lengths > 1).any()
    torch.testing.assert_close(decisions["decision_steps"], lengths)
    assert (one_step["decision_steps"] == 1).all()


def test_replay_buffer_transform_with_dqn_loss_targets():
    """The stored transitions feed DQNLoss, which bootstraps with gamma ** k."""
    gamma = 0.9
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=16)
    rb.append_transform(SMDPTransform(gamma))
    for batch in _collector_batches():
        rb.extend(batch)
    data = rb[:]
    actor = QValueActor(torch.nn.Linear(8, 4), in_keys=["observation"], spec=Categorical(4))
    loss = DQNLoss(actor, action_space=Categorical(4), reduction="none")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    with torch.no_grad():
        target_q = actor(data["next"].clone())["action_value"].max(-1).values
        value = loss(data.clone())["loss"]
        q = actor(data.clone())["action_value"].gather(-1, data["action"].unsqueeze(-1)).squeeze(-1)
    k = data["steps_to_next_obs"].squeeze(-1).float()
    not_term = (~data["next", "terminated"].squeeze(-1)).float()
    target = data["next", "reward"].squeeze(-1) + gamma**k * not_term * target_q
    torch.testing.assert_close(value, (q - target) ** 2)


def test_replay_buffer_transform_bad_use():
    with pytest.raises(ValueError, match="needs num_actions"):
        SMDPTransform(0.9, intra_option_actions=True)
    with pytest.raises(ValueError, match="discount_per='step'"):
        SMDPTransform(0.9, option_suffixes=True, discount_per="decision")
    with pytest.raises(ValueError, match="num_actions"):
        SMDPTransform(0.9, num_actions=0)
    with pytest.raises(TypeError, match="option_suffixes"):
        SMDPTransform(0.9, option_suffixes=1)
    env = Corridor(8, max_steps=10).append_transform(SMDPTransform(0.9))
    with pytest.raises(ValueError, match="replay-buffer transform"):
        env.rollout(3)
