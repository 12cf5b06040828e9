"""OptionExecutor with nested and multiple done entries (issue 51 part 5), as TorchRL's StepCounter handles them.

Two tiny natively batched envs whose episodes end at random (so sub-envs reset at different times): one whose
done entries live under ``("agent", ...)`` only, and a two-agent one with a root ``"done"`` ``[N, 1]`` beside
per-agent ``("agents", "done")`` ``[N, 2, 1]`` (an agent is done at random and stays done; the episode ends when
both are). The options are deterministic (option ``k`` always takes action ``k``; it terminates on a position
multiple of 3), so the test recomputes, in plain Python, every record of the executor from the observed data and
compares, step by step, in a real :class:`~torchrl.collectors.Collector` and through manual partial resets.
"""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, check_env_specs

from torchrl_options.transforms import OptionExecutor
from torchrl_options.transforms.keys import FlagToState, done_keys_for

pytestmark = pytest.mark.usefixtures("torch_single_thread")

A, K, BIG = 3, 2, 1e9  # primitive actions, options


def _flag(shape):
    return Categorical(2, shape=shape, dtype=torch.bool)


class NestedDoneWalk(EnvBase):
    """A counter moved by the action (action ``a``: ``+a+1``); every entry, done ones included, under ``"agent"``
    (TorchRL merges a partial reset node by node: the data of a done entry lives next to it)."""

    batch_locked = True

    def __init__(self, num_envs: int = 4, end_prob: float = 0.15, seed: int = 0):
        super().__init__(batch_size=torch.Size([num_envs]))
        n = num_envs
        self.observation_spec = Composite(
            agent=Composite(
                observation=Unbounded((n, 1)), received_action=Unbounded((n,), dtype=torch.int64), shape=(n,)
            ),
            shape=(n,),
        )
        self.full_action_spec = Composite(agent=Composite(action=Categorical(A, shape=(n,)), shape=(n,)), shape=(n,))
        self.full_reward_spec = Composite(agent=Composite(reward=Unbounded((n, 1)), shape=(n,)), shape=(n,))
        self.done_spec = Composite(
            agent=Composite(done=_flag((n, 1)), terminated=_flag((n, 1)), shape=(n,)), shape=(n,)
        )
        self.end_prob = end_prob
        self.pos = torch.zeros(n, 1)
        self.rng = torch.Generator().manual_seed(seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get(("agent", "_reset"), None)
        mask = torch.ones(self.pos.shape, dtype=torch.bool) if reset is None else reset.reshape(self.pos.shape)
        self.pos = torch.where(mask, 0.0, self.pos)
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {
                "agent": {
                    "observation": self.pos.clone(),
                    "received_action": torch.full(self.batch_size, -1),
                    "done": done,
                    "terminated": done.clone(),
                }
            },
            self.batch_size,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(("agent", "action"))
        self.pos = self.pos + action.unsqueeze(-1).float() + 1
        ended = torch.rand(*self.batch_size, 1, generator=self.rng) < self.end_prob
        return TensorDict(
            {
                "agent": {
                    "observation": self.pos.clone(),
                    "received_action": action.clone(),
                    "reward": self.pos.clone(),
                    "done": ended,
                    "terminated": ended.clone(),
                }
            },
            self.batch_size,
        )

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(seed)


class TwoAgentWalk(EnvBase):
    """Two agents with counters; each is done at random and stays done; the episode ends when both are."""

    batch_locked = True

    def __init__(self, num_envs: int = 4, end_prob: float = 0.2, seed: int = 0):
        super().__init__(batch_size=torch.Size([num_envs]))
        n = num_envs
        agents = Composite(
            observation=Unbounded((n, 2, 1)), received_action=Unbounded((n, 2), dtype=torch.int64), shape=(n, 2)
        )
        self.observation_spec = Composite(agents=agents, shape=(n,))
        self.full_action_spec = Composite(
            agents=Composite(action=Categorical(A, shape=(n, 2)), shape=(n, 2)), shape=(n,)
        )
        self.full_reward_spec = Composite(agents=Composite(reward=Unbounded((n, 2, 1)), shape=(n, 2)), shape=(n,))
        self.full_done_spec = Composite(
            done=_flag((n, 1)),
            terminated=_flag((n, 1)),
            agents=Composite(done=_flag((n, 2, 1)), terminated=_flag((n, 2, 1)), shape=(n, 2)),
            shape=(n,),
        )
        self.end_prob = end_prob
        self.pos = torch.zeros(n, 2, 1)
        self.agent_done = torch.zeros(n, 2, 1, dtype=torch.bool)
        self.rng = torch.Generator().manual_seed(seed)

    def _out(self, received: torch.Tensor, reward: bool = True) -> TensorDict:
        episode = self.agent_done.all(1)
        out = TensorDict(
            {
                "done": episode,
                "terminated": episode.clone(),
                "agents": TensorDict(
                    {
                        "observation": self.pos.clone(),
                        "received_action": received,
                        "done": self.agent_done.clone(),
                        "terminated": self.agent_done.clone(),
                    },
                    (*self.batch_size, 2),
                ),
            },
            self.batch_size,
        )
        if reward:
            out["agents", "reward"] = self.pos.clone()
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(self.batch_size, dtype=torch.bool) if reset is None else reset.reshape(self.batch_size)
        mask = mask.reshape(-1, 1, 1)
        self.pos = torch.where(mask, 0.0, self.pos)
        self.agent_done = torch.where(mask, False, self.agent_done)
        return self._out(torch.full((*self.batch_size, 2), -1), reward=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(("agents", "action"))
        self.pos = self.pos + action.unsqueeze(-1).float() + 1
        ends = torch.rand(*self.batch_size, 2, 1, generator=self.rng) < self.end_prob
        self.agent_done = self.agent_done | ends
        return self._out(action.clone())

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(seed)


class FixedOptions(nn.Module):
    """Option ``k`` always takes action ``k`` and terminates where the counter is a multiple of 3."""

    def forward(self, observation):
        batch = observation.shape[:-1]
        logits = torch.full((K, A), -BIG)
        logits[torch.arange(K), torch.arange(K)] = BIG
        term = torch.where(observation.remainder(3) == 0, BIG, -BIG).expand(*batch, K)
        return logits.expand(*batch, K, A), term


RECORDS = ("option", "option_actions", "executed_action", "executed_option", "option_decision")


def nested_executor(group: str, **kwargs) -> OptionExecutor:
    """An executor whose action, options' input and records all live under ``group``."""
    options = TensorDictModule(FixedOptions(), [(group, "observation")], ["option_logits", "termination_logits"])
    keys = {f"{name if name != 'option_decision' else 'decision'}_key": (group, name) for name in RECORDS}
    return OptionExecutor(options, K, greedy=True, action_key=(group, "action"), **keys, **kwargs)


def nested_env(**kwargs):
    return NestedDoneWalk(**kwargs).append_transform(nested_executor("agent"))


def two_agent_env(**kwargs):
    return TwoAgentWalk(**kwargs).append_transform(nested_executor("agents"))


def expected_records(option_at_start, action, obs_after, done_after):
    """The executor's records of one env (or agent) over time, recomputed from the data: start an option at a
    decision, keep it while it runs (taking action k), end it where it terminates or where a done entry is set."""
    running = int(option_at_start)
    out = {"decision": [], "option": [], "executed": [], "running_after": []}
    for t in range(len(action)):
        decision = running < 0
        option = (int(action[t]) - A if int(action[t]) >= A else -1) if decision else running
        executed = option if option >= 0 else int(action[t])
        ends = option < 0 or float(obs_after[t]) % 3 == 0 or bool(done_after[t])
        running = -1 if ends else option
        for key, value in zip(out, (decision, option, executed, running)):
            out[key].append(value)
    return out


def column(batch, group: str, i: int, j: int | None = None) -> TensorDict:
    """The records of env ``i`` (and agent ``j``) of a collected batch ``[N, T]``, as a [T] TensorDict."""
    pick = (lambda x: x[i]) if j is None else (lambda x: x[i][:, j])
    now, nxt = batch[group], batch["next", group]
    return TensorDict(
        {
            "option": pick(now["option"]),
            "action": pick(now["action"]),
            "next": {name: pick(nxt[name]) for name in (*RECORDS, "received_action", "observation")},
        },
        [batch.shape[1]],
    )


def check_against_reference(data: TensorDict, done_after: torch.Tensor) -> None:
    """The executor's records in ``data`` (one env or agent, [T]) equal those recomputed from its observations."""
    nxt = data["next"]
    expected = expected_records(data["option"][0], data["action"], nxt["observation"].reshape(-1), done_after)
    assert nxt["option_decision"].tolist() == expected["decision"]
    assert nxt["executed_option"].tolist() == expected["option"]
    assert nxt["executed_action"].tolist() == expected["executed"]
    assert nxt["received_action"].tolist() == expected["executed"]  # the env received exactly that
    assert nxt["option"].tolist() == expected["running_after"]


def test_nested_done_key_in_a_collector():
    env = nested_env()
    check_env_specs(env)
    assert env.transform.done_keys == [("agent", "done")]
    torch.manual_seed(0)
    collector = Collector(env, None, frames_per_batch=4 * 60, total_frames=4 * 120)
    n_batches = ends = starts = 0
    for batch in collector:
        n_batches += 1
        for i in range(batch.shape[0]):
            data = column(batch, "agent", i)
            done_after = batch["next", "agent", "done"][i].reshape(-1)
            ends += int(done_after.sum())
            starts += int((data["next", "executed_option"] >= 0).sum())
            check_against_reference(data, done_after)
            # after a done, the collector reset that env alone: its next step starts with no option
            after_done = done_after[:-1].nonzero().flatten() + 1
            assert (data["option"][after_done] == -1).all()
    collector.shutdown()
    assert n_batches == 2 and ends > 20 and starts > 50  # partial resets and options did happen


def test_nested_reset_key_resets_exactly_the_flagged_envs():
    env = nested_env(num_envs=3, end_prob=0.0)
    td = env.reset()
    td["agent", "action"] = torch.tensor([A + 1, A + 1, A + 1])  # start option 1 (+2 a step: 2, 4, 6, where it ends)
    td = env.step_mdp(env.step(td))
    td["agent", "action"] = torch.tensor([0, 0, 0])
    td = env.step_mdp(env.step(td))
    assert td["agent", "option"].tolist() == [1, 1, 1]
    assert td["agent", "option_decision"].tolist() == [False, False, False]
    td["agent", "_reset"] = torch.tensor([[False], [True], [False]])
    td = env.reset(td)
    assert td["agent", "option"].tolist() == [1, -1, 1]
    assert td["agent", "executed_option"].tolist() == [1, -1, 1]
    assert td["agent", "observation"].reshape(-1).tolist() == [4.0, 0.0, 4.0]


def test_nested_done_ends_the_option():
    env = nested_env(num_envs=2, end_prob=0.0)
    td = env.reset()
    td["agent", "action"] = torch.tensor([A + 1, A + 1])
    td = env.step(td)
    assert td["next", "agent", "option"].tolist() == [1, 1]
    td = env.step_mdp(td)
    env.base_env.end_prob = 1.0  # both episodes end at the next step
    td["agent", "action"] = torch.tensor([0, 0])
    td = env.step(td)
    assert td["next", "agent", "done"].all()
    assert td["next", "agent", "option"].tolist() == [-1, -1]


def test_two_agents_root_and_agent_done_in_a_collector():
    env = two_agent_env()
    check_env_specs(env)
    assert env.transform.done_keys == ["done", ("agents", "done")]
    torch.manual_seed(0)
    collector = Collector(env, None, frames_per_batch=4 * 60, total_frames=4 * 120)
    agent_ends_alone = episode_ends = starts = 0
    for batch in collector:
        for i in range(batch.shape[0]):
            root_done = batch["next", "done"][i].reshape(-1)
            episode_ends += int(root_done.sum())
            after_done = root_done[:-1].nonzero().flatten() + 1
            for j in range(2):
                # the option of agent j ends with its own done or with the episode's
                agent_done = batch["next", "agents", "done"][i][:, j].reshape(-1)
                agent_ends_alone += int((agent_done & ~root_done).sum())
                data = column(batch, "agents", i, j)
                starts += int((data["next", "executed_option"] >= 0).sum())
                check_against_reference(data, agent_done | root_done)
                assert (data["option"][after_done] == -1).all()  # a new episode starts with a decision
    collector.shutdown()
    assert episode_ends > 10 and agent_ends_alone > 10 and starts > 50


def test_two_agents_partial_reset():
    env = two_agent_env(num_envs=3, end_prob=0.0)
    td = env.reset()
    td["agents", "action"] = torch.full((3, 2), A + 1)
    td = env.step_mdp(env.step(td))
    assert td["agents", "option"].tolist() == [[1, 1]] * 3
    td["_reset"] = torch.tensor([[False], [True], [False]])
    td["agents", "_reset"] = torch.zeros(3, 2, 1, dtype=torch.bool)
    td = env.reset(td)
    assert td["agents", "option"].tolist() == [[1, 1], [-1, -1], [1, 1]]
    assert td["agents", "executed_option"].tolist() == [[1, 1], [-1, -1], [1, 1]]


def test_two_agents_one_agent_done_ends_only_its_option():
    env = two_agent_env(num_envs=1, end_prob=0.0)
    td = env.reset()
    td["agents", "action"] = torch.tensor([[A + 1, A + 0]])
    td = env.step_mdp(env.step(td))
    env.base_env.agent_done[0, 0] = True  # agent 0 is done at the next step; the episode goes on
    td["agents", "action"] = torch.tensor([[0, 0]])
    td = env.step(td)
    assert not td["next", "done"].any()
    assert td["next", "agents", "option"].tolist() == [[-1, 0]]


def test_explicit_done_keys_and_errors():
    explicit = nested_executor("agent", done_key=[("agent", "done"), ("agent", "terminated")])
    env = NestedDoneWalk().append_transform(explicit)
    assert env.transform.done_keys == [("agent", "done"), ("agent", "terminated")]
    with pytest.raises(ValueError, match=r"done_key 'finished' names no entry of the env's done spec"):
        NestedDoneWalk().append_transform(nested_executor("agent", done_key="finished"))
    with pytest.raises(ValueError, match=r"the state entry .option. \(option_key\) lies outside every node"):
        # the env's resets are all under "agent": root state entries would never be reset by TorchRL
        NestedDoneWalk().append_transform(
            OptionExecutor(
                TensorDictModule(FixedOptions(), [("agent", "observation")], ["option_logits", "termination_logits"]),
                K,
                action_key=("agent", "action"),
            )
        )
    options = TensorDictModule(FixedOptions(), ["observation"], ["option_logits", "termination_logits"])
    with pytest.raises(ValueError, match="done_key must name at least one"):
        OptionExecutor(options, K, done_key=[])
    with pytest.raises(ValueError, match=r"option_key and done_key\[1\] are both 'option'"):
        OptionExecutor(options, K, done_key=["done", "option"])


def test_keys_helpers():
    assert done_keys_for("done", ["done", "truncated"], ["_reset"], "X") == ["done"]
    assert done_keys_for(["done", ("a", "done")], ["done", ("a", "done")], ["_reset"], "X") == ["done", ("a", "done")]
    assert done_keys_for("done", ["done", ("a", "done")], ["_reset", ("a", "_reset")], "X") == ["done", ("a", "done")]
    assert done_keys_for(["done"], ["done", ("a", "done")], ["_reset", ("a", "_reset")], "X") == ["done"]
    flag = torch.tensor([[[True], [False]], [[False], [False]]])  # [2, 2, 1]
    assert FlagToState((2, 2, 1), (2,), "k", "X")(flag).tolist() == [True, False]
    assert FlagToState((2, 1), (2,), "k", "X")(flag[:, 0]).tolist() == [True, False]
    assert FlagToState((2, 1), (2, 2), "k", "X")(flag[:, 0]).tolist() == [[True, True], [False, False]]
    with pytest.raises(ValueError, match=r"X: the done entry 'k' has shape \(3, 1\)"):
        FlagToState((3, 1), (2, 2), "k", "X")
