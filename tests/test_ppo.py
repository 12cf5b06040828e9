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


# --------------------------------------------------------------------------- the exact SMDP policy gradient
L5, COST = 5, 0.1  # Corridor(5) (terminal cell 4), a step cost of 0.1, checkpoint options every 2 cells


def _moves(cell: int, action: int) -> tuple[int, int]:
    """Next decision cell and number of steps of each augmented action (deterministic corridor and options)."""
    if action < 2:
        return (max(cell - 1, 0), 1) if action == 0 else (cell + 1, 1)
    step, k = (1 if action == OPT_RIGHT else -1), 0
    while True:
        cell, k = min(max(cell + step, 0), L5 - 1), k + 1
        if cell % 2 == 0 or cell == L5 - 1:
            return cell, k


def _exact_values(theta: torch.Tensor) -> torch.Tensor:
    """SMDP values V(cell) of the tabular policy softmax(theta[cell]) over the decision cells 0..3 (gamma = 1):
    the linear system V = r + P V, differentiable in theta."""
    pi = theta[: L5 - 1].softmax(-1)
    rows_r, rows_p = [], []
    for s in range(L5 - 1):
        r, p = 0.0, torch.zeros(L5 - 1)
        for a in range(4):
            s2, k = _moves(s, a)
            r = r + pi[s, a] * (-COST * k + float(s2 == L5 - 1))
            if s2 != L5 - 1:
                p = p + pi[s, a] * torch.nn.functional.one_hot(torch.tensor(s2), L5 - 1)
        rows_r.append(r)
        rows_p.append(p)
    return torch.linalg.solve(torch.eye(L5 - 1) - torch.stack(rows_p), torch.stack(rows_r))


def _policy_gradient_estimates(lmbda: float = 0.5, num_envs: int = 4096, steps: int = 64):
    """Exact gradient of the expected return from cell 0, and the expected ClipPPOLoss gradients (at ratio 1,
    summed over the first episode of each env, averaged over envs) of the decision-level and of the naive
    step-level composition, both with the exact SMDP values as critic."""
    from torchrl.envs import ExplorationType, set_exploration_type

    torch.manual_seed(0)
    theta = (0.5 * torch.randn(L5, 4) + torch.tensor([0.0, 1.0, 1.0, 0.0])).requires_grad_()
    values = _exact_values(theta)
    (exact,) = torch.autograd.grad(values[0], theta)
    critic_net = nn.Linear(L5, 1, bias=False)
    with torch.no_grad():
        critic_net.weight.copy_(torch.cat([values.detach(), torch.zeros(1)]).unsqueeze(0))
    critic = ValueOperator(critic_net, in_keys=["observation"])
    actor = _tabular_actor(L5, 4, theta.detach())
    env = Corridor(L5, batch_size=[num_envs]).append_transform(RewardScaling(loc=-COST, scale=1.0))
    env = env.append_transform(OptionExecutor(checkpoint_options(L5, every=2), num_options=2))
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        data = env.rollout(steps, actor, break_when_any_done=False)
    done = data["next", "done"].squeeze(-1)
    finished = done.any(-1)
    assert finished.float().mean() > 0.999, "almost every env must finish its first episode"
    first_end = torch.where(finished, done.float().argmax(-1), -1)  # the few unfinished ones are left out
    data["t"] = torch.arange(steps).expand(num_envs, steps).clone()
    data["env_id"] = torch.arange(num_envs).unsqueeze(-1).expand(num_envs, steps).clone()

    def gradient(batch):
        loss = ClipPPOLoss(actor, critic, entropy_bonus=False, normalize_advantage=False, reduction="sum")
        loss.make_value_estimator(ValueEstimators.GAE, gamma=1.0, lmbda=lmbda)
        loss.value_estimator(batch)
        batch = batch[batch["t"] <= first_end[batch["env_id"]]]  # the first episode of each env
        (grad,) = torch.autograd.grad(loss(batch)["loss_objective"], [actor.module[0].module.weight])
        return -grad.T / finished.sum()  # [cell, action], like theta

    return exact, gradient(OnPolicyDecisions(gamma=1.0)(data)), gradient(data.clone())


def test_decision_level_gradient_is_the_exact_smdp_policy_gradient():
    """On an enumerable SMDP (corridor, deterministic options), the expected gradient of ClipPPOLoss over
    decision-level batches (Monte Carlo over 4096 episodes) equals the analytic gradient of the expected return;
    the naive composition (step-level batches, per-step GAE) is off by much more than the sampling error."""
    exact, decision_level, naive = _policy_gradient_estimates()
    scale = exact.norm()
    decision_error = (decision_level - exact).norm() / scale
    naive_error = (naive - exact).norm() / scale
    assert decision_error < 0.06, decision_error  # sampling error (measured: 0.019)
    assert naive_error > 0.15, naive_error  # biased (measured: 0.247)
    assert naive_error > 5 * decision_error


# ------------------------------------------------------------------------------------------- the agent
def test_ppo_with_options_learns_where_primitive_ppo_does_not():
    """Corridor(24), 40 steps per episode, reward only at the end: a random walk essentially never gets there
    (23 net steps right), the "go right" option does. Same budget (2048 frames), same seed."""
    results = {}
    for mode in ("actions", "both"):
        config = OptionsPPOConfig(
            mode=mode, total_frames=2048, frames_per_batch=256, num_epochs=4, minibatch_size=64, lr=3e-3, gamma=0.95,
            hidden_sizes=(16,), seed=0,
        )  # fmt: skip
        options = None if mode == "actions" else go_right_options(24)
        torch.manual_seed(0)  # the networks' initialisation and the policy's draws
        agent = OptionsPPO(
            lambda: Corridor(24, max_steps=40, batch_size=[8]), config, options=options,
            num_options=None if mode == "actions" else 2,
        )  # fmt: skip
        agent.train()
        recent = agent.log.episode_returns[-20:]
        results[mode] = (sum(recent) / len(recent), agent.evaluate(num_episodes=4, max_steps=200))
    assert results["actions"][0] == 0.0 and results["actions"][1] == [0.0] * 4
    assert results["both"][0] >= 0.9 and results["both"][1] == [1.0] * 4


def test_options_only_and_two_level_executors(tmp_path):
    """mode='options' (Categorical(K)); over an env that already runs level-1 options the agent's executor is level
    2 and its decisions are those of option_decision_2; a checkpoint restores the agent."""
    from _tiny_envs import constant_options

    config = OptionsPPOConfig(mode="options", total_frames=128, frames_per_batch=64, hidden_sizes=(8,))
    agent = OptionsPPO(lambda: Corridor(8, max_steps=20, batch_size=[2]), config, options=go_right_options(8), num_options=2)
    assert agent.env.full_action_spec_unbatched["action"].n == 2 and agent.decision_key == ("next", "option_decision")
    agent.train()

    def two_levels():
        return Corridor(8, max_steps=20, batch_size=[2]).append_transform(
            OptionExecutor(checkpoint_options(8, every=3), num_options=2)
        )

    upper = constant_options(torch.tensor([[-9.0, -9.0, 9.0, -9.0], [-9.0, -9.0, -9.0, 9.0]]), torch.tensor([-2.0, -2.0]))
    config = OptionsPPOConfig(mode="both", total_frames=128, frames_per_batch=64, hidden_sizes=(8,))
    agent = OptionsPPO(two_levels, config, options=upper, num_options=2)
    assert agent.decision_key == ("next", "option_decision_2")
    assert agent.env.full_action_spec_unbatched["action"].n == 6  # 2 primitive + 2 level-1 + 2 level-2
    seen = []
    agent.train(callback=lambda a, batch: seen.append(a.decisions(batch.clone())) and False)
    agent.save(tmp_path / "ppo.pt")
    other = OptionsPPO(two_levels, config, options=upper, num_options=2)
    other.load(tmp_path / "ppo.pt")
    assert other.frames == 128 and other.log.episode_returns == agent.log.episode_returns
    for key, value in agent.loss_module.state_dict().items():
        torch.testing.assert_close(other.loss_module.state_dict()[key], value)
    with pytest.raises(ValueError, match="mode"):
        OptionsPPO(two_levels, OptionsPPOConfig(mode="actions"), options=None).load(tmp_path / "ppo.pt")


@pytest.mark.parametrize(
    "kwargs, match",
    [({"mode": "bogus"}, "mode"), ({"gamma": 1.5}, "gamma"), ({"num_epochs": 0}, "num_epochs"),
     ({"minibatch_size": 0}, "minibatch_size"), ({"clip_epsilon": 0.0}, "clip_epsilon"),
     ({"hidden_sizes": [0]}, "hidden_sizes"), ({"max_grad_norm": -1.0}, "max_grad_norm")],
)  # fmt: skip
def test_bad_config_named(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        OptionsPPOConfig(**kwargs)


def test_options_mode_needs_options():
    with pytest.raises(ValueError, match="options"):
        OptionsPPO(lambda: Corridor(8), OptionsPPOConfig(mode="both"))


def test_the_documented_lines_in_a_plain_torchrl_ppo_loop():
    """docs/ppo.md: a TorchRL PPO loop (Collector, ProbabilisticActor, ValueOperator, ClipPPOLoss, GAE) gains options
    with the executor, OnPolicyDecisions and the guard; the unchanged loop on step-level batches is refused."""
    from torchrl.collectors import Collector

    torch.manual_seed(0)
    env = Corridor(8, max_steps=20, batch_size=[4]).append_transform(
        OptionExecutor(checkpoint_options(8, every=3), num_options=2)
    )
    n = env.full_action_spec_unbatched["action"].n
    assert n == 4
    actor = _tabular_actor(8, n)
    critic = ValueOperator(nn.Linear(8, 1), in_keys=["observation"])
    loss_module = guard_decision_level(ClipPPOLoss(actor, critic, entropy_coeff=0.01))
    loss_module.make_value_estimator(ValueEstimators.GAE, gamma=0.9, lmbda=0.95)
    optim = torch.optim.Adam(loss_module.parameters(), lr=1e-2)
    decisions = OnPolicyDecisions(0.9)
    collector = Collector(env, actor, frames_per_batch=64, total_frames=192, auto_register_policy_transforms=False)
    for i, batch in enumerate(collector):
        if i == 0:
            with pytest.raises(StepLevelDataError):
                loss_module.value_estimator(batch.clone())
        data = decisions(batch)
        with torch.no_grad():
            loss_module.value_estimator(data)
        for minibatch in data[torch.randperm(data.shape[0])].split(16):
            out = loss_module(minibatch)
            loss = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            optim.zero_grad()
            loss.backward()
            optim.step()
            assert loss.isfinite()
    collector.shutdown()


def test_train_keeps_the_callers_thread_count():
    """TorchRL's Collector closes the env when its frame budget is spent, and closing a SerialEnv raises torch's
    thread count (to min(the count at torchrl's import, the count + its workers)); train() puts the caller's back, so
    one-thread agents in processes sharing a machine do not oversubscribe it (each chunk of a resumable cell is a
    train() call). Where TorchRL's close does not raise the count (one core, or torchrl imported at one thread) this
    passes either way; on CI's 2 cores it fails without the guard."""
    from torchrl.envs import SerialEnv

    env = SerialEnv(2, lambda: Corridor(6, max_steps=10))
    env.reset()
    env.close()
    raised = torch.get_num_threads()  # what TorchRL's close did to the fixture's 1 thread (> 1 where it bumps)
    torch.set_num_threads(1)
    config = OptionsPPOConfig(mode="actions", num_envs=2, total_frames=64, frames_per_batch=32, num_epochs=1,
                              minibatch_size=16, hidden_sizes=(8,), seed=0)  # fmt: skip
    agent = OptionsPPO(lambda: Corridor(6, max_steps=10), config)
    for _ in range(2):  # the second call restarts the env the first one's collector closed
        agent.train(total_frames=32)
        assert torch.get_num_threads() == 1, f"train() left {torch.get_num_threads()} threads (a close gives {raised})"
    assert agent.frames == 64
