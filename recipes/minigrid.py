"""Options from the BabyAI bot's demonstrations on MiniGrid (issue 50): the bot's demonstrations, DDO, the
segmentation scored against the bot's subgoals with trivial baselines, then PPO / DQN over actions + options against
actions only on a sparse-reward level, with options from that level (same level) and from an easier one (transfer).
See ``torchrl_options.experiments.minigrid`` and ``docs/experiments/minigrid.md``.

Run:
    python recipes/minigrid.py                          # default scale: about 15 minutes on 2 CPU cores
    python recipes/minigrid.py minigrid_scale=tiny      # every stage in about a minute
    python recipes/minigrid.py minigrid_scale=paper backend=local num_workers=8

Writes to ``out_dir``: ``segmentation.jsonl`` (one record per level and seed), ``options/<level>/seed<s>.pt``,
``results.csv`` (one row per RL episode), ``summary.md``, ``curves.png``, ``config.yaml`` and the log; running the
same command again resumes.
"""
from __future__ import annotations

import logging
import os
import sys

# This script's name is the minigrid package's: with its folder first on the import path (Python puts it there),
# ``import minigrid`` would import this file. Its folder holds nothing else the recipe imports.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import hydra
from omegaconf import DictConfig, OmegaConf

from torchrl_options.experiments.minigrid import run_minigrid, store_minigrid_config
from torchrl_options.experiments.recipe_runner import log_to_file, recipe_guard

store_minigrid_config()  # the schema of the `minigrid` section, named in config/minigrid.yaml's defaults


def run(cfg: DictConfig) -> str:
    """Runs the stages described by ``cfg`` (the composed Hydra config), writes the outputs, prints the summary."""
    out_dir = os.path.abspath(cfg.out_dir)
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "config.yaml"), "w") as f:
        f.write(OmegaConf.to_yaml(cfg, resolve=True))
    with log_to_file(os.path.join(out_dir, cfg.log_file), quiet_console=True):
        summary = run_minigrid(
            OmegaConf.to_container(cfg.minigrid, resolve=True), out_dir=out_dir, backend=cfg.backend,
            num_workers=cfg.num_workers, ray_address=cfg.ray_address,
            allow_changed_settings=bool(cfg.allow_changed_settings), progress=bool(cfg.progress),
            title=f"MiniGrid, scale `{cfg.scale_name}`",
        )  # fmt: skip
    print(summary)
    print(f"summary.md, segmentation.jsonl, results.csv, curves.png and {cfg.log_file} in {out_dir}")
    return summary


@hydra.main(version_base="1.3", config_path="config", config_name="minigrid")
def main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    with recipe_guard(cfg.out_dir, checkpoints="rl/*.partial.pt"):  # one line for a bad setting or an interruption
        run(cfg)


if __name__ == "__main__":
    main()
