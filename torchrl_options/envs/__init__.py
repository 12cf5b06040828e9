"""GridWorld environments of the DDO paper, their maps, rendering helpers and a value-iteration supervisor."""
from torchrl_options.envs.gridworld import TASKS, GridWorldEnv
from torchrl_options.envs.maps import ACTION_NAMES, MOVES, GridMap, available_maps, detect_rooms, load_map, parse_map
from torchrl_options.envs.render import draw_heatmap, draw_trajectory, option_colors, render_grid, write_video
from torchrl_options.envs.supervisor import ValueIterationSupervisor, generate_demonstrations, value_iteration

__all__ = [
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
