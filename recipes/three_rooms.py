"""Three rooms GridWorld (Fox et al. 2017, appendix B): DQN with actions, then DDO on its greedy trajectories, then
DQN with the augmented action space (H1u) against DQN continuing with actions only (A).

    python recipes/three_rooms.py                # default scale
    python recipes/three_rooms.py scale=paper    # 15 seeds, 5000 pre-training + 5000 episodes
"""
from functools import partial

import hydra
import torch

from torchrl_options.experiments import run_sweep
from torchrl_options.experiments.gridworld import run_gridworld_cell
from torchrl_options.experiments.gridworld_config import gridworld_settings
from torchrl_options.experiments.gridworld_run import GridWorldRun
from torchrl_options.experiments.recipe_runner import recipe_guard, run_recipe_main

TITLE = "Three rooms"


def run(cfg, quiet: bool = False) -> str | None:
    """The recipe on ``cfg`` (its composed config); returns the summary table (``None``: stopped early)."""
    torch.set_num_threads(1)  # the networks are tiny: one thread is the fastest
    cfg = gridworld_settings(cfg)  # the schema's keys and types, protocol=paper merged, every value checked
    with GridWorldRun(cfg, TITLE, quiet=quiet) as recipe:  # settings.json, the log file, the cells left to run
        run_sweep(partial(run_gridworld_cell, cfg=cfg), recipe.cells, recipe.results, on_result=recipe.finished,
                  **recipe.sweep_options)  # fmt: skip
        summary = recipe.outputs()  # summary.md, curves.png, pictures/
    if summary is not None:
        print(summary)
        print(f"results.csv, summary.md, curves.png, pictures/ (a PNG and a video per set of options) and "
              f"{cfg.get('log_file', 'recipe.log')} in {cfg['out_dir']}")
    return summary


@hydra.main(config_path="config", config_name="three_rooms", version_base="1.3")
def main(cfg) -> None:
    with recipe_guard(cfg.out_dir):  # one line for a bad setting or an interruption, no traceback
        run(cfg, quiet=True)


if __name__ == "__main__":
    run_recipe_main(main)  # Hydra's refusals (an unknown key, a wrong type) as one line too
