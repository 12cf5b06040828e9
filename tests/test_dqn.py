"""OptionsDQN: options make a sparse corridor learnable within a budget where primitive DQN fails."""
from __future__ import annotations

import pytest
import torch

from _tiny_envs import Corridor, go_right_options
from torchrl_options.agents import OptionsDQN, OptionsDQNConfig
from torchrl_options.data import option_suffix_transitions

pytestmark = pytest.mark.usefixtures("torch_single_thread")

LENGTH, MAX_STEPS = 20, 40  # a random walk reaches the end within 40 steps with probability ~0.3%


def corridor():
    return Corridor(LENGTH, max_steps=MAX_STEPS, batch_size=[4])


def config(mode, **kwargs):
    defaults = dict(
        mode=mode,
        total_frames=2_000,
        frames_per_batch=64,
        eps_annealing_frames=1_500,
        gamma=0.95,
        lr=2e-3,
        updates_per_batch=4,
        hidden_sizes=(32,),
        hard_update_interval=50,
        greedy_options=True,
        seed=0,
    )
    defaults.update(kwargs)
    return OptionsDQNConfig(**defaults)


def seeded_dqn(*args, **kwargs) -> OptionsDQN:
    """The agent does not seed torch's global generator (network init, exploration): the caller does."""
    torch.manual_seed(0)
    return OptionsDQN(*args, **kwargs)


def test_options_learn_what_primitive_dqn_cannot():
    with_options = seeded_dqn(corridor, config("both"), options=go_right_options(LENGTH), num_options=2)
    log = with_options.train()
    primitive = seeded_dqn(corridor, config("actions"))
    primitive.train()
    assert with_options.frames == primitive.frames >= 2_000
    # same budget: the option agent reaches the goal greedily every time, the primitive one never
    assert with_options.evaluate(8, MAX_STEPS) == [1.0] * 8
    assert sum(primitive.evaluate(8, MAX_STEPS)) == 0.0
    # random decisions already find the goal often (1 in 4 starts the right option); learning makes it direct
    lengths = torch.tensor(log.episode_lengths, dtype=torch.float)
    assert lengths[-20:].mean() < lengths[:20].mean()
    assert lengths[-20:].min() == LENGTH - 1
    assert len(log.episode_returns) == len(log.episode_lengths) == len(log.episode_end_frames)
    assert log.episode_end_frames == sorted(log.episode_end_frames)


def test_checkpoint_resume_options_only(tmp_path):
    cfg = config("options", total_frames=256, learning_starts=8, batch_size=8)
    agent = seeded_dqn(corridor, cfg, options=go_right_options(LENGTH), num_options=2)
    assert agent.env.full_action_spec_unbatched["action"].n == 2
    agent.train()
    assert agent.frames == 256 and agent.gradient_steps > 0
    agent.save(tmp_path / "ckpt.pt", include_buffer=True)

    resumed = seeded_dqn(corridor, cfg, options=go_right_options(LENGTH), num_options=2)
    resumed.load(tmp_path / "ckpt.pt")
    for p, q in zip(agent.loss_module.parameters(), resumed.loss_module.parameters()):
        torch.testing.assert_close(p, q)
    torch.testing.assert_close(resumed.exploration.eps, agent.exploration.eps)
    assert len(resumed.replay_buffer) == len(agent.replay_buffer)
    # the Q-actor used by the collector shares the restored weights
    td = resumed.env.reset()
    torch.testing.assert_close(resumed.actor(td.clone())["action_value"], agent.actor(td.clone())["action_value"])
    resumed.train(128)
    assert resumed.frames == 384
    assert resumed.log.episode_returns[: len(agent.log.episode_returns)] == agent.log.episode_returns


def test_config_errors():
    with pytest.raises(ValueError, match="mode"):
        OptionsDQN(corridor, config("everything"))
    with pytest.raises(ValueError, match="options"):
        OptionsDQN(corridor, config("both"))


def test_batches_without_a_finished_decision():
    # 4-frame batches while a "go right" option runs for 19 steps: most batches end no decision
    cfg = config("options", total_frames=64, frames_per_batch=4, learning_starts=1, batch_size=1)
    agent = seeded_dqn(lambda: Corridor(LENGTH, max_steps=MAX_STEPS), cfg, options=go_right_options(LENGTH), num_options=2)
    agent.train()
    assert agent.frames == 64
    assert 0 < len(agent.replay_buffer) < 16
    returns = agent.evaluate(3, 2 * MAX_STEPS)  # an unbatched env: episodes follow each other
    assert 2 <= len(returns) <= 3 and set(returns) <= {0.0, 1.0}


def test_callback_stops_training_and_checkpoints_do_not_alias(tmp_path):
    cfg = config("actions", total_frames=10_000, learning_starts=8, batch_size=8)
    agent = seeded_dqn(corridor, cfg)
    calls = []

    def stop_after_three_batches(agent_, batch):
        calls.append(batch.numel())
        return len(calls) == 3

    agent.train(callback=stop_after_three_batches)
    assert len(calls) == 3 and agent.frames == 3 * cfg.frames_per_batch
    state = agent.state_dict()
    resumed = seeded_dqn(corridor, cfg)
    resumed.load_state_dict(state)
    before = len(state["log"]["episode_end_frames"])
    resumed.train(4 * MAX_STEPS * 4)  # every env finishes at least one more episode
    # training after a load appends to the agent's own log, not to the checkpoint's lists
    assert len(resumed.log.episode_end_frames) > before
    assert len(state["log"]["episode_end_frames"]) == before


@pytest.mark.parametrize("mode", ["actions", "both"])
def test_max_decisions_limits_episodes_in_decisions(mode):
    cfg = config(mode, total_frames=512, learning_starts=8, batch_size=8, max_decisions=3)
    options = dict(options=go_right_options(LENGTH), num_options=2) if mode == "both" else {}
    agent = seeded_dqn(corridor, cfg, **options)
    assert "decision_count" in agent.env.observation_spec.keys()
    log = agent.train()
    assert agent.frames == 512 and agent.gradient_steps > 0
    lengths = set(log.episode_lengths)
    if mode == "actions":
        assert lengths == {3}  # 3 decisions = 3 primitive steps (the end of the corridor is 19 steps away)
    else:
        assert max(lengths) > 3 and max(lengths) <= MAX_STEPS  # an option of up to 19 steps counts as one decision
    returns = agent.evaluate(4, 2 * MAX_STEPS)
    assert len(returns) == 4
    with pytest.raises(ValueError, match="max_decisions"):
        OptionsDQN(corridor, config(mode, max_decisions=0), **options)


def test_collector_is_given_the_env_device(monkeypatch):
    """TorchRL 0.14.1's Collector chooses its env-side CUDA synchronisation from the ``env_device`` argument alone;
    without it a CUDA policy's actions reach a CPU env unsynchronised (garbage actions, seen on an H100). The agent
    must therefore always name the env's device."""
    import torchrl_options.agents.training_loop as loop_mod  # the agents' shared training loop builds the collector

    seen = {}
    real = loop_mod.Collector

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(loop_mod, "Collector", spy)
    agent = seeded_dqn(
        lambda: Corridor(length=4, device="cpu"), OptionsDQNConfig(mode="actions", frames_per_batch=8, learning_starts=8)
    )
    agent.train(total_frames=8)
    assert "env_device" in seen and seen["env_device"] == agent.env.device == torch.device("cpu")
    assert seen["policy_device"] == agent.device


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_agent_on_cpu_env_actions_arrive_intact():
    """A CUDA Q-network driving a CPU env: at every step the env receives exactly the action the policy chose
    (an unsynchronised device-to-host copy shows up here as a mismatch, or as an out-of-range action)."""
    agent = seeded_dqn(lambda: Corridor(LENGTH, max_steps=MAX_STEPS, batch_size=[4], device="cpu"),
                       config("actions", total_frames=3_000, device="cuda"))
    checked = [0]

    def check(agent, batch):
        sent = batch["action"].cpu()
        received = batch["next", "received_action"].cpu()
        assert ((sent >= 0) & (sent < 2)).all()
        torch.testing.assert_close(received, sent, rtol=0, atol=0)
        checked[0] += sent.numel()

    agent.train(callback=check)
    assert checked[0] >= 3_000


def test_optimizer_factory():
    made = []

    def factory(params, lr):
        made.append(lr)
        return torch.optim.Adam(params, lr=lr, fused=True)

    agent = seeded_dqn(corridor, config("actions", total_frames=128, lr=3e-3), optimizer=factory)
    assert made == [3e-3] and agent.optimizer.defaults["fused"] is True
    before = [p.detach().clone() for p in agent.loss_module.parameters()]
    agent.train()
    assert agent.gradient_steps > 0
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.loss_module.parameters()))  # it did step
    default = seeded_dqn(corridor, config("actions"))
    assert isinstance(default.optimizer, torch.optim.Adam) and not default.optimizer.defaults.get("fused")
    with pytest.raises(TypeError, match="optimizer must make a torch.optim.Optimizer, got list"):
        OptionsDQN(corridor, config("actions"), optimizer=lambda params, lr: list(params))


def test_record_evaluation_is_logged_checkpointed_and_leaves_training_unchanged(tmp_path):
    cfg = config("both", total_frames=512, learning_starts=8, batch_size=8, greedy_options=False)

    def run(evaluate: bool) -> OptionsDQN:
        torch.manual_seed(0)  # the agent does not seed torch's global generator: the caller does
        agent = seeded_dqn(corridor, cfg, options=go_right_options(LENGTH), num_options=2)

        def callback(agent, batch):  # evaluations between collector batches, as the Atari recipe does
            if evaluate and agent.frames in (128, 320):
                mean = agent.record_evaluation(num_episodes=4, max_steps=MAX_STEPS)
                assert agent.log.evaluations[-1] == [len(agent.log.episode_returns), agent.frames, mean, 4]

        agent.train(callback=callback)
        return agent

    with_eval, without = run(True), run(False)
    # the evaluation draws from a forked generator: training goes on exactly as without it
    assert with_eval.log.losses == without.log.losses
    assert with_eval.log.episode_returns == without.log.episode_returns
    # the same games every time: evaluating twice in a row gives the same figure (options sample their actions)
    assert with_eval.record_evaluation(4, MAX_STEPS) == with_eval.record_evaluation(4, MAX_STEPS)
    with_eval.save(tmp_path / "ckpt.pt")
    restored = seeded_dqn(corridor, cfg, options=go_right_options(LENGTH), num_options=2)
    restored.load(tmp_path / "ckpt.pt")
    assert restored.log.evaluations == with_eval.log.evaluations and len(restored.log.evaluations) == 4
    with pytest.raises(RuntimeError, match="max_steps"):
        with_eval.record_evaluation(4, max_steps=2)  # no episode can finish in 2 steps
    # with an env that draws from torch's global generator (random no-op starts), evaluate() moves it and
    # record_evaluation() does not
    from torchrl.envs import NoopResetEnv, TransformedEnv

    noop_corridor = lambda: TransformedEnv(Corridor(LENGTH, max_steps=MAX_STEPS), NoopResetEnv(3, random=True))  # noqa
    agent = seeded_dqn(noop_corridor, cfg, options=go_right_options(LENGTH), num_options=2)
    state = torch.get_rng_state().clone()
    agent.evaluate(2, MAX_STEPS)
    assert not torch.equal(state, torch.get_rng_state())
    state = torch.get_rng_state().clone()
    agent.record_evaluation(2, MAX_STEPS)
    assert torch.equal(state, torch.get_rng_state())


def test_intra_option_actions_buffer_holds_every_option_step():
    """With ``intra_option_actions`` and ``option_suffixes`` the buffer holds the same decisions as without, plus one
    one-step transition of the executed primitive action per step an option controlled and the option suffixes of
    each batch (no gradient step: both agents act alike)."""
    counts = []

    def count(agent, batch):
        suffixes = option_suffix_transitions(batch, agent.config.gamma, action_offset=2).shape[0]
        counts.append(int((batch["next", "executed_option"] >= 0).sum()) + suffixes)

    buffers = []
    for intra in (False, True):
        cfg = config("both", total_frames=640, learning_starts=10**9, greedy_options=False, intra_option_actions=intra,
                     option_suffixes=intra, eps_annealing_frames=10**6)
        agent = seeded_dqn(corridor, cfg, options=go_right_options(LENGTH), num_options=2)
        agent.train(callback=count if intra else None)
        buffers.append(agent.replay_buffer[: len(agent.replay_buffer)].exclude("index"))
    plain, with_intra = buffers
    intra = with_intra["intra_option"].reshape(-1)
    assert "intra_option" not in plain.keys()
    decisions = with_intra[~intra].exclude("intra_option")
    assert decisions.shape == plain.shape
    for key in ("observation", "action", "steps_to_next_obs", ("next", "observation"), ("next", "reward")):
        torch.testing.assert_close(decisions[key], plain[key])
    extra = with_intra[intra]
    assert extra.shape[0] == sum(counts) > 0
    steps = extra[extra["action"] < 2]  # the primitive steps; the rest are option suffixes
    assert (steps["steps_to_next_obs"] == 1).all()
    assert (steps["action"] == steps["next", "received_action"]).all()  # the action the corridor received
    suffixes = extra[extra["action"] >= 2]
    assert suffixes.shape[0] > 0 and (suffixes["steps_to_next_obs"] >= 1).all()


def test_intra_option_actions_learn_primitive_values():
    """The agent only ever runs option 0 (go right), so its primitive actions are never decided: their values are
    learned from the steps inside the option with ``intra_option_actions``, and not at all without it."""
    length = 6

    def make():
        return Corridor(length, max_steps=10, batch_size=[4])

    learned = {}
    for intra in (False, True):
        net = torch.nn.Linear(length, 4, bias=False)  # one weight per (cell, augmented action)
        with torch.no_grad():
            net.weight.zero_()
            net.weight[2] = 100.0  # Q(s, option 0) = 100 everywhere: the greedy policy always starts option 0
        cfg = config("both", total_frames=500, frames_per_batch=20, updates_per_batch=4, learning_starts=8,
                     batch_size=16, lr=0.02, eps_init=0.0, eps_end=0.0, hard_update_interval=10**6,
                     intra_option_actions=intra)
        agent = seeded_dqn(make, cfg, options=go_right_options(length), num_options=2, q_network=net)
        agent.train()
        buf = agent.replay_buffer[: len(agent.replay_buffer)]
        decided = buf["action"] if not intra else buf["action"][~buf["intra_option"].reshape(-1)]
        assert (decided == 2).all()  # only option 0 was ever chosen
        learned[intra] = net.weight.detach().clone()
    # without: the primitive rows got no gradient; with: Q(cell 4, right) -> 1, the reward of the terminal step
    assert (learned[False][:2] == 0).all()
    assert abs(float(learned[True][1, length - 2]) - 1.0) < 0.1
    assert (learned[True][0] == 0).all()  # "left" is never taken, inside an option or not


def test_option_suffixes_learn_option_values_where_never_decided():
    """The agent decides only at cell 0 (option 0 runs to the goal); with ``option_suffixes`` the option's value is
    also learned at the cells it passes through, Q(c, option 0) -> gamma ** (cells left - 1); without, never."""
    length, gamma = 6, 0.95

    def make():
        return Corridor(length, max_steps=10, batch_size=[4])

    learned = {}
    for suffixes in (False, True):
        net = torch.nn.Linear(length, 4, bias=False)
        with torch.no_grad():
            net.weight.zero_()
            net.weight[2, 0] = 100.0  # at cell 0 the greedy policy starts option 0, which then runs to the goal
        cfg = config("both", total_frames=600, frames_per_batch=20, updates_per_batch=4, learning_starts=8,
                     batch_size=16, lr=0.02, eps_init=0.0, eps_end=0.0, hard_update_interval=10**6, gamma=gamma,
                     option_suffixes=suffixes)
        agent = seeded_dqn(make, cfg, options=go_right_options(length), num_options=2, q_network=net)
        agent.train()
        buf = agent.replay_buffer[: len(agent.replay_buffer)]
        if suffixes:
            extra = buf[buf["intra_option"].reshape(-1)]
            assert (extra["action"] == 2).all() and (extra["position"] > 0).all()
            buf = buf[~buf["intra_option"].reshape(-1)]
        assert (buf["action"] == 2).all() and (buf["position"] == 0).all()  # decided at cell 0 only
        learned[suffixes] = net.weight.detach().clone()
    assert (learned[False][2, 1:] == 0).all()
    expected = gamma ** torch.arange(length - 2, 0, -1, dtype=torch.float) / gamma  # cells 1 .. length-2
    torch.testing.assert_close(learned[True][2, 1 : length - 1], expected, atol=0.1, rtol=0)
    assert (learned[True][:2] == 0).all()  # the primitive actions were never taken as decisions or stored


def test_intra_option_actions_errors():
    for mode in ("actions", "options"):
        kwargs = {} if mode == "actions" else dict(options=go_right_options(LENGTH), num_options=2)
        with pytest.raises(ValueError, match="intra_option_actions=True needs mode='both'"):
            OptionsDQN(corridor, config(mode, intra_option_actions=True), **kwargs)
    with pytest.raises(ValueError, match="option_suffixes=True needs options"):
        OptionsDQN(corridor, config("actions", option_suffixes=True))
    with pytest.raises(ValueError, match="discount_per='step'"):
        OptionsDQN(corridor, config("both", option_suffixes=True, discount_per="decision"),
                   options=go_right_options(LENGTH), num_options=2)
