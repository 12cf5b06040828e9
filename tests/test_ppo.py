"""PPO over actions and options: decision-level batches, SMDP advantages by hand, the exact policy gradient, the
guard against step-level data, and learning with options where primitive actions fail."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import RewardScaling
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from _tiny_envs import Corridor, checkpoint_options, go_right_options
from torchrl_options.agents import OptionsPPO, OptionsPPOConfig
from torchrl_options.data import OnPolicyDecisions
from torchrl_options.objectives import guard_decision_level, StepLevelDataError
from torchrl_options.transforms import OptionExecutor

pytestmark = pytest.mark.usefixtures("torch_single_thread")

# Corridor(8) with checkpoint options every 3 cells (checkpoints 0, 3, 6, 7): augmented actions 0 left, 1 right,
# 2 "right to the next checkpoint", 3 "left to the next checkpoint".
OPT_RIGHT = 2


class Scripted(nn.Module):
    """Primitive right at cell 3, else the option right; log-probability -position (to see which one is kept)."""

    def forward(self, position):
        pos = position.squeeze(-1)
        return torch.where(pos == 3, 1, OPT_RIGHT), -pos.float()


def value_table(length: int) -> TensorDictModule:
    """V(cell) = cell / 10 + 0.1, on the one-hot observation."""
    net = nn.Linear(length, 1, bias=False)
    with torch.no_grad():
        net.weight.copy_(torch.arange(length, dtype=torch.float).unsqueeze(0) / 10 + 0.1)
    return ValueOperator(net, in_keys=["observation"])


def V(cell: int) -> float:
    return cell / 10 + 0.1


def scripted_rollout(steps: int, max_steps=None, num_envs: int = 2) -> TensorDict:
    env = Corridor(8, max_steps=max_steps, batch_size=[num_envs]).append_transform(
        OptionExecutor(checkpoint_options(8, every=3), num_options=2)
    )
    policy = TensorDictModule(Scripted(), ["position"], ["action", "action_log_prob"])
    return env.rollout(steps, policy, break_when_any_done=False)


def gae(decisions: TensorDict, gamma: float, lmbda: float) -> TensorDict:
    """TorchRL's GAE (what OptionsPPO uses) on a decision-level batch."""
    from torchrl.objectives.value import GAE

    GAE(gamma=gamma, lmbda=lmbda, value_network=value_table(8), differentiable=False)(decisions)
    return decisions


def test_advantages_equal_hand_computation_across_batches():
    """Episode: option 0->3 (3 steps), right 3->4, option 4->6 (2 steps), option 6->7 (reward 1, terminal); twice.
    Batches cut at steps 5 and 9: inside the option from 4 and inside the second episode's first option."""
    g, lam = 0.5, 0.8
    data = scripted_rollout(14)  # [2 envs, 14 steps] = 2 episodes each
    decisions = OnPolicyDecisions(gamma=g)
    batches = [gae(decisions(data[:, a:b]), g, lam) for a, b in ((0, 5), (5, 9), (9, 14))]

    def A(deltas, ks):  # backward GAE recursion over one cut sequence of decisions
        out, next_a = [], 0.0
        for delta, k in zip(reversed(deltas), reversed(ks)):
            next_a = delta + g**k * lam * next_a
            out.append(next_a)
        return out[::-1]

    d_opt0, d_right3 = g**3 * V(3) - V(0), g * V(4) - V(3)  # the two decisions ending in batch 1
    d_opt4, d_opt6 = g**2 * V(6) - V(4), 1.0 - V(6)  # the option from 4 ends in batch 2; the last is terminal
    expected = [
        ([0, 3], [3, 1], A([d_opt0, d_right3], [3, 1])),  # cut at the batch end: bootstrapped with V(4)
        ([4, 6], [2, 1], A([d_opt4, d_opt6], [2, 1])),  # terminal: not bootstrapped
        ([0, 3, 4, 6], [3, 1, 2, 1], A([d_opt0, d_right3, d_opt4, d_opt6], [3, 1, 2, 1])),
    ]
    for batch, (cells, ks, advantages) in zip(batches, expected):
        n = len(cells)
        assert batch.shape == (2 * n,)  # env 0's decisions, then env 1's
        assert batch["position"].squeeze(-1).tolist() == cells * 2
        assert batch["steps_to_next_obs"].squeeze(-1).tolist() == ks * 2
        # the log-probability the policy had when it made the decision (also for the one spanning two batches)
        assert batch["action_log_prob"].tolist() == [-float(c) for c in cells] * 2
        torch.testing.assert_close(batch["advantage"].squeeze(-1), torch.tensor(advantages * 2))
        values = torch.tensor([V(c) for c in cells] * 2)
        torch.testing.assert_close(batch["value_target"].squeeze(-1), torch.tensor(advantages * 2) + values)
    assert batches[1]["next", "terminated"].squeeze(-1).tolist() == [False, True] * 2
    assert batches[0]["next", "end_of_batch"].squeeze(-1).tolist() == [False, True] * 2


def test_episode_truncated_inside_an_option_is_bootstrapped():
    """max_steps=5 cuts the option from 4 after one step (at cell 5): one decision of k=1, bootstrapped with V(5)
    (truncated, not terminated), and the lambda-chain stops at the episode end."""
    g, lam = 0.9, 0.7
    data = scripted_rollout(10, max_steps=5, num_envs=1)  # two truncated episodes of 5 steps
    out = gae(OnPolicyDecisions(gamma=g)(data), g, lam)
    assert out["position"].squeeze(-1).tolist() == [0, 3, 4, 0, 3, 4]
    assert out["steps_to_next_obs"].squeeze(-1).tolist() == [3, 1, 1, 3, 1, 1]
    assert out["next", "truncated"].squeeze(-1).tolist() == [False, False, True] * 2
    assert not out["next", "terminated"].any()
    d = [g**3 * V(3) - V(0), g * V(4) - V(3), g * V(5) - V(4)]
    a3 = d[2]
    a2 = d[1] + g * lam * a3
    a1 = d[0] + g**3 * lam * a2
    torch.testing.assert_close(out["advantage"].squeeze(-1), torch.tensor([a1, a2, a3] * 2))


def test_without_executor_every_step_is_a_decision():
    data = Corridor(4, batch_size=[2]).rollout(6, break_when_any_done=False)
    out = OnPolicyDecisions(gamma=0.9, decision_key=None)(data)
    assert out.shape == (12,) and (out["steps_to_next_obs"] == 1).all()
    assert out["next", "end_of_batch"].squeeze(-1).tolist() == ([False] * 5 + [True]) * 2


def test_missing_decision_key_named():
    data = Corridor(4).rollout(3)
    with pytest.raises(ValueError, match="option_decision"):
        OnPolicyDecisions(gamma=0.9)(data)
    with pytest.raises(TypeError, match="TensorDict"):
        OnPolicyDecisions(gamma=0.9)(torch.zeros(3))
    with pytest.raises(ValueError, match="gamma"):
        OnPolicyDecisions(gamma=1.5)


def _tabular_actor(length: int, n: int, logits: torch.Tensor | None = None) -> ProbabilisticActor:
    net = nn.Linear(length, n, bias=False)
    if logits is not None:
        with torch.no_grad():
            net.weight.copy_(logits.T)
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["logits"]), in_keys=["logits"],
        distribution_class=torch.distributions.Categorical, return_log_prob=True,
    )  # fmt: skip


def test_guard_refuses_step_level_executor_data():
    data = scripted_rollout(6, num_envs=1)
    data["action_log_prob"] = torch.zeros(1, 6)
    loss = guard_decision_level(ClipPPOLoss(_tabular_actor(8, 4), value_table(8)))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.9, lmbda=0.9)
    with pytest.raises(StepLevelDataError, match="OnPolicyDecisions"):
        loss(data.clone())
    with pytest.raises(StepLevelDataError, match="step-level data"):
        loss.value_estimator(data.clone())
    decisions = OnPolicyDecisions(gamma=0.9)(data)
    loss.value_estimator(decisions)
    assert loss(decisions)["loss_objective"].isfinite()
    # data without an executor passes untouched
    plain = Corridor(8).rollout(4)
    plain["action_log_prob"] = torch.zeros(4)
    loss(plain)
    with pytest.raises(TypeError, match="loss module"):
        guard_decision_level("ClipPPOLoss")
