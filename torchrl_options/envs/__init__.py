"""The DDO paper's environments: GridWorlds (maps, rendering, a value-iteration supervisor) and Atari RAM games."""
from torchrl_options.envs.atari import (
    ATARI_GAMES,
    EpisodicLife,
    make_atari_ram_env,
    PAPER_NUM_OPTIONS,
    ram_q_network,
    RAMBytesEncoder,
    RAMOneHotEncoder,
    RAMToFloat,
    render_frame,
)
from torchrl_options.envs.gridworld import TASKS, GridWorldEnv
from torchrl_options.envs.maps import ACTION_NAMES, MOVES, GridMap, available_maps, detect_rooms, load_map, parse_map
from torchrl_options.envs.render import draw_heatmap, draw_trajectory, option_colors, render_grid, write_video
from torchrl_options.envs.supervisor import ValueIterationSupervisor, generate_demonstrations, value_iteration

__all__ = [
    "ATARI_GAMES",
    "EpisodicLife",
    "make_atari_ram_env",
    "PAPER_NUM_OPTIONS",
    "ram_q_network",
    "RAMBytesEncoder",
    "RAMOneHotEncoder",
    "RAMToFloat",
    "render_frame",
    "ACTION_NAMES",
    "MOVES",
    "TASKS",
    "ValueIterationSupervisor",
    "GridMap",
    "GridWorldEnv",
    "available_maps",
    "detect_rooms",
    "draw_heatmap",
    "draw_trajectory",
    "generate_demonstrations",
    "load_map",
    "option_colors",
    "parse_map",
    "render_grid",
    "value_iteration",
    "write_video",
]
