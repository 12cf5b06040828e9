"""Tests of the GridWorld maps, environment and rendering (torchrl_options.envs)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torchrl.envs import SerialEnv
from torchrl.envs.utils import check_env_specs

from torchrl_options.envs import (
    GridWorldEnv,
    available_maps,
    detect_rooms,
    draw_heatmap,
    draw_trajectory,
    load_map,
    parse_map,
    render_grid,
    write_video,
)

UP, RIGHT, DOWN, LEFT = range(4)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # tiny tensors: intra-op threads only add contention on a shared CPU
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def step(env: GridWorldEnv, td, action):
    td["action"] = torch.as_tensor(action, dtype=torch.long).expand(env.batch_size).clone()
    return env.step(td)["next"]


# ------------------------------------------------------------------------------------------------------- maps
@pytest.mark.parametrize(
    "name, shape, rooms",
    [
        ("four-rooms", (15, 11), 4),
        ("two-rooms", (10, 20), 2),
        ("two-rooms-8x20", (8, 20), 2),
        ("three-rooms", (10, 25), 3),
    ],
)
def test_builtin_maps(name, shape, rooms):
    grid = load_map(name)
    assert grid.shape == shape
    assert grid.num_rooms == rooms
    assert grid.walls[0].all() and grid.walls[-1].all() and grid.walls[:, 0].all() and grid.walls[:, -1].all()
    assert name in available_maps()


def test_four_rooms_rooms_are_the_corner_3x3_blocks():
    grid = load_map("four-rooms")
    corners = {(1, 1), (11, 1), (1, 7), (11, 7)}
    found = set()
    for cells in grid.room_cells:
        pos = grid.free_cells[cells]
        top_left = tuple(pos.min(0).values.tolist())
        assert len(cells) == 9 and (pos.max(0).values - pos.min(0).values).tolist() == [2, 2]
        found.add(top_left)
    assert found == corners


def test_three_rooms_markers_in_successive_rooms():
    grid = load_map("three-rooms")
    assert [grid.room_of(grid.start), grid.room_of(grid.goals[0]), grid.room_of(grid.goals[1])] == [0, 1, 2]


def test_load_map_from_path_and_errors(tmp_path):
    path = tmp_path / "tiny.txt"
    path.write_text("1 1 1 1\n1 2 3 1\n1 1 1 1\n")
    grid = load_map(path)
    assert grid.name == "tiny" and grid.start == (1, 1) and grid.goals == ((1, 2),)
    with pytest.raises(ValueError, match="Unknown map"):
        load_map("five-rooms")
    with pytest.raises(ValueError, match="unknown cell"):
        parse_map("1 1\n1 7")
    with pytest.raises(ValueError, match="same number"):
        parse_map("1 1 1\n1 0")


def test_detect_rooms_ignores_corridors():
    grid = parse_map(
        """
        1 1 1 1 1 1 1 1
        1 0 0 1 1 0 0 1
        1 0 0 0 0 0 0 1
        1 1 1 1 1 1 1 1
        """
    )
    rooms = detect_rooms(grid.walls)
    assert rooms[2, 3] == -1 and rooms[2, 4] == -1  # the corridor
    assert rooms[1, 1] == 0 and rooms[2, 6] == 1


def test_next_cell_table_blocks_walls():
    grid = load_map("four-rooms")
    cell = grid.cell_index[1, 1]
    # up and left blocked by walls, right and down open
    assert grid.free_cells[grid.next_cell[cell]].tolist() == [[1, 1], [1, 2], [2, 1], [1, 1]]


# ------------------------------------------------------------------------------------------------ dynamics
def test_walls_block():
    env = GridWorldEnv("four-rooms", batch_size=[4], noise=0.0, seed=0)
    td = env.reset_at(agent_pos=(1, 1), target_pos=(13, 9))
    out = step(env, td, [UP, RIGHT, DOWN, LEFT])
    assert out["agent_pos"].tolist() == [[1, 1], [1, 2], [2, 1], [1, 1]]
    # a vertical corridor cell: left and right are walls
    td = env.reset_at(agent_pos=(5, 3), target_pos=(13, 9))
    out = step(env, td, [UP, RIGHT, DOWN, LEFT])
    assert out["agent_pos"].tolist() == [[4, 3], [5, 3], [6, 3], [5, 3]]
    assert (out["reward"] == 0).all()


def test_map_without_border_walls_clamps():
    env = GridWorldEnv(parse_map("0 0\n0 0"), batch_size=[2], noise=0.0, seed=0)
    td = env.reset_at(agent_pos=(0, 0), target_pos=(1, 1))
    assert step(env, td, [UP, LEFT])["agent_pos"].tolist() == [[0, 0], [0, 0]]


@pytest.mark.parametrize("noise", [0.0, 0.3, 1.0])
def test_noise_rate(noise):
    # From the centre of a 3x3 room every move is possible, so the executed move can be read off the
    # displacement. The chosen action is replaced w.p. `noise` by a uniform one (possibly itself): the executed
    # move differs from the chosen one w.p. 0.75 * noise, and each other move has probability noise / 4.
    n = 20_000
    env = GridWorldEnv("four-rooms", batch_size=[n], noise=noise, seed=1)
    td = env.reset_at(agent_pos=(2, 2), target_pos=(13, 9))
    moved = step(env, td, UP)["agent_pos"] - torch.tensor([2, 2])
    executed = {(-1, 0): UP, (0, 1): RIGHT, (1, 0): DOWN, (0, -1): LEFT}
    counts = torch.bincount(torch.tensor([executed[tuple(d)] for d in moved.tolist()]), minlength=4) / n
    expected = torch.full((4,), noise / 4)
    expected[UP] += 1 - noise
    tol = 5 * math.sqrt(0.25 / n)
    assert torch.allclose(counts, expected, atol=tol), (counts, expected)


def test_apple_taken_and_respawned_in_a_room():
    n = 2000
    env = GridWorldEnv("four-rooms", batch_size=[n], noise=0.0, seed=2)
    grid = env.grid
    td = env.reset_at(agent_pos=(1, 1), target_pos=(2, 1))
    out = step(env, td, DOWN)
    assert (out["reward"] == 1).all() and not out["done"].any()
    agent, apple = out["agent_pos"], out["target_pos"]
    assert (agent == torch.tensor([2, 1])).all()
    assert not grid.walls[apple[:, 0], apple[:, 1]].any()
    rooms = grid.rooms[apple[:, 0], apple[:, 1]]
    assert (rooms >= 0).all(), "the apple respawns inside a room"
    assert not (apple == agent).all(-1).any(), "never on the agent"
    # room uniform (1/4 each); within the agent's room, 8 cells left
    frac = torch.bincount(rooms, minlength=4) / n
    assert torch.allclose(frac, torch.full((4,), 0.25), atol=0.05)
    # observation follows the new apple
    assert torch.allclose(out["observation"][:, 2:], apple / torch.tensor([14.0, 10.0]))
    # not taken (moving up to (1, 1) where there is no apple): no reward, the apple stays
    out2 = step(env, out.clone(), UP)
    elsewhere = (apple != torch.tensor([1, 1])).any(-1)
    assert (out2["reward"][elsewhere] == 0).all() and (out2["reward"][~elsewhere] == 1).all()
    assert torch.equal(out2["target_pos"][elsewhere], apple[elsewhere])


def test_apple_reset_distribution():
    env = GridWorldEnv("four-rooms", batch_size=[3000], seed=3)
    td = env.reset()
    grid = env.grid
    agent, apple = td["agent_pos"], td["target_pos"]
    assert (grid.rooms[apple[:, 0], apple[:, 1]] >= 0).all()
    assert not (agent == apple).all(-1).any()
    # the agent starts anywhere, corridors included
    assert (grid.rooms[agent[:, 0], agent[:, 1]] < 0).any()
    assert not td["done"].any() and (td["step_count"] == 0).all()


def test_goal_task():
    env = GridWorldEnv("two-rooms", task="goal", batch_size=[500], max_steps=20, seed=4)
    grid = env.grid
    td = env.reset()
    start, goal = td["agent_pos"], td["target_pos"]
    assert (grid.rooms[start[:, 0], start[:, 1]] != grid.rooms[goal[:, 0], goal[:, 1]]).all()
    assert (grid.rooms[start[:, 0], start[:, 1]] >= 0).all() and (grid.rooms[goal[:, 0], goal[:, 1]] >= 0).all()
    # +1 and termination at the goal
    env0 = GridWorldEnv("two-rooms", task="goal", goal=(4, 16), batch_size=[2], noise=0.0, seed=0)
    td = env0.reset_at(agent_pos=(4, 15))
    out = step(env0, td, [RIGHT, LEFT])
    assert out["reward"].squeeze(-1).tolist() == [1.0, 0.0]
    assert out["terminated"].squeeze(-1).tolist() == [True, False]
    assert out["done"].squeeze(-1).tolist() == [True, False]
    # truncation after max_steps
    env1 = GridWorldEnv("two-rooms", task="goal", start=(1, 1), goal="map", batch_size=[3], max_steps=5, noise=0.0)
    td = env1.reset()
    assert (td["agent_pos"] == torch.tensor([1, 1])).all() and (td["target_pos"] == torch.tensor([4, 16])).all()
    for t in range(5):
        td = step(env1, td, LEFT)  # against the wall
        assert td["truncated"].all() == (t == 4) and not td["terminated"].any()
    assert td["done"].all() and (td["step_count"] == 5).all()


def test_subgoals_task():
    env = GridWorldEnv("three-rooms", task="subgoals", batch_size=[3], noise=0.0, seed=0)
    (g1, g2) = env.subgoals
    td = env.reset()
    assert (td["agent_pos"] == torch.tensor(load_map("three-rooms").start)).all()
    assert (td["target_pos"] == torch.tensor(g1)).all() and (td["stage"] == 0).all()
    # stage 0: the second goal gives nothing, the first gives 0.5
    td = env.reset_at(agent_pos=[[g1[0], g1[1] - 1], [g2[0], g2[1] - 1], [1, 1]])
    out = step(env, td, RIGHT)
    assert out["reward"].squeeze(-1).tolist() == [0.5, 0.0, 0.0]
    assert out["stage"].squeeze(-1).tolist() == [1, 0, 0]
    assert out["target_pos"].tolist() == [list(g2), list(g1), list(g1)]
    assert not out["done"].any()
    # stage 1: the second goal gives 0.5 and ends the episode
    td = env.reset_at(agent_pos=(g2[0], g2[1] - 1), stage=1)
    out = step(env, td, RIGHT)
    assert (out["reward"] == 0.5).all() and out["terminated"].all() and (out["stage"] == 2).all()
    # random start: in the leftmost room
    env = GridWorldEnv("three-rooms", task="subgoals", start="random", batch_size=[200], seed=0)
    start = env.reset()["agent_pos"]
    assert (env.grid.rooms[start[:, 0], start[:, 1]] == 0).all()


# ---------------------------------------------------------------------------------------- batching and RNG
def _run(env: GridWorldEnv, actions: torch.Tensor) -> dict[str, torch.Tensor]:
    """Steps with auto-reset; returns per-step records stacked on the last batch dim."""
    records = {k: [] for k in ("agent_pos", "target_pos", "reward", "done")}
    td = env.reset()
    for a in actions:
        td["action"] = a.reshape(env.batch_size).clone()
        td, td_root = env.step_and_maybe_reset(td)
        for key in records:
            records[key].append(td["next", key].reshape(-1, td["next", key].shape[-1]))
        td = td_root
    return {k: torch.stack(v, 1) for k, v in records.items()}


@pytest.mark.parametrize("task, grid", [("apple", "four-rooms"), ("goal", "two-rooms-8x20")])
def test_batched_equals_single_envs(task, grid):
    n, T, seed = 4, 40, 11
    actions = torch.randint(0, 4, (T, n), generator=torch.Generator().manual_seed(0))
    batched = _run(GridWorldEnv(grid, task=task, batch_size=[n], max_steps=7, seed=seed), actions)
    for i in range(n):
        single = _run(GridWorldEnv(grid, task=task, max_steps=7, seed=seed + i), actions[:, i])
        for key, value in single.items():
            assert torch.equal(batched[key][i], value[0]), (key, i)
    assert batched["done"].any(), "the test should cross episode boundaries"


def test_seeding_is_reproducible():
    a = GridWorldEnv(batch_size=[8], seed=5).rollout(30)
    b = GridWorldEnv(batch_size=[8], seed=5).rollout(30)
    env = GridWorldEnv(batch_size=[8], seed=6)
    c = env.rollout(30)
    # rollout's random actions come from torch's global generator: compare the env's own draws (the resets)
    assert torch.equal(a["agent_pos"][:, 0], b["agent_pos"][:, 0])
    assert not torch.equal(a["agent_pos"][:, 0], c["agent_pos"][:, 0])
    env.set_seed(5)
    assert torch.equal(env.reset()["agent_pos"], a["agent_pos"][:, 0])


def test_partial_reset():
    n = 6
    env = GridWorldEnv("four-rooms", batch_size=[n], seed=8)
    twin = GridWorldEnv("four-rooms", batch_size=[n], seed=8)
    td, td_twin = env.reset(), twin.reset()
    for _ in range(3):
        td = step(env, td, RIGHT)
        td_twin = step(twin, td_twin, RIGHT)
    reset = torch.tensor([True, False, True, False, False, False])
    before = td.clone()
    td["_reset"] = reset[:, None]
    td = env.reset(td)
    assert (td["step_count"][reset] == 0).all() and (td["step_count"][~reset] == 3).all()
    assert torch.equal(td["agent_pos"][~reset], before["agent_pos"][~reset])
    assert torch.equal(td["target_pos"][~reset], before["target_pos"][~reset])
    assert not torch.equal(td["agent_pos"][reset], before["agent_pos"][reset])
    # envs that were not reset drew no random numbers: they go on exactly like their twins
    for _ in range(5):
        td = step(env, td, DOWN)
        td_twin = step(twin, td_twin, DOWN)
        assert torch.equal(td["agent_pos"][~reset], td_twin["agent_pos"][~reset])


def test_partial_step():
    env = GridWorldEnv("four-rooms", batch_size=[3], noise=0.0, seed=0)
    td = env.reset_at(agent_pos=(2, 2), target_pos=(13, 9))
    td["action"] = torch.full((3,), DOWN)
    td["_step"] = torch.tensor([True, False, True])
    out = env.step(td)["next"]
    assert out["agent_pos"].tolist() == [[3, 2], [2, 2], [3, 2]]
    assert out["step_count"].squeeze(-1).tolist() == [1, 0, 1]


# ---------------------------------------------------------------------------------------------------- specs
@pytest.mark.parametrize(
    "kwargs",
    [
        dict(),
        dict(one_hot=True),
        dict(normalize=False),
        dict(grid="two-rooms", task="goal", max_steps=20),
        dict(grid="three-rooms", task="subgoals"),
    ],
)
@pytest.mark.parametrize("batch_size", [(), (3,)])
def test_check_env_specs(kwargs, batch_size):
    check_env_specs(GridWorldEnv(batch_size=batch_size, seed=0, **kwargs))


def test_check_env_specs_serial():
    env = SerialEnv(2, lambda: GridWorldEnv("two-rooms", task="goal", max_steps=4, batch_size=[2]))
    try:
        check_env_specs(env)
    finally:
        env.close()


def test_observation_variants():
    env = GridWorldEnv("four-rooms", batch_size=[5], seed=0)
    td = env.reset()
    pos = torch.cat([td["agent_pos"], td["target_pos"]], -1).float()
    assert torch.allclose(td["observation"], pos / torch.tensor([14.0, 10.0, 14.0, 10.0]))
    assert ((td["observation"] >= 0) & (td["observation"] <= 1)).all()
    raw = GridWorldEnv("four-rooms", batch_size=[5], seed=0, normalize=False).reset()
    assert torch.equal(raw["observation"], pos)
    hot = GridWorldEnv("four-rooms", batch_size=[5], seed=0, one_hot=True).reset()
    F = env.grid.num_free
    assert hot["observation"].shape == (5, 2 * F) and (hot["observation"].sum(-1) == 2).all()
    cells = env.grid.cell_index[td["agent_pos"][:, 0], td["agent_pos"][:, 1]]
    assert torch.equal(hot["observation"][:, :F].argmax(-1), cells)


def test_collector_runs():
    from torchrl.collectors import Collector

    env = GridWorldEnv("four-rooms", batch_size=[4], max_steps=10, seed=0)
    collector = Collector(env, None, frames_per_batch=40, total_frames=80)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2 and batches[0].numel() == 40


def test_invalid_arguments():
    with pytest.raises(ValueError, match="task"):
        GridWorldEnv(task="cheese")
    with pytest.raises(ValueError, match="noise"):
        GridWorldEnv(noise=1.5)
    with pytest.raises(ValueError, match="free cell"):
        GridWorldEnv(start=(0, 0))
    with pytest.raises(ValueError, match="same cell"):
        GridWorldEnv("two-rooms", task="goal", start=(1, 1), goal=(1, 1))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_device():
    env = GridWorldEnv(batch_size=[4], device="cuda", seed=0)
    td = env.rollout(5)
    assert td.device.type == "cuda"
    check_env_specs(env)


# ------------------------------------------------------------------------------------------------ rendering
def test_render():
    env = GridWorldEnv("four-rooms", batch_size=[2], seed=0)
    td = env.reset()
    image = env.render(td, index=1, cell_size=10)
    assert image.shape == (150, 110, 3) and image.dtype == np.uint8
    r, c = td["agent_pos"][1].tolist()
    assert image[r * 10 + 5, c * 10 + 5].tolist() == [40, 90, 220]  # the agent's colour


def test_render_helpers(tmp_path):
    grid = load_map("two-rooms")
    heat = torch.linspace(0, 1, grid.num_free)
    image = render_grid(grid, heatmap=heat, trajectories=[torch.tensor([[4, 1], [4, 2], [4, 3]])], cell_size=12)
    assert image.shape == (120, 240, 3) and image.dtype == np.uint8
    # the hottest free cell is the last one (row-major), tinted towards red
    r, c = grid.free_cells[-1].tolist()
    pixel = image[r * 12 + 2, c * 12 + 2]
    assert pixel[0] > 200 and pixel[1] < 60
    image = draw_heatmap(image, grid, torch.zeros(grid.shape), cell_size=12)
    image = draw_trajectory(image, np.array([[1, 1], [2, 1]]), cell_size=12, color=(0, 255, 0))
    with pytest.raises(ValueError):
        draw_heatmap(image, grid, torch.zeros(3), cell_size=12)
    path = write_video([image, image], tmp_path / "clip.avi", fps=2)
    assert path.stat().st_size > 0
