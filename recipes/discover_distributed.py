"""Data-parallel DDO (Fox et al., 2017) over ``torch.distributed``: each process streams its own shard of the
trajectories of a demonstration buffer on disk, and the gradients are all-reduced every G-step.

Run (one command; ``torchrun`` starts the processes and the process group's rendezvous)::

    torchrun --nproc-per-node 2 recipes/discover_distributed.py                       # planted demo, 2 CPU processes
    torchrun --nproc-per-node 2 recipes/discover_distributed.py data.path=demos discovery.num_options=4
    torchrun --nproc-per-node 8 recipes/discover_distributed.py data.path=demos device=cuda   # 8 GPUs, NCCL
    python recipes/discover_distributed.py                                            # one process

``data.path`` is a directory written by :func:`torchrl_options.data.write_demonstrations` (or
:func:`~torchrl_options.data.write_demonstration_files`); without it, process 0 writes planted corridor
demonstrations into ``<output_dir>/demonstrations`` first. Process 0 writes ``options.pt``
(:func:`torchrl_options.load_options`) and ``metrics.json`` (processes, iterations, seconds, iterations per
second, final log-likelihood per step) to ``output_dir``. Settings: ``recipes/config/discover_distributed.yaml``, its schema
:class:`~torchrl_options.experiments.discover_distributed_config.DiscoverDistributedConfig`.
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import hydra
import torch
import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf

from torchrl_options import discover_options, save_options
from torchrl_options.data import demonstration_buffer, MANIFEST, open_demonstrations
from torchrl_options.experiments.discover_distributed_config import discover_distributed_settings
from torchrl_options.experiments.recipe_runner import recipe_guard, run_recipe_main
from torchrl_options.testing import write_planted_corridor

logger = logging.getLogger("discover_distributed")


def _device(cfg: DictConfig, local_rank: int) -> torch.device:
    if cfg.device == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    if cfg.device == "cuda":
        return torch.device(f"cuda:{local_rank}")
    return torch.device(cfg.device)


def _demonstrations(cfg: DictConfig, rank: int, world_size: int):
    if cfg.data.path:
        return open_demonstrations(hydra.utils.to_absolute_path(cfg.data.path))
    path = Path(cfg.output_dir) / "demonstrations"
    if rank == 0 and not (path / MANIFEST).exists():
        n, length = cfg.data.planted_trajectories, cfg.data.planted_length
        write_planted_corridor(demonstration_buffer(n * length, path=path), n, length, seed=cfg.data.seed)
        logger.info("wrote %d planted trajectories of %d steps to %s", n, length, path)
    if world_size > 1:
        dist.barrier()
    return open_demonstrations(path)


def run(cfg: DictConfig) -> dict:
    """Runs the recipe in this process (one of ``WORLD_SIZE``); returns the metrics (written by process 0)."""
    cfg = discover_distributed_settings(cfg)  # the schema's keys and types, every value checked, before any work
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    torch.set_num_threads(cfg.threads)
    device = _device(cfg, local_rank)
    if world_size > 1:
        backend = cfg.backend if cfg.backend != "auto" else ("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group(backend)
    try:
        out = Path(cfg.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        buffer = _demonstrations(cfg, rank, world_size)
        d = cfg.discovery
        start = time.perf_counter()
        result = discover_options(
            buffer, d.num_options, batch_size=d.batch_size, chunk_trajectories=d.chunk_trajectories,
            eval_trajectories=d.eval_trajectories, m_steps=d.m_steps, lr=d.lr, num_iterations=d.num_iterations,
            tol=d.tol, patience=d.patience, restarts=d.restarts, init=d.init, num_cells=d.num_cells, seed=d.seed,
            device=device, distributed=world_size > 1, progress=cfg.progress and rank == 0, return_info=True,
            desc=f"DDO, {world_size} process{'es' if world_size > 1 else ''}",
        )  # fmt: skip
        seconds = time.perf_counter() - start
        metrics = {
            "processes": world_size,
            "device": str(device),
            "iterations": len(result.history),
            "seconds": seconds,
            "iterations_per_second": len(result.history) / seconds,
            "log_likelihood_per_step": result.final_log_likelihood_per_step,
            "converged": result.converged,
            "steps": len(buffer),
        }
        if rank == 0:
            save_options(result.options, out / "options.pt")
            (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
            logger.info("metrics: %s", metrics)
        return metrics
    finally:
        if world_size > 1:
            dist.destroy_process_group()


@hydra.main(config_path="config", config_name="discover_distributed", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if int(os.environ.get("RANK", "0")) == 0:
        logger.info("config:\n%s", OmegaConf.to_yaml(cfg))
    with recipe_guard(cfg.output_dir, checkpoints="(no checkpoints: this recipe reruns whole)"):
        run(cfg)


if __name__ == "__main__":
    run_recipe_main(main)  # Hydra's refusals (an unknown key, a wrong type) as one line too
