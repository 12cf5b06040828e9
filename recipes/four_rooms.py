"""Four rooms GridWorld, supervised and exploration settings (Fox et al. 2017, section 5.1).

Conditions: A (DQN with actions only), H1u / H1s (DQN over actions and options discovered by DDO with a uniform /
learned meta-control). Writes results.csv, summary.md, curves.png and pictures/ to ``out_dir`` and prints the
summary table.

    python recipes/four_rooms.py                 # default scale, about 10 minutes on 2 CPU cores
    python recipes/four_rooms.py scale=paper     # 15 seeds x 5000 episodes, supervised and exploration
    python recipes/four_rooms.py backend=local num_workers=8 logger.backend=tensorboard
"""
import logging

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_options.experiments.gridworld import run_gridworld_recipe


def run(cfg: DictConfig) -> str | None:
    torch.set_num_threads(1)  # tiny networks: threads only add overhead
    summary = run_gridworld_recipe(OmegaConf.to_container(cfg, resolve=True), "Four rooms")
    if summary is not None:
        print(summary)
        print(f"results, summary.md, curves.png and pictures/ in {cfg.out_dir}")
    return summary


@hydra.main(config_path="config", config_name="four_rooms", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if not cfg.verbose:  # progress bars and the summary only; verbose=true adds the per-batch DQN/DDO logs
        for name in ("torchrl", "torchrl_options"):
            logging.getLogger(name).setLevel(logging.WARNING)
    run(cfg)


if __name__ == "__main__":
    main()
