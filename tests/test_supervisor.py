"""Tests of the value-iteration supervisor and the demonstrations (torchrl_options.envs.supervisor)."""
from __future__ import annotations

from collections import deque

import pytest
import torch

from torchrl_options.envs import (
    GridWorldEnv,
    ValueIterationSupervisor,
    generate_demonstrations,
    load_map,
    parse_map,
    value_iteration,
)
from torchrl_options.envs.maps import GridMap


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def bfs_distances(grid: GridMap) -> torch.Tensor:
    """``[F, F]`` shortest-path lengths by breadth-first search (``inf`` when unreachable)."""
    nxt = grid.next_cell.tolist()
    F = grid.num_free
    rows = []
    for source in range(F):
        dist = [float("inf")] * F
        dist[source] = 0.0
        queue = deque([source])
        while queue:
            s = queue.popleft()
            for t in nxt[s]:
                if dist[t] == float("inf"):
                    dist[t] = dist[s] + 1
                    queue.append(t)
        rows.append(dist)
    return torch.tensor(rows, dtype=torch.float64)  # symmetric: moves are reversible


@pytest.mark.parametrize("name", ["four-rooms", "two-rooms-8x20"])
def test_value_iteration_without_noise_is_bfs(name):
    grid = load_map(name)
    values, _ = value_iteration(grid, noise=0.0)
    assert torch.equal(values, bfs_distances(grid))


def test_value_iteration_with_noise_is_a_bellman_fixed_point():
    grid = load_map("four-rooms")
    noise = 0.3
    values, q = value_iteration(grid, noise=noise)
    successors = values[:, grid.next_cell]
    bellman = 1 + (1 - noise) * successors.min(-1).values + noise * successors.mean(-1)
    off_target = ~torch.eye(grid.num_free, dtype=torch.bool)
    assert torch.allclose(values[off_target], bellman[off_target], atol=1e-6)
    assert (values.diagonal() == 0).all()
    assert (values >= bfs_distances(grid) - 1e-9).all(), "noise can only make targets further"
    assert torch.allclose(q.min(-1).values[off_target], values[off_target])


def test_value_iteration_unreachable_is_inf():
    grid = parse_map("1 1 1 1 1\n1 0 1 0 1\n1 1 1 1 1")
    values, _ = value_iteration(grid, noise=0.3)
    assert values.tolist() == [[0.0, float("inf")], [float("inf"), 0.0]]


@pytest.mark.parametrize("tie_break", ["random", "first"])
@pytest.mark.parametrize("name", ["four-rooms", "two-rooms"])
def test_greedy_supervisor_takes_shortest_paths(name, tie_break):
    n = 64
    env = GridWorldEnv(name, task="goal", batch_size=[n], noise=0.0, max_steps=200, seed=0)
    supervisor = ValueIterationSupervisor(env, tie_break=tie_break, seed=0)
    grid = env.grid
    td = env.reset()
    start = grid.cell_index[td["agent_pos"][:, 0], td["agent_pos"][:, 1]]
    goal = grid.cell_index[td["target_pos"][:, 0], td["target_pos"][:, 1]]
    shortest = bfs_distances(grid)[goal, start]
    rollout = env.rollout(200, supervisor, auto_reset=False, tensordict=td, break_when_any_done=False,
                          break_when_all_done=True)  # fmt: skip
    terminated = rollout["next", "terminated"].squeeze(-1)
    steps = terminated.long().argmax(-1) + 1  # first termination
    assert terminated.any(-1).all()
    assert torch.equal(steps.double(), shortest)


def test_supervisor_noise():
    n = 4000
    env = GridWorldEnv("four-rooms", batch_size=[n], seed=1)
    td = env.reset()
    grid = env.grid
    agent = grid.cell_index[td["agent_pos"][:, 0], td["agent_pos"][:, 1]]
    target = grid.cell_index[td["target_pos"][:, 0], td["target_pos"][:, 1]]
    for eps in (0.0, 0.5, 1.0):
        supervisor = ValueIterationSupervisor(env, supervisor_noise=eps, seed=2)
        optimal = supervisor.optimal[target, agent]  # [n, 4]
        action = supervisor(td.clone())["action"]
        assert action.shape == (n,) and action.dtype == torch.long
        chosen_optimal = optimal.gather(-1, action[:, None]).squeeze(-1)
        # a random action is sub-optimal w.p. 1 - |optimal| / 4
        expected = (eps * (1 - optimal.sum(-1) / 4)).mean()
        assert abs((~chosen_optimal).float().mean() - expected) < 0.03, eps


def test_supervisor_random_ties_cover_all_optimal_actions():
    env = GridWorldEnv("four-rooms", batch_size=[400], noise=0.0, seed=0)
    td = env.reset_at(agent_pos=(1, 1), target_pos=(3, 3))  # down and right are both shortest
    actions = ValueIterationSupervisor(env, seed=0)(td)["action"]
    assert set(actions.tolist()) == {1, 2}
    first = ValueIterationSupervisor(env, tie_break="first")(td)["action"]
    assert set(first.tolist()) == {1}


def test_demonstrations_apple():
    demos = generate_demonstrations("four-rooms", num_trajectories=6, length=150, seed=0)
    assert demos.shape == (6, 150)
    for key in [
        "observation", "action", "agent_pos", "target_pos",
        ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated"),
        ("next", "truncated"), ("collector", "mask"), ("collector", "traj_ids"),
    ]:  # fmt: skip
        assert key in demos.keys(True), key
    assert demos["action"].dtype == torch.long and demos["action"].shape == (6, 150)
    assert demos["collector", "mask"].dtype == torch.bool and demos["collector", "mask"].all()
    assert demos["next", "truncated"][:, -1].all() and not demos["next", "done"][:, :-1].any()
    assert torch.equal(demos["collector", "traj_ids"][:, 0], torch.arange(6))
    # trajectory layout: the next observation is the following observation
    assert torch.equal(demos["next", "observation"][:, :-1], demos["observation"][:, 1:])
    assert demos["next", "reward"].sum() > 0
    # "action" is the supervisor's choice (always optimal), not the noisy move the env executed
    supervisor = ValueIterationSupervisor(load_map("four-rooms"))
    grid = load_map("four-rooms")
    agent = grid.cell_index[demos["agent_pos"][..., 0], demos["agent_pos"][..., 1]]
    target = grid.cell_index[demos["target_pos"][..., 0], demos["target_pos"][..., 1]]
    assert supervisor.optimal[target, agent].gather(-1, demos["action"][..., None]).all()
    # reproducible
    again = generate_demonstrations("four-rooms", num_trajectories=6, length=150, seed=0)
    assert torch.equal(again["action"], demos["action"]) and torch.equal(again["agent_pos"], demos["agent_pos"])


def test_demonstrations_goal_are_padded():
    demos = generate_demonstrations("two-rooms", 8, 120, task="goal", seed=3)
    mask = demos["collector", "mask"]
    lengths = mask.sum(-1)
    assert (lengths < 120).all()
    # the mask is a prefix, ending at the step that reached the goal
    assert torch.equal(mask, torch.arange(120)[None] < lengths[:, None])
    terminated = demos["next", "terminated"].squeeze(-1)
    assert torch.equal(terminated.long().argmax(-1) + 1, lengths) and (terminated.sum(-1) == 1).all()
    assert (demos["next", "reward"].squeeze(-1).sum(-1) == 1).all()
    # padding is zero
    assert (demos["observation"][~mask] == 0).all() and (demos["action"][~mask] == 0).all()


def test_demonstrations_from_env_and_noise_knobs():
    env = GridWorldEnv("three-rooms", task="subgoals", one_hot=True, noise=0.1)
    demos = generate_demonstrations(env, 4, 80, supervisor_noise=0.2, seed=0)
    assert demos.shape == (4, 80) and demos["observation"].shape == (4, 80, 2 * env.grid.num_free)
    # without any noise the supervisor follows shortest paths: start -> sub-goal 1 -> sub-goal 2
    clean = generate_demonstrations(env, 2, 80, noise=0.0, seed=0)
    grid = env.grid
    dist = bfs_distances(grid)
    s, g1, g2 = (int(grid.cell_index[p]) for p in (grid.start, *grid.goals))
    assert (clean["collector", "mask"].sum(-1) == int(dist[s, g1] + dist[g1, g2])).all()
    assert (clean["next", "reward"].sum((1, 2)) == 1).all()
