"""Warm start: an actions-only DQN's networks and replay buffer carried over to a DQN over actions + options."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from _tiny_envs import Corridor, go_right_options
from torchrl_options.agents import OptionsDQN, OptionsDQNConfig, widen_action_rows, widen_action_values

pytestmark = pytest.mark.usefixtures("torch_single_thread")

LENGTH = 10


def corridor():
    return Corridor(LENGTH, max_steps=20, batch_size=[2])


def config(mode, **kwargs):
    defaults = dict(mode=mode, total_frames=256, frames_per_batch=32, learning_starts=16, batch_size=16,
                    updates_per_batch=2, hidden_sizes=(16,), hard_update_interval=5, eps_init=0.5, seed=0)
    defaults.update(kwargs)
    return OptionsDQNConfig(**defaults)


def q_values(agent, obs, target=False):
    params = agent.loss_module.target_value_network_params if target else agent.loss_module.value_network_params
    with params.to_module(agent.loss_module.value_network):
        return agent.loss_module.value_network(TensorDict(observation=obs, batch_size=obs.shape[:1]))["action_value"]


def test_widen_action_rows_keeps_outputs_and_starts_new_ones_at_their_mean():
    torch.manual_seed(0)
    old = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 3))
    new = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 5))
    new.load_state_dict(widen_action_rows(old.state_dict(), new.state_dict(), num_actions=3))
    x = torch.randn(32, 4)
    torch.testing.assert_close(new(x)[:, :3], old(x))
    torch.testing.assert_close(new(x)[:, 3:], old(x).mean(-1, keepdim=True).expand(32, 2))
    # the copy does not alias the source
    new[2].weight.data.zero_()
    assert old[2].weight.abs().sum() > 0


def test_widen_action_rows_bad_input():
    old = torch.nn.Linear(4, 3).state_dict()
    with pytest.raises(KeyError, match="'extra'"):
        widen_action_rows(old, {**torch.nn.Linear(4, 5).state_dict(), "extra": torch.zeros(1)}, num_actions=3)
    with pytest.raises(ValueError, match="'weight'.*num_actions=3"):
        widen_action_rows(old, torch.nn.Linear(6, 5).state_dict(), num_actions=3)  # input width changed
    with pytest.raises(ValueError, match="num_actions=2"):
        widen_action_rows(old, torch.nn.Linear(4, 5).state_dict(), num_actions=2)


def test_widen_action_values():
    td = TensorDict(action_value=torch.tensor([[0.0, 2.0, 4.0], [1.0, 1.0, 1.0]]), batch_size=[2])
    out = widen_action_values(td, 5)
    assert out["action_value"].tolist() == [[0.0, 2.0, 4.0, 2.0, 2.0], [1.0, 1.0, 1.0, 1.0, 1.0]]
    assert widen_action_values(TensorDict(batch_size=[2]), 5).is_empty()
    with pytest.raises(ValueError, match="'action_value' has 5 entries, more than num_outputs=4"):
        widen_action_values(td, 4)


def test_warm_start_from_copies_networks_and_buffer_then_trains():
    source = OptionsDQN(corridor, config("actions"))
    source.train()
    assert source.gradient_steps > 0 and len(source.replay_buffer) > 0
    agent = OptionsDQN(corridor, config("both", seed=1), options=go_right_options(LENGTH), num_options=2)
    obs = torch.randn(16, source.replay_buffer[:1]["observation"].shape[-1])
    before = q_values(agent, obs)
    assert not torch.allclose(before[:, :2], q_values(source, obs))  # different initialisations
    assert agent.warm_start_from(source) is agent
    for target in (False, True):  # online and target networks
        q_new, q_old = q_values(agent, obs, target), q_values(source, obs, target)
        assert q_new.shape == (16, 4)
        torch.testing.assert_close(q_new[:, :2], q_old)
        torch.testing.assert_close(q_new[:, 2:], q_old.mean(-1, keepdim=True).expand(16, 2))
    # the buffer: the same decisions, action values widened
    n = len(source.replay_buffer)
    assert len(agent.replay_buffer) == n
    old, new = source.replay_buffer[:n], agent.replay_buffer[:n]
    for key in ("action", ("next", "reward"), ("next", "observation"), "steps_to_next_obs"):
        assert torch.equal(old[key], new[key])
    assert new["action_value"].shape == (n, 4)
    # training goes on: new decisions (including options) land after the copied ones, and the loss is finite
    agent.train(total_frames=128)
    assert len(agent.replay_buffer) > n and agent.gradient_steps > 0
    assert torch.isfinite(torch.tensor(agent.log.losses)).all()
    assert (agent.replay_buffer[n: len(agent.replay_buffer)]["action"] >= 0).all()


def test_warm_start_from_without_buffer_and_bad_pairs():
    source = OptionsDQN(corridor, config("actions", total_frames=64))
    source.train(total_frames=64)
    agent = OptionsDQN(corridor, config("both"), options=go_right_options(LENGTH), num_options=2)
    agent.warm_start_from(source, copy_buffer=False)
    assert len(agent.replay_buffer) == 0
    with pytest.raises(ValueError, match="source must have mode='actions'"):
        agent.warm_start_from(agent)
    only_options = OptionsDQN(corridor, config("options"), options=go_right_options(LENGTH), num_options=2)
    with pytest.raises(ValueError, match="must have mode='both'"):
        only_options.warm_start_from(source)
    # a source over a different action space
    wider = OptionsDQN(corridor, config("both"), options=go_right_options(LENGTH), num_options=2)
    wider.num_options = 3
    with pytest.raises(ValueError, match="expected 2 \\+ 3"):
        wider.warm_start_from(source)
