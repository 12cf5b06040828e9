"""The usage floor (posterior regularisation of the E-step): the projected posterior against exact enumeration,
the penalised objective and its gradient, the dual step, the floor held by a real fit, and bad input."""
import math

import pytest
import torch
from tensordict import TensorDict

from _enumeration import latent_sequences
from torchrl_options import DDOLoss, discover_options, forward_backward, OptionsMLP
from torchrl_options.data import demonstration_buffer, write_demonstrations
from torchrl_options.discovery import TabulatedDDO
from torchrl_options.discovery.usage_floor import UsageFloor
from torchrl_options.testing import planted_corridor_demonstrations


def _random_inputs(T, K, seed):
    g = torch.Generator().manual_seed(seed)
    log_pi = torch.randn(T, K, generator=g, dtype=torch.float64).log_softmax(-1) * 2
    psi = torch.rand(T, K, generator=g, dtype=torch.float64)
    log_eta = torch.randn(T, K, generator=g, dtype=torch.float64).log_softmax(-1)
    return log_pi, psi.log(), torch.log1p(-psi), log_eta


@pytest.mark.parametrize("terminal", [False, True])
def test_projected_posterior_against_enumeration(terminal):
    """q*(z) ~ p(z | x) exp(sum_t lambda_{h_t}): its marginals are the biased pass's, and log Z_lambda - lambda . E[n]
    is log p(x) - KL(q* || p(z | x)), all by brute force over every latent sequence."""
    T, K = 4, 3
    inputs = _random_inputs(T, K, seed=3 + terminal)
    bias = torch.tensor([0.0, 0.7, 1.9], dtype=torch.float64)
    joint = list(latent_sequences(*inputs, T, terminal))
    log_p = torch.stack([lp for lp, _, _ in joint])
    log_weight = torch.stack([lp + sum(bias[h] for h in hs) for lp, hs, _ in joint])
    log_px = torch.logsumexp(log_p, 0)
    q = (log_weight - torch.logsumexp(log_weight, 0)).exp()
    u = torch.zeros(T, K, dtype=torch.float64)
    for qz, (_, hs, _) in zip(q, joint):
        for t, h in enumerate(hs):
            u[t, h] += qz
    kl = (q * (q.clamp_min(1e-300).log() - (log_p - log_px))).sum()

    floor = UsageFloor(K, 0.5)
    floor.bias = bias
    log_pi, log_term, log_cont, log_eta = (x.unsqueeze(0) for x in inputs)
    fb = forward_backward(floor.biased(log_pi), log_term, log_cont, log_eta, terminal=terminal, backend="reference")
    torch.testing.assert_close(fb.u[0], u, rtol=0, atol=1e-12)
    penalised = fb.log_likelihood.sum() - floor.penalty(fb.u)
    torch.testing.assert_close(penalised, log_px - kl, rtol=0, atol=1e-10)
    assert float(penalised) < float(log_px)  # a binding floor costs likelihood


def test_without_bias_the_penalised_objective_is_the_likelihood():
    data = planted_corridor_demonstrations(4, 30, seed=1)
    loss = DDOLoss(OptionsMLP(2, 2, 3))
    table = TabulatedDDO(loss, data)
    exact, _ = table.e_step()
    floor = UsageFloor(3, 0.01)  # starts at lambda = 0
    projected, _ = table.e_step(usage_floor=floor)
    assert float(projected["log_likelihood_per_step"]) == float(exact["log_likelihood_per_step"])


def test_tabulated_e_step_gradient_is_the_projected_expectation_gradient():
    """The G-step objective of a projected E-step has the gradient of log Z_lambda (the biased pass's
    normaliser) at the current parameters, and the record holds the penalised objective."""
    torch.manual_seed(0)
    data = planted_corridor_demonstrations(4, 30, seed=2)
    loss = DDOLoss(OptionsMLP(2, 2, 3))
    floor = UsageFloor(3, 0.5)
    floor.bias = torch.tensor([0.0, 0.4, 1.3])
    bias = floor.bias.clone()
    record, objective = TabulatedDDO(loss, data).e_step(usage_floor=floor)
    objective().backward()
    tabulated = [p.grad.clone() for p in loss.parameters()]
    loss.zero_grad()
    p = loss.log_probabilities(data)
    fb = forward_backward(p["log_pi"] + bias, p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
    n = p["mask"].sum()
    (-fb.log_likelihood.sum() / n).backward()
    for a, b in zip(tabulated, (p.grad for p in loss.parameters())):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    expected = (fb.log_likelihood.sum() - (fb.u.sum((0, 1)) * bias).sum()) / n
    torch.testing.assert_close(record["log_likelihood_per_step"], expected.detach(), rtol=1e-5, atol=1e-6)
    # and the dual stepped from this posterior's usage
    usage = (fb.u.sum((0, 1)) / n).detach()
    torch.testing.assert_close(floor.bias, (bias + (0.5 - 3 * usage)).clamp_min(0.0), rtol=1e-5, atol=1e-6)


def test_dual_step_raises_the_bias_of_an_option_below_the_floor_only():
    floor = UsageFloor(4, 0.4, step=2.0)
    floor.update(torch.tensor([0.7, 0.25, 0.05, 0.0]))  # relative usage 2.8, 1.0, 0.2, 0.0
    torch.testing.assert_close(floor.bias, torch.tensor([0.0, 0.0, 0.4, 0.8]))
    floor.update(torch.tensor([0.25, 0.25, 0.25, 0.25]))  # at the uniform usage, every bias shrinks by 2 * 0.6
    torch.testing.assert_close(floor.bias, torch.tensor([0.0, 0.0, 0.0, 0.0]))


def _one_policy_data():
    """Every step's action is one deterministic function of the observation: one option can explain them all."""
    g = torch.Generator().manual_seed(0)
    B, T = 16, 40
    obs = torch.randn(B, T + 1, 2, generator=g)
    action = (obs[:, :-1, 0] + obs[:, :-1, 1] > 0).long()
    return TensorDict({"observation": obs[:, :-1], "action": action, "next": {"observation": obs[:, 1:]}}, [B, T])


def test_a_fit_with_a_floor_keeps_every_option_at_the_floor():
    """On data one option can copy, one random start leaves two options under half their uniform share; with
    ``usage_floor=0.5`` the trained model's own usage (its exact posterior) keeps every option at the floor."""
    data = _one_policy_data()
    common = dict(init="random", seed=0, progress=False, return_info=True, num_iterations=300)
    free = discover_options(data, 3, **common)
    held = discover_options(data, 3, usage_floor=0.5, **common)
    assert min(free.option_usage) < 0.5 / 3 * 0.6
    assert min(held.option_usage) > 0.5 / 3 * 0.9
    # the floor costs next to nothing here: both fit the deterministic actions
    assert held.final_log_likelihood_per_step > -0.01 and free.final_log_likelihood_per_step > -0.01


def test_a_floor_that_does_not_bind_changes_nothing():
    data = planted_corridor_demonstrations(8, 30, seed=0)
    common = dict(seed=0, progress=False, return_info=True, num_iterations=120)
    free = discover_options(data, 2, **common)
    held = discover_options(data, 2, usage_floor=0.05, **common)
    assert min(free.option_usage) > 0.05 / 2  # the floor never binds on this run
    assert [h["log_likelihood_per_step"] for h in free.history] == [h["log_likelihood_per_step"] for h in held.history]


@pytest.mark.parametrize("value", [0.0, 1.0, -0.2, 1.5, math.nan])
def test_bad_usage_floor_is_refused_at_the_door(value):
    data = planted_corridor_demonstrations(2, 10, seed=0)
    with pytest.raises(ValueError, match="usage_floor"):
        discover_options(data, 2, usage_floor=value, progress=False)


def test_usage_floor_of_the_wrong_type_is_refused():
    data = planted_corridor_demonstrations(2, 10, seed=0)
    with pytest.raises(TypeError, match="usage_floor"):
        discover_options(data, 2, usage_floor="half", progress=False)


def test_usage_floor_with_a_replay_buffer_is_refused(tmp_path):
    data = planted_corridor_demonstrations(4, 10, seed=0)
    buffer = demonstration_buffer(1000, path=tmp_path / "demos")
    write_demonstrations(buffer, data)
    with pytest.raises(ValueError, match="usage_floor=0.5 .*replay buffer"):
        discover_options(buffer, 2, usage_floor=0.5, progress=False)


def test_update_refuses_usage_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"usage must be a \[K=3\] tensor, got \(2,\)"):
        UsageFloor(3, 0.5).update(torch.tensor([0.5, 0.5]))
