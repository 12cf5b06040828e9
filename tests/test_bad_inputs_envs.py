"""Bad inputs of torchrl_options.envs (issue 53's walk of the public API): GridWorld, its supervisor and maps, the
pictures, and the Atari RAM envs and networks. One row per case, controls included."""
import numpy as np
import pytest
import torch

from _bad_inputs import check, ids, OK
from torchrl_options.envs import (
    detect_rooms,
    draw_heatmap,
    draw_trajectory,
    generate_demonstrations,
    GridWorldEnv,
    load_map,
    option_colors,
    parse_map,
    ram_q_network,
    RAMBytesEncoder,
    RAMOneHotEncoder,
    RAMToFloat,
    render_frame,
    render_grid,
    value_iteration,
    ValueIterationSupervisor,
    write_video,
)

NAN = float("nan")


def atari(**kw):
    pytest.importorskip("ale_py")
    from torchrl_options.envs import make_atari_ram_env

    return lambda: make_atari_ram_env(**kw)


def image():
    return render_grid(load_map("two-rooms"), cell_size=4)


CASES = [
    ("GridWorldEnv", "unknown map", lambda: GridWorldEnv("nowhere"), ValueError, "Unknown map 'nowhere'"),
    ("GridWorldEnv", "noise 2", lambda: GridWorldEnv("two-rooms", noise=2.0), ValueError, "noise must be a number in [0, 1]"),
    ("GridWorldEnv", "noise NaN", lambda: GridWorldEnv("two-rooms", noise=NAN), ValueError, "noise must be a number in [0, 1]"),
    ("GridWorldEnv", "noise a string", lambda: GridWorldEnv("two-rooms", noise="0.3"), TypeError, "noise must be a number"),
    ("GridWorldEnv", "max_steps a float", lambda: GridWorldEnv("two-rooms", max_steps=2.5), ValueError, "max_steps must be a positive int or None"),
    ("GridWorldEnv", "batch_size negative", lambda: GridWorldEnv("two-rooms", batch_size=[-1]), ValueError, "batch_size must be an int >= 1"),
    ("GridWorldEnv", "one_hot a string", lambda: GridWorldEnv("two-rooms", one_hot="yes"), TypeError, "one_hot must be True or False"),
    ("GridWorldEnv", "task unknown", lambda: GridWorldEnv("two-rooms", task="chess"), ValueError, "task must be one of"),
    ("GridWorldEnv", "control: batched, no step limit", lambda: GridWorldEnv("two-rooms", batch_size=[2], max_steps=None), OK, None),
    ("generate_demonstrations", "no trajectory", lambda: generate_demonstrations("two-rooms", 0, 10), ValueError,
     "num_trajectories must be an int >= 1"),
    ("generate_demonstrations", "length negative", lambda: generate_demonstrations("two-rooms", 2, -1), ValueError, "length must be an int >= 1"),
    ("generate_demonstrations", "noise NaN", lambda: generate_demonstrations("two-rooms", 2, 5, noise=NAN), ValueError,
     "noise must be a number in [0, 1]"),
    ("generate_demonstrations", "tie_break unknown", lambda: generate_demonstrations("two-rooms", 2, 5, tie_break="x"), ValueError,
     "tie_break must be 'random' or 'first'"),
    ("generate_demonstrations", "control: one short trajectory", lambda: generate_demonstrations("two-rooms", 1, 3), OK, None),
    ("ValueIterationSupervisor", "agent_key equal to target_key", lambda: ValueIterationSupervisor("two-rooms", agent_key="target_pos"),
     ValueError, "agent_key and target_key are both 'target_pos'"),
    ("ValueIterationSupervisor", "supervisor_noise 2", lambda: ValueIterationSupervisor("two-rooms", supervisor_noise=2.0), ValueError,
     "supervisor_noise must be a number in [0, 1]"),
    ("ValueIterationSupervisor", "noise negative", lambda: ValueIterationSupervisor("two-rooms", noise=-1.0), ValueError,
     "noise must be a number in [0, 1]"),
    ("value_iteration", "noise 1", lambda: value_iteration("two-rooms", 1.0), ValueError, "noise must be a number in [0, 1)"),
    ("value_iteration", "tol negative (it never converged, silently)", lambda: value_iteration("two-rooms", tol=-1.0), ValueError,
     "tol must be a number >= 0"),
    ("value_iteration", "max_iterations 0 (UnboundLocalError before)", lambda: value_iteration("two-rooms", max_iterations=0), ValueError,
     "max_iterations must be an int >= 1"),
    ("load_map", "unknown name", lambda: load_map("nowhere"), ValueError, "Unknown map 'nowhere'"),
    ("parse_map", "cells that are not digits", lambda: parse_map("###\n#.\n###"), ValueError, "cells must be integers 0-4"),
    ("parse_map", "empty text", lambda: parse_map(""), ValueError, "Map 'custom' is empty"),
    ("detect_rooms", "one-dimensional walls", lambda: detect_rooms(torch.zeros(5, dtype=torch.bool)), ValueError,
     "walls must be an [H, W] grid, got shape [5]"),
    ("detect_rooms", "control: 0/1 walls as floats", lambda: detect_rooms(torch.zeros(3, 3)), OK, None),
    ("option_colors", "negative count", lambda: option_colors(-1), ValueError, "k must be an int >= 0"),
    ("option_colors", "a string", lambda: option_colors("3"), TypeError, "k must be an int"),
    ("option_colors", "control: none", lambda: option_colors(0), OK, None),
    ("render_grid", "cell_size 0 (an empty image before)", lambda: render_grid(load_map("two-rooms"), cell_size=0), ValueError,
     "cell_size must be an int >= 1"),
    ("draw_heatmap", "values of another shape", lambda: draw_heatmap(image(), load_map("two-rooms"), torch.zeros(2, 2), cell_size=4),
     ValueError, "values must be [H, W]"),
    ("draw_heatmap", "cell_size 0", lambda: draw_heatmap(image(), load_map("two-rooms"), torch.zeros(load_map("two-rooms").num_free),
     cell_size=0), ValueError, "cell_size must be an int >= 1"),
    ("draw_heatmap", "control: NaN cells are left uncoloured",
     lambda: draw_heatmap(image(), load_map("two-rooms"), torch.full((load_map("two-rooms").num_free,), NAN), cell_size=4), OK, None),
    ("draw_trajectory", "positions of another shape", lambda: draw_trajectory(image(), [[1]], cell_size=4), ValueError,
     "positions must be [T, 2] (row, col) cells, got shape [1, 1]"),
    ("draw_trajectory", "control: two cells", lambda: draw_trajectory(image(), [[1, 1], [1, 2]], cell_size=4), OK, None),
    ("write_video", "no frame", lambda: write_video([], "v.avi"), ValueError, "needs at least one frame"),
    ("write_video", "fps 0", lambda: write_video([np.zeros((8, 8, 3), np.uint8)], "v.avi", fps=0), ValueError, "fps must be a number > 0"),
    ("write_video", "a folder that does not exist", lambda: write_video([np.zeros((8, 8, 3), np.uint8)], "/nowhere/v.avi"), ValueError,
     "the folder /nowhere does not exist"),
    ("ram_q_network", "no action", lambda: ram_q_network(0), ValueError, "num_actions must be an int >= 1"),
    ("ram_q_network", "a layer of width 0", lambda: ram_q_network(4, num_cells=(0,)), ValueError, "num_cells[0] must be an int >= 1"),
    ("ram_q_network", "num_cells a string", lambda: ram_q_network(4, num_cells="64"), TypeError, "num_cells must be a list"),
    ("ram_q_network", "encoding unknown", lambda: ram_q_network(4, encoding="pixels"), ValueError, "encoding must be 'bytes' or 'one_hot'"),
    ("ram_q_network", "control: one layer", lambda: ram_q_network(4, num_cells=[8]), OK, None),
    ("RAMBytesEncoder", "out_features 0", lambda: RAMBytesEncoder(0), ValueError, "out_features must be an int >= 1"),
    ("RAMOneHotEncoder", "out_features 0", lambda: RAMOneHotEncoder(0), ValueError, "out_features must be an int >= 1"),
    ("RAMOneHotEncoder", "num_bytes 0 (ZeroDivisionError before)", lambda: RAMOneHotEncoder(4, num_bytes=0), ValueError,
     "num_bytes must be an int >= 1"),
    ("RAMToFloat", "two inputs written to one output", lambda: RAMToFloat(in_keys=["observation", "pixels"], out_keys=["x", "x"]),
     ValueError, "out_keys[0] and out_keys[1] are both 'x'"),
    ("RAMToFloat", "fewer outputs than inputs", lambda: RAMToFloat(in_keys=["a", "b"], out_keys=["x"]), ValueError,
     "out_keys must have one key per in_key"),
    ("RAMToFloat", "control: in place", lambda: RAMToFloat(), OK, None),
    ("render_frame", "not an env", lambda: render_frame(3), TypeError, "render_frame expects a TorchRL env"),
    ("render_frame", "an env without a gymnasium env", lambda: render_frame(GridWorldEnv("two-rooms")), ValueError,
     "wraps no gymnasium env to render"),
    ("make_atari_ram_env", "an unknown game", lambda: atari(game="Chess")(), ValueError, "game 'Chess': no such Atari game"),
    ("make_atari_ram_env", "sticky actions 2", lambda: atari(game="Pong", repeat_action_probability=2.0)(), ValueError,
     "repeat_action_probability must be a number in [0, 1]"),
    ("make_atari_ram_env", "noop_max negative", lambda: atari(game="Pong", noop_max=-1)(), ValueError, "noop_max must be an int >= 0"),
    ("make_atari_ram_env", "frame_skip 0", lambda: atari(game="Pong", frame_skip=0)(), ValueError, "frame_skip must be an int >= 1"),
    ("make_atari_ram_env", "game not a string", lambda: atari(game=3)(), TypeError, "game must be a game name"),
    ("make_atari_ram_env", "max_episode_steps 0", lambda: atari(game="Pong", max_episode_steps=0)(), ValueError,
     "max_episode_steps must be an int >= 1"),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_envs_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)
