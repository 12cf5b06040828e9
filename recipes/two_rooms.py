"""Two rooms GridWorld (Fox et al. 2017, appendix B): DQN with actions (A), options only (O), actions + options (AO).

Options are discovered by DDO from 10 supervisor demonstrations between random cells of the two rooms; DQN learns a
new start/goal task (+1 if the goal is reached within 20 steps). summary.md adds the episodes each condition needs
to converge.

    python recipes/two_rooms.py                  # default scale
    python recipes/two_rooms.py scale=paper      # 30 seeds x 5000 episodes
"""
import logging

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_options.experiments.gridworld import run_gridworld_recipe


def run(cfg: DictConfig) -> str | None:
    torch.set_num_threads(1)  # tiny networks: threads only add overhead
    summary = run_gridworld_recipe(OmegaConf.to_container(cfg, resolve=True), "Two rooms")
    if summary is not None:
        print(summary)
        print(f"results, summary.md, curves.png and pictures/ in {cfg.out_dir}")
    return summary


@hydra.main(config_path="config", config_name="two_rooms", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if not cfg.verbose:  # progress bars and the summary only; verbose=true adds the per-batch DQN/DDO logs
        for name in ("torchrl", "torchrl_options"):
            logging.getLogger(name).setLevel(logging.WARNING)
    run(cfg)


if __name__ == "__main__":
    main()
