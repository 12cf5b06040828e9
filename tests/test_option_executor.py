"""OptionExecutor: step-by-step invariants in every env layout, nesting, seeding and bad input."""
from __future__ import annotations

from functools import partial

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.data import OneHot
from torchrl.envs import Compose, ParallelEnv, SerialEnv, TransformedEnv, check_env_specs
from torchrl.modules import EGreedyModule, QValueActor

from _tiny_envs import BIG, LEFT, RIGHT, Corridor, CheckpointOptions, checkpoint_options, constant_options
from torchrl_options.transforms import OptionExecutor

pytestmark = pytest.mark.usefixtures("torch_single_thread")

L, EVERY, A, K = 8, 3, 2, 2  # corridor length, checkpoint spacing, primitive actions, options


def corridor_with_executor(batch_size=(), max_steps=12, **kwargs):
    env = Corridor(L, max_steps=max_steps, batch_size=batch_size)
    return env.append_transform(OptionExecutor(checkpoint_options(L, EVERY), num_options=K, **kwargs))


def check_invariants(
    data: TensorDict, num_actions: int = A, primitive_actions: bool = True, action_key=("action",)
) -> int:
    """Checks the executor's records step by step, env by env; returns the number of option steps seen.

    ``data`` is [T] or [N, T] (time last), collected with checkpoint options (option 0 goes right, 1 goes
    left, both until a checkpoint cell), which are deterministic so every record can be recomputed.
    ``action_key`` is the executor's input (under a level-2 executor, the action level 2 passed down).
    """
    data = data.reshape(-1, data.shape[-1]).cpu()
    opts = CheckpointOptions(L, EVERY)
    option_steps = 0
    for env_data in data.unbind(0):
        action = env_data[action_key].reshape(-1)
        nxt = env_data["next"]
        executed = nxt["executed_action"].reshape(-1)
        option = nxt["executed_option"].reshape(-1)
        decision = nxt["option_decision"].reshape(-1)
        running_after = nxt["option"].reshape(-1)
        done = nxt["done"].reshape(-1)
        position_after = nxt["position"].reshape(-1)
        # the env received exactly the executed action
        torch.testing.assert_close(nxt["received_action"].reshape(-1), executed)
        for t in range(action.shape[0]):
            if t == 0:
                # the executor's state is part of the data: the first step of a batch continues it
                expect_decision = bool(env_data["option"].reshape(-1)[0] < 0)
            else:
                # the decision for step t is "no option running after step t-1": no option, the option
                # terminated at s_t (evaluated after the step, where it landed) or the episode ended
                prev = int(option[t - 1])
                expect_decision = bool(
                    done[t - 1] or prev < 0 or opts.terminates(position_after[t - 1 : t].unsqueeze(-1)).item()
                )
            assert bool(decision[t]) == expect_decision, f"step {t}: decision {bool(decision[t])}"
            assert bool(running_after[t] < 0) == (bool(done[t]) or option[t] < 0 or opts.terminates(position_after[t : t + 1].unsqueeze(-1)).item())
            if decision[t]:
                a = int(action[t])
                if primitive_actions:
                    assert int(option[t]) == (a - num_actions if a >= num_actions else -1)
                    if a < num_actions:
                        assert int(executed[t]) == a
                else:
                    assert int(option[t]) == a
            else:
                # a running option keeps control whatever the policy drew
                assert int(option[t]) == int(option[t - 1]) >= 0
            if option[t] >= 0:
                option_steps += 1
                assert int(executed[t]) == int(opts.action(option[t]))
    return option_steps


def test_augmented_spec_and_single_env():
    env = corridor_with_executor()
    assert env.action_spec.n == A + K
    assert env.base_env.action_spec.n == A
    check_env_specs(env)
    env.set_seed(0)
    data = env.rollout(200, break_when_any_done=False)  # uniform random augmented actions: epsilon = 1
    assert check_invariants(data) > 20
    assert data["next", "option_decision"].any() and not data["next", "option_decision"].all()
    # the first step of every episode is a decision
    starts = torch.cat([torch.ones(1, dtype=torch.bool), data["next", "done"].reshape(-1)[:-1]])
    assert data["next", "option_decision"][starts].all()


def test_options_only_mode():
    env = corridor_with_executor(primitive_actions=False)
    assert env.action_spec.n == K
    check_env_specs(env)
    data = env.rollout(100, break_when_any_done=False)
    assert (data["next", "executed_option"] >= 0).all()
    check_invariants(data, primitive_actions=False)


def test_termination_evaluated_after_the_step():
    """Option 0 from cell 0 goes right until the checkpoint cell 3, lands there and stops: no overshoot."""
    env = corridor_with_executor(max_steps=50)
    td = env.reset()
    positions = []
    for action in [A + 0, 0, 0, 0]:  # start option 0, then the policy's (ignored) actions
        td["action"] = torch.tensor(action)
        td = env.step(td)
        positions.append(int(td["next", "position"]))
        td = env.step_mdp(td)
    assert positions[:3] == [1, 2, 3]
    assert positions[3] == 2  # at the checkpoint the option has ended: the policy's "left" was executed


def test_partial_reset_keeps_running_options():
    env = corridor_with_executor(batch_size=[3], max_steps=50)
    td = env.reset()
    td["action"] = torch.tensor([A + 0, A + 0, 0])
    td = env.step_mdp(env.step(td))
    assert td["option"].tolist() == [0, 0, -1]
    td["_reset"] = torch.tensor([[True], [False], [False]])
    td = env.reset(td)
    assert td["option"].tolist() == [-1, 0, -1]
    assert td["position"].reshape(-1).tolist() == [0, 1, 0]
    td["action"] = torch.tensor([1, 0, 1])  # env 1 still runs option 0 (right) and ignores its "left"
    td = env.step(td)
    assert td["next", "executed_action"].tolist() == [1, 1, 1]
    assert td["next", "option_decision"].tolist() == [True, False, True]


# Worker processes: "fork" starts in a second where "spawn" re-imports torch for tens of seconds on a loaded
# 2-core machine; the workers run single-threaded, so forking is safe. The spawn variant (which also checks
# that the executor and its options pickle) is marked slow.
def test_serial_env_outside():
    env = TransformedEnv(
        SerialEnv(2, partial(Corridor, L, 12)), OptionExecutor(checkpoint_options(L, EVERY), num_options=K)
    )
    check_env_specs(env)
    env.set_seed(0)
    check_invariants(env.rollout(60, break_when_any_done=False))


def test_parallel_env_outside():
    env = TransformedEnv(
        ParallelEnv(2, partial(Corridor, L, 12), mp_start_method="fork"),
        OptionExecutor(checkpoint_options(L, EVERY), num_options=K),
    )
    try:
        check_env_specs(env)
        env.set_seed(0)
        check_invariants(env.rollout(60, break_when_any_done=False))
    finally:
        env.close()


def stochastic_corridor(max_steps=12):
    """Options with random actions and terminations: their draws come only from the executor's generator."""
    options = constant_options([[0.0, 0.0], [1.0, -1.0]], [0.0, -1.0])
    return Corridor(L, max_steps=max_steps).append_transform(OptionExecutor(options, num_options=K))


def _inside_parallel_workers(start_method):
    # worker 0: deterministic checkpoint options (invariants); worker 1: stochastic options (seeding)
    env = ParallelEnv(
        2, [partial(corridor_with_executor, (), 12), partial(stochastic_corridor, 12)], mp_start_method=start_method
    )
    try:
        check_env_specs(env)
        runs = []
        for seed in (0, 0, 1):
            env.set_seed(seed)
            torch.manual_seed(0)  # the random policy of the rollout draws from the main process' generator
            runs.append(env.rollout(60, break_when_any_done=False))
    finally:
        env.close()
    check_invariants(runs[0][0])
    # each worker seeds its executor through env.set_seed: same seed, same draws; another seed, other draws
    for key in ("executed_action", "option_decision"):
        assert (runs[0]["next", key] == runs[1]["next", key]).all()
    assert (runs[0]["next", "executed_action"][1] != runs[2]["next", "executed_action"][1]).any()


def test_inside_parallel_workers_and_reproducible():
    _inside_parallel_workers("fork")


@pytest.mark.slow
def test_inside_parallel_workers_spawn():
    _inside_parallel_workers("spawn")


def test_collector_with_qvalue_egreedy_policy():
    env = corridor_with_executor(batch_size=[3])
    spec = env.full_action_spec_unbatched["action"]
    actor = QValueActor(torch.nn.LazyLinear(spec.n), in_keys=["observation"], spec=spec)
    policy = TensorDictSequential(actor, EGreedyModule(spec, eps_init=1.0, eps_end=1.0))
    collector = Collector(env, policy, frames_per_batch=60, total_frames=120, auto_register_policy_transforms=False)
    collector.set_seed(0)
    batches = [batch.clone() for batch in collector]
    collector.shutdown()
    data = torch.cat(batches, -1)
    assert data.shape == (3, 40)
    # the policy draws an action at every step; on non-decision steps it is ignored
    assert check_invariants(data) > 10
    ignored = ~data["next", "option_decision"]
    assert (data["action"][ignored] != data["next", "executed_action"][ignored]).any()


def _multisync(monkeypatch, start_method):
    import torch.multiprocessing as mp
    from torchrl.collectors import _multi_base

    monkeypatch.setattr(_multi_base, "_get_mp_ctx", lambda *args, **kwargs: mp.get_context(start_method))
    collector = MultiSyncCollector(
        [partial(corridor_with_executor, (), 12)] * 2, policy=None, frames_per_batch=40, total_frames=80
    )
    collector.set_seed(0)
    try:
        batches = [batch.clone() for batch in collector]
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.shape[0] == 2
    check_invariants(torch.cat(batches, -1))


def test_multisync_collector(monkeypatch):
    _multisync(monkeypatch, "fork")


@pytest.mark.slow
def test_multisync_collector_spawn(monkeypatch):
    _multisync(monkeypatch, "spawn")


def _stochastic_records(seed, executor_seed=None, policy_draws=False):
    """Executed actions and decisions of stochastic options (always asking for option 0)."""
    executor = OptionExecutor(constant_options([[0.0, 0.0], [1.0, -1.0]], [0.0, 0.0]), num_options=K)
    env = Corridor(L, max_steps=50, batch_size=[4]).append_transform(executor)
    if executor_seed is not None:
        executor.set_seed(executor_seed)
    torch.manual_seed(seed)
    env.set_seed(seed)
    td = env.reset()
    records = []
    for _ in range(30):
        td["action"] = torch.full((4,), A + 0)  # always ask for option 0; it only starts at decisions
        if policy_draws:
            torch.rand(3)  # other code drawing from torch's default generator
        td = env.step(td)
        records.append(td["next", "executed_action"].clone())
        records.append(td["next", "option_decision"].clone())
        td = env.step_mdp(td)
    return torch.stack([r.long() for r in records])


def test_seeding_reproducible_and_distinct():
    """Stochastic options draw from torch's default generator (TorchRL's convention), or from a private one."""
    with torch.random.fork_rng():
        # torch.manual_seed makes a run reproducible; other seeds give other draws
        assert (_stochastic_records(1) == _stochastic_records(1)).all()
        assert (_stochastic_records(1) != _stochastic_records(2)).any()
        # executor.set_seed: the draws follow its own seed, whatever the global seed or other code's draws
        private = _stochastic_records(1, executor_seed=7)
        assert (private == _stochastic_records(2, executor_seed=7, policy_draws=True)).all()
        assert (private != _stochastic_records(1, executor_seed=8)).any()
        # the private generator is not shared by a clone appended to another env: it restarts from the seed
        executor = OptionExecutor(constant_options([[0.0, 0.0], [1.0, -1.0]], [0.0, 0.0]), num_options=K)
        executor.set_seed(3)
        env = Corridor(L, max_steps=50, batch_size=[4]).append_transform(executor)
        state = executor.generator.get_state()
        env.rollout(5)
        assert not torch.equal(state, executor.generator.get_state())
        clone = executor.clone()
        Corridor(L, max_steps=50, batch_size=[4]).append_transform(clone)
        assert torch.equal(clone.generator.get_state(), state)
        # re-seeding a used executor restarts its draws (a fixed number per step)
        executor.set_seed(3)
        assert torch.equal(executor.generator.get_state(), state)
        env.rollout(5, break_when_any_done=False)
        after = executor.generator.get_state()
        assert not torch.equal(after, state)
        executor.set_seed(3)
        env.rollout(5, break_when_any_done=False)
        assert torch.equal(executor.generator.get_state(), after)
        with pytest.raises(TypeError, match="seed"):
            executor.set_seed(1.5)
        executor.set_seed(None)
        assert executor.generator is None


def test_stochastic_termination_rate():
    # termination logit 0 at every state: each option step ends the option with probability 1/2
    env = Corridor(L, max_steps=1000, batch_size=[64]).append_transform(
        OptionExecutor(constant_options([[0.0, 0.0], [0.0, 0.0]], [0.0, 0.0]), num_options=K, primitive_actions=False)
    )
    env.set_seed(0)
    data = env.rollout(50, break_when_any_done=False)
    ended = (data["next", "option"] < 0).float().mean()
    assert abs(ended.item() - 0.5) < 0.03


def test_greedy_options():
    env = Corridor(L, max_steps=50, batch_size=[8]).append_transform(
        OptionExecutor(constant_options([[0.0, 0.5], [0.5, 0.0]], [-BIG, -BIG]), num_options=K, greedy=True)
    )
    data = env.rollout(10, policy=lambda td: td.set("action", torch.tensor([A + 0] * 4 + [A + 1] * 4)))
    assert (data["next", "executed_action"][:4] == 1).all() and (data["next", "executed_action"][4:] == 0).all()


def scripted_policy(actions):
    actions = iter(actions)
    return lambda td: td.set("action", torch.tensor(next(actions)))


# ------------------------------------------------------------------------------------------- nesting
class OuterOption(torch.nn.Module):
    """One level-2 option over the level-1 space {left, right, option 0, option 1}: always invoke level-1
    option 0 (right to the next checkpoint); terminate at any cell >= 4 (cells 4 and 5 are passed while the
    level-1 option runs, so call-and-return must postpone the check to the checkpoint 6)."""

    def forward(self, position):
        batch = position.shape[:-1]
        logits = torch.full((*batch, 1, A + K), -BIG)
        logits[..., 0, A + 0] = BIG
        term = torch.where(position >= 4, BIG, -BIG).float()
        return logits, term


def nested_env(layout: str, max_steps: int = 30):
    inner = OptionExecutor(checkpoint_options(L, EVERY), num_options=K)
    outer = OptionExecutor(
        TensorDictModule(OuterOption(), ["position"], ["option_logits", "termination_logits"]), num_options=1, level=2
    )
    base = Corridor(L, max_steps=max_steps)
    if layout == "compose":
        return TransformedEnv(base, Compose(inner, outer))
    return TransformedEnv(TransformedEnv(base, inner), outer)


@pytest.mark.parametrize("layout", ["compose", "stacked"])
def test_nested_call_and_return(layout):
    env = nested_env(layout)
    assert env.action_spec.n == A + K + 1
    check_env_specs(env)
    # start the level-2 option, then always "left" (ignored while an option runs)
    data = env.rollout(8, policy=scripted_policy([A + K + 0] + [0] * 7))
    pos = data["next", "position"].reshape(-1).tolist()
    # level-2 option -> level-1 option 0 runs 0..3, returns, level-2 continues (3 < 4) -> option 0 runs 3..6,
    # returns at 6 >= 4: level-2 terminates there, not at 4 or 5
    assert pos[:6] == [1, 2, 3, 4, 5, 6]
    assert data["next", "executed_option_2"][:6].tolist() == [0] * 6
    assert data["next", "option_2"][:6].tolist() == [0] * 5 + [-1]
    assert data["next", "option_decision_2"].tolist()[:7] == [True] + [False] * 5 + [True]
    # the level-2 option acted (passed level-1 option 0 down) only when level 1 was waiting for an action
    assert data["next", "option_decision"][:6].tolist() == [True, False, False, True, False, False]
    assert (data["next", "executed_action_2"][data["next", "option_decision"][:6].nonzero()] == A + 0).all()


def test_nested_random_policy_outer_never_terminates_while_inner_runs():
    env = nested_env("compose", max_steps=20)
    env.set_seed(0)
    data = env.rollout(300, break_when_any_done=False)
    check_invariants(data, action_key=("next", "executed_action_2"))  # level 1 under level 2
    nxt = data["next"]
    inner_running_after = (nxt["option"] >= 0) & ~nxt["done"].squeeze(-1)
    outer_option = nxt["executed_option_2"]
    assert (inner_running_after & (outer_option >= 0)).sum() > 5
    # an outer option never terminates (nor is replaced) while the inner option it invoked still runs
    assert (nxt["option_2"][inner_running_after & (outer_option >= 0)] == outer_option[inner_running_after & (outer_option >= 0)]).all()
    # the outer level decides only when the inner level is free
    running_before = data["option"] >= 0
    assert not (data["next", "option_decision_2"] & running_before).any()


# ------------------------------------------------------------------------------------------ bad input
def test_non_categorical_action_spec():
    env = Corridor(L)
    env.action_spec = OneHot(2)
    with pytest.raises(TypeError, match="Categorical"):
        env.append_transform(OptionExecutor(checkpoint_options(L), num_options=K))


def test_options_module_outputs_checked():
    with pytest.raises(ValueError, match="termination_logits"):
        OptionExecutor(TensorDictModule(torch.nn.Identity(), ["position"], ["option_logits"]), num_options=K)
    env = Corridor(L).append_transform(OptionExecutor(checkpoint_options(L), num_options=3))  # wrote K=2
    with pytest.raises(ValueError, match=r"K=3, A=2"):
        env.rollout(2)
    wrong_a = constant_options(torch.zeros(K, 3), torch.zeros(K))
    env = Corridor(L).append_transform(OptionExecutor(wrong_a, num_options=K))
    with pytest.raises(ValueError, match=r"A=2"):
        env.rollout(2)


def test_options_for_another_observation_size_raise_at_the_door():
    from torchrl_options.modules import OptionsMLP

    options = OptionsMLP(L + 3, 2, K, num_cells=[4], in_keys=["observation"])  # built for a longer corridor
    env = Corridor(L).append_transform(OptionExecutor(options, num_options=K))
    with pytest.raises(ValueError, match=rf"shapes \{{'observation': \({L},\)\}}.*built for this env's observation size"):
        env.rollout(3, break_when_any_done=False)


def test_action_out_of_range():
    env = corridor_with_executor()
    td = env.reset()
    td["action"] = torch.tensor(A + K)
    with pytest.raises(ValueError, match=r"\[0, 4\)"):
        env.step(td)
    # negative indices too (the range check is the lookup of the started option, which does not wrap them)
    env = corridor_with_executor(batch_size=[3])
    td = env.reset()
    td["action"] = torch.tensor([0, -1, A])
    expected = r"expected integers in \[0, 4\) \(2 primitive actions \+ 2 options\), got values in \[-1, 2\]"
    with pytest.raises(ValueError, match=expected):
        env.step(td)


class NaNOptions(torch.nn.Module):
    """Options whose outputs at cell ``bad_cell`` (and only there) are replaced by ``logits`` / ``term``."""

    def __init__(self, logits, term, bad_cell=2):
        super().__init__()
        self.logits, self.term, self.bad_cell = torch.as_tensor(logits), torch.as_tensor(term), bad_cell

    def forward(self, position):
        batch = position.shape[:-1]
        at_bad = (position == self.bad_cell).unsqueeze(-1)  # [..., 1, 1]
        logits = torch.where(at_bad, self.logits, torch.zeros(K, A)).expand(*batch, K, A)
        term = torch.where(at_bad.squeeze(-1), self.term, torch.full((K,), -BIG)).expand(*batch, K)
        return logits, term


def nan_corridor(logits, term):
    options = TensorDictModule(NaNOptions(logits, term), ["position"], ["option_logits", "termination_logits"])
    return Corridor(L, max_steps=50).append_transform(OptionExecutor(options, num_options=K))


NAN = float("nan")
INF = float("inf")


@pytest.mark.parametrize(
    "logits, term, match",
    [
        ([[NAN, 0.0], [0.0, 0.0]], [0.0, 0.0], r"NaN in 'option_logits'"),
        ([[0.0, 0.0], [0.0, 0.0]], [0.0, NAN], r"NaN in 'termination_logits'"),
        ([[INF, 0.0], [0.0, 0.0]], [0.0, 0.0], r"without a valid softmax"),
        ([[0.0, 0.0], [-INF, -INF]], [0.0, 0.0], r"without a valid softmax"),
    ],
)
def test_options_writing_nan_raise(logits, term, match):
    """NaN outputs (or logits without a softmax) do not silently execute the last action: the step landing there
    raises, naming the entry."""
    env = nan_corridor(logits, term)
    td = env.reset()
    td["action"] = torch.tensor(RIGHT)
    td = env.step_mdp(env.step(td))  # cell 1: fine
    td["action"] = torch.tensor(RIGHT)
    with pytest.raises(ValueError, match=match):
        env.step(td)  # lands on cell 2


@pytest.mark.parametrize(
    "logits, term, match",
    [
        ([[NAN, 0.0], [0.0, 0.0]], [0.0, 0.0], r"NaN in 'option_logits'"),
        ([[0.0, 0.0], [0.0, 0.0]], [NAN, 0.0], r"NaN in 'termination_logits'"),
        ([[INF, -INF], [0.0, 0.0]], [0.0, 0.0], r"without a valid softmax"),
        # infinities of both signs in different rows (and terminations) are valid for argmax: no error
        ([[INF, 0.0], [-INF, 0.0]], [INF, -INF], None),
    ],
)
def test_greedy_options_writing_nan_raise(logits, term, match):
    """With ``greedy=True`` the options act by argmax: NaN (or a row holding +inf and -inf) raises at the step
    landing there, infinite logits elsewhere do not."""
    options = TensorDictModule(NaNOptions(logits, term), ["position"], ["option_logits", "termination_logits"])
    env = Corridor(L, max_steps=50).append_transform(OptionExecutor(options, num_options=K, greedy=True))
    td = env.reset()
    td["action"] = torch.tensor(RIGHT)
    td = env.step_mdp(env.step(td))  # cell 1: fine
    td["action"] = torch.tensor(RIGHT)
    if match is None:
        assert int(env.step(td)["next", "position"]) == 2
    else:
        with pytest.raises(ValueError, match=match):
            env.step(td)  # lands on cell 2


def test_infinite_logits_that_are_valid_do_not_raise():
    """-inf masks an action, +inf / -inf termination logits mean always / never: all valid."""
    env = Corridor(L, max_steps=50).append_transform(
        OptionExecutor(constant_options([[-INF, 0.0], [0.0, -INF]], [INF, -INF]), num_options=K)
    )
    env.set_seed(0)
    torch.manual_seed(0)
    data = env.rollout(40, break_when_any_done=False)
    ran = data["next", "executed_option"] >= 0
    assert ran.any()
    # option 0 only goes right, option 1 only left, wherever they run
    option, executed = data["next", "executed_option"][ran], data["next", "executed_action"][ran]
    assert (executed == torch.where(option == 0, RIGHT, LEFT)).all()
    # option 0 always terminates after its step, option 1 never (until the episode ends)
    nxt = data["next"]
    assert (nxt["option"][nxt["executed_option"] == 0] == -1).all()
    assert ((nxt["option"] == 1) | nxt["done"].squeeze(-1))[nxt["executed_option"] == 1].all()


@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: OptionExecutor(checkpoint_options(L), num_options=True), ValueError, "num_options"),
        (lambda: OptionExecutor(checkpoint_options(L), num_options=2.0), ValueError, "num_options"),
        (lambda: OptionExecutor(checkpoint_options(L), num_options=K, level=0), ValueError, "level"),
        (lambda: OptionExecutor(checkpoint_options(L), num_options=K, greedy="yes"), TypeError, "greedy"),
        (lambda: OptionExecutor(CheckpointOptions(L), num_options=K), TypeError, "TensorDict module"),
        (lambda: OptionExecutor(checkpoint_options(L), num_options=K, option_key="executed_option"), ValueError,
         "must differ"),
        # keys checked when the executor is appended
        (lambda: Corridor(L).append_transform(OptionExecutor(checkpoint_options(L, in_key="pos"), num_options=K)),
         ValueError, r"reads \['pos'\], which the env does not observe"),
        (lambda: Corridor(L).append_transform(OptionExecutor(checkpoint_options(L), num_options=K, action_key="act")),
         ValueError, "action entry 'act'"),
        (lambda: Corridor(L).append_transform(OptionExecutor(checkpoint_options(L), num_options=K, level=2)),
         ValueError, "running-option entry 'option'"),
    ],
)
def test_bad_construction(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_step_without_reset_state():
    env = corridor_with_executor()
    td = env.reset()
    del td["option_actions"]
    td["action"] = torch.tensor(0)
    with pytest.raises(ValueError, match="'option_actions' is missing .* Reset the env first"):
        env.step(td)


def test_public_apis_only():
    """No TensorDict / torch internals: they change between releases (the reason for narrow version pins)."""
    import inspect

    import torchrl_options.transforms.option_executor as module

    source = inspect.getsource(module)
    for private in ("_get_str", "_set_str", "_get_tuple", "_set_tuple", "._version", "._kwargs", "_assert_async",
                    '__dict__["set_seed"]'):
        assert private not in source, private


def _deferred_bad_input(device):
    """Bad input with the checks of an accelerator: the step runs, a later step (or the next reset) raises, once."""
    env = Corridor(L, max_steps=50, batch_size=[3], device=device).append_transform(
        OptionExecutor(checkpoint_options(L).to(device), num_options=K)
    )
    td = env.reset()
    td["action"] = torch.tensor([0, A + K, 1], device=device)
    td = env.step_mdp(env.step(td))  # runs (the action clamped into range: option K - 1), flagged on the device
    assert td["executed_option"].tolist() == [-1, K - 1, -1]
    with pytest.raises(ValueError, match=r"expected integers in \[0, 4\).*earlier step on"):
        for _ in range(50):  # raises as soon as the flag reached the host
            td["action"] = torch.zeros(3, dtype=torch.long, device=device)
            td = env.step_mdp(env.step(td))
    env.reset()  # reported once
    # NaN options: the next reset at the latest raises
    module = NaNOptions([[NAN, 0.0], [0.0, 0.0]], [0.0, 0.0], bad_cell=0)
    module.logits, module.term = module.logits.to(device), module.term.to(device)
    options = TensorDictModule(module, ["position"], ["option_logits", "termination_logits"])
    env = Corridor(L, max_steps=50, device=device).append_transform(OptionExecutor(options, num_options=K))
    env.reset()  # flags the NaN written at cell 0
    with pytest.raises(ValueError, match="NaN .* at an earlier step"):
        env.reset()
    # valid input: same invariants as with immediate checks
    env = Corridor(L, max_steps=12, batch_size=[3], device=device).append_transform(
        OptionExecutor(checkpoint_options(L, EVERY).to(device), num_options=K)
    )
    torch.manual_seed(0)
    check_invariants(env.rollout(60, break_when_any_done=False))


def test_deferred_checks_logic_on_cpu(monkeypatch):
    """The deferred (CUDA) checks, forced on the CPU: same behaviour, without CUDA events or pinned memory."""
    from torchrl_options.transforms import option_executor

    monkeypatch.setattr(option_executor, "_defers_checks", lambda device: True)
    _deferred_bad_input("cpu")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_bad_input_raises_without_a_sync_per_step():
    """On CUDA the range and NaN checks do not wait for the device: a later step (at the latest the next reset)
    raises."""
    _deferred_bad_input("cuda")


# ------------------------------------------------------------------------------- options evaluated once
class CountingOptions(torch.nn.Module):
    """One option whose action depends on the state (right below cell 4, left from it) and that never
    terminates; counts its forward calls. ``flip`` (a buffer) swaps left and right."""

    def __init__(self):
        super().__init__()
        self.calls = 0
        self.register_buffer("flip", torch.zeros(()))

    def forward(self, position):
        self.calls += 1
        right = (position.squeeze(-1) < 4) ^ self.flip.bool()
        logits = torch.stack([torch.where(right, -BIG, BIG), torch.where(right, BIG, -BIG)], -1).unsqueeze(-2)
        return logits, torch.full((*position.shape[:-1], 1), -BIG)


def counting_corridor(batch_size=()):
    options = CountingOptions()
    env = Corridor(L, max_steps=None, batch_size=batch_size).append_transform(
        OptionExecutor(TensorDictModule(options, ["position"], ["option_logits", "termination_logits"]), num_options=1)
    )
    return env, options


def test_options_run_once_per_step():
    """The outputs computed for the termination at s_{t+1} give the action at t+1: one forward per step."""
    env, options = counting_corridor(batch_size=[4])
    env.set_seed(0)
    policy = scripted_policy([[LEFT, LEFT, A + 0, LEFT]] * 10)  # no env reaches the end: no reset
    data = env.rollout(10, policy=policy, break_when_any_done=False)
    assert not data["next", "done"].any()
    # + the reset
    assert options.calls == 10 + 1
    # env 2 runs the option: right up to cell 4, then left (state-dependent actions from the reused outputs)
    assert data["next", "position"][2].squeeze(-1).tolist() == [1, 2, 3, 4, 3, 4, 3, 4, 3, 4]


def test_option_actions_are_state_in_the_tensordict():
    """Each option's action at s_t is drawn when s_t is observed and carried in the tensordict, as TorchRL's state."""
    env, options = counting_corridor()
    check_env_specs(env)
    td = env.reset()
    assert td["option_actions"].tolist() == [RIGHT]  # the option's action at cell 0
    td["action"] = torch.tensor(A + 0)  # start the option at cell 0: right
    td = env.step_mdp(env.step(td))
    assert int(td["position"]) == 1 and int(td["option"]) == 0 and td["option_actions"].tolist() == [RIGHT]
    # the executed action is the one carried in the tensordict
    td["option_actions"] = torch.tensor([LEFT])
    td["action"] = torch.tensor(RIGHT)  # ignored: the option runs
    td = env.step_mdp(env.step(td))
    assert int(td["executed_action"]) == LEFT and int(td["position"]) == 0
    # the options' parameters (here a buffer) change in place (training, load_state_dict): the action at the
    # current state was drawn before; the next states use the new parameters
    options.flip.fill_(1.0)
    for expected in (RIGHT, LEFT):
        td["action"] = torch.tensor(RIGHT)
        td = env.step_mdp(env.step(td))
        assert int(td["executed_action"]) == expected
    assert int(td["position"]) == 0


def test_inference_mode_and_float64_options():
    """Under torch.inference_mode (tensors without version counters) the data are those of no_grad."""
    def rollout(mode, dtype=torch.float32):
        logits = torch.tensor([[0.0, 0.0], [1.0, -1.0]], dtype=dtype)
        options = constant_options(logits, torch.tensor([0.0, -1.0], dtype=dtype))
        env = Corridor(L, max_steps=12, batch_size=[4]).append_transform(OptionExecutor(options, num_options=K))
        env.set_seed(0)
        with torch.random.fork_rng():  # the random policy's draws; other tests' global RNG state is kept
            torch.manual_seed(0)
            with mode():
                return env.rollout(40, break_when_any_done=False)

    expected = rollout(torch.no_grad)
    for data in (rollout(torch.inference_mode), rollout(torch.no_grad, torch.float64)):
        for key in ("executed_action", "executed_option", "option_decision", "option"):
            assert (data["next", key] == expected["next", key]).all()


# ------------------------------------------------------------------------------- the options' call
def test_compiled_options_give_the_same_records():
    """``compile_options``: the options run through ``torch.compile`` (the eager backend here: no C++ build); the
    records are those of the plain TensorDict call, and the compiled module is a runtime cache, not pickled."""
    import pickle

    def rollout(compile_options):
        env = corridor_with_executor(batch_size=[3], compile_options=compile_options)
        with torch.random.fork_rng():
            torch.manual_seed(0)
            return env, env.rollout(30, break_when_any_done=False)

    _, expected = rollout(False)
    env, data = rollout({"backend": "eager"})
    executor = env.transform
    assert "_compiled_options" in executor.__dict__ and executor.compile_options == {"backend": "eager"}
    for key in ("executed_action", "executed_option", "option_decision", "option"):
        assert (data["next", key] == expected["next", key]).all()
    assert "_compiled_options" not in pickle.loads(pickle.dumps(executor)).__dict__
    with pytest.raises(TypeError, match="compile_options must be a bool or a dict"):
        OptionExecutor(checkpoint_options(L), num_options=K, compile_options="eager")
