"""Segment demonstrations into skills with DDO (Fox et al., 2017, section 5.3), and score the boundaries.

Loads trajectories (or generates a benchmark), discovers options, decodes each trajectory, and writes to
``output_dir``:

- ``segmentation.npz``: ``options`` [N, T] (-1 on padding), ``boundaries`` [N, T] bool (a segment starts; never
  at t = 0), ``posterior`` [N, T, K], ``switch_probability`` [N, T], ``log_likelihood`` [N], ``lengths`` [N], and
  ``reference_boundaries`` [N, T] when the data has them;
- ``options.pt``: the discovered options (``torchrl_options.load_options``);
- ``metrics.json`` and ``metrics.md``: the log-likelihood and, with reference boundaries, the paper's boundary
  accuracy, precision, recall and F1 within +-window steps, next to random boundaries at the same rate;
- ``segmentation.png``: one row per trajectory coloured by option, reference boundaries marked x (figure 5).

Run::

    python recipes/segment.py                                   # continuous pick-and-place demo
    python recipes/segment.py data.source=gridworld              # GridWorld sub-goal patrols (8 options)
    python recipes/segment.py data.source=gridworld data.grid=four-rooms
    python recipes/segment.py data.source=file data.path=demos.npz discovery.num_options=5 output_dir=out

File formats and keys: :mod:`torchrl_options.segmentation.io`. Settings: ``recipes/config/segment.yaml``.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_options import discover_options, save_options
from torchrl_options.envs import available_maps
from torchrl_options.experiments.recipe_runner import recipe_guard, run_recipe_main
from torchrl_options.experiments.segment_config import segment_settings
from torchrl_options.segmentation import (
    boundary_metrics,
    gridworld_subgoal_demonstrations,
    load_trajectories,
    plot_segmentation,
    random_baseline,
    reach_grasp_demonstrations,
    segment,
)

logger = logging.getLogger("segment")


def _sizes(value):
    """A config's hidden sizes for discover_options: None and ints as they are, a list (Hydra ListConfig) as a list."""
    return value if value is None or isinstance(value, int) else list(value)


def load_data(cfg: DictConfig):
    source = cfg.data.source
    if source == "continuous":
        return reach_grasp_demonstrations(cfg.data.num_trajectories, seed=cfg.data.seed)
    if source == "gridworld":
        grid = cfg.data.get("grid", "diamond")
        if grid not in ("diamond", *available_maps()):
            grid = hydra.utils.to_absolute_path(grid)  # a map file
        return gridworld_subgoal_demonstrations(
            cfg.data.num_trajectories, cfg.data.length, grid=grid, seed=cfg.data.seed
        )
    if source == "file":
        if not cfg.data.path:
            raise ValueError("data.source=file needs data.path=<file or directory>.")
        return load_trajectories(hydra.utils.to_absolute_path(cfg.data.path), format=cfg.data.format)
    raise ValueError(f"data.source must be 'continuous', 'gridworld' or 'file', got {source!r}.")


def _fmt(x: float) -> str:
    return "n/a" if isinstance(x, float) and math.isnan(x) else (f"{x:.3f}" if isinstance(x, float) else str(x))


def run(cfg: DictConfig) -> dict:
    """Runs the recipe; returns the metrics dict (also written to ``metrics.json``)."""
    cfg = segment_settings(cfg)  # the schema's keys and types, every value checked, before any work
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = load_data(cfg)
    action_space = cfg.discovery.action_space
    if action_space == "auto":
        action_space = "continuous" if data["action"].is_floating_point() else "categorical"
    lengths = data["collector", "mask"].sum(1)
    logger.info("%d trajectories, %d steps (%s actions)", data.batch_size[0], int(lengths.sum()), action_space)

    d = cfg.discovery
    num_options = d.num_options
    if num_options is None:  # the benchmarks' choice: twice the 4 sub-goals of the GridWorld demo, else 4
        num_options = 8 if cfg.data.source == "gridworld" else 4
    result = discover_options(
        data, num_options, action_space=action_space, meta_control=d.meta_control, init=d.init,
        num_cells=list(d.num_cells),
        termination_cells=_sizes(d.get("termination_cells")),
        init_scale=d.get("init_scale") if action_space == "continuous" else None,
        num_iterations=d.num_iterations, lr=d.lr, batch_size=d.batch_size, m_steps=d.m_steps, restarts=d.restarts,
        tol=d.tol, seed=d.seed,
        progress=cfg.progress, return_info=True, desc=f"DDO: {num_options} options, {d.meta_control} meta-control",
    )
    save_options(result.options, out / "options.pt")
    s = cfg.segmentation
    seg = segment(data, result, method=s.method, boundary=s.boundary)

    arrays = seg.to_dict()
    metrics: dict = {
        "num_trajectories": int(data.batch_size[0]),
        "num_steps": int(lengths.sum()),
        "num_options": int(num_options),
        "log_likelihood_per_step": float(seg.log_likelihood.sum() / lengths.sum()),
        "mean_segment_length": float(lengths.sum() / (seg.boundary_mask.sum() + data.batch_size[0])),
    }
    reference = data.get(s.reference_key, None) if s.reference_key else None
    if reference is not None:
        window = s.window if s.window is not None else (1 if cfg.data.source == "gridworld" else 2)
        arrays["reference_boundaries"] = reference.cpu().numpy().astype(bool)
        m = boundary_metrics(seg.boundary_mask, reference, window, lengths=lengths)
        base = random_baseline(reference, lengths, window, m["rate"], num_samples=s.baseline_samples, generator=0)
        metrics.update(window=int(window), **m, random={k: base[k] for k in ("accuracy", "precision", "recall", "f1")})
        metrics["random"]["expected_accuracy"] = base["expected_accuracy"]
    np.savez_compressed(out / "segmentation.npz", **arrays)

    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=True))
    lines = ["| quantity | value |", "|---|---|"]
    lines += [f"| {k} | {_fmt(v)} |" for k, v in metrics.items() if not isinstance(v, dict)]
    if "random" in metrics:
        lines += [f"| random {k} | {_fmt(v)} |" for k, v in metrics["random"].items()]
    (out / "metrics.md").write_text("\n".join(lines) + "\n")
    logger.info("metrics:\n%s", "\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    title = f"DDO segmentation ({s.method}), {num_options} options"
    if "accuracy" in metrics:
        title += f": boundary accuracy {_fmt(metrics['accuracy'])} (random {_fmt(metrics['random']['accuracy'])})"
    fig = plot_segmentation(
        seg.options, reference, lengths=lengths, num_options=num_options,
        max_trajectories=cfg.plot.max_trajectories, title=title, path=out / "segmentation.png",
    )
    plt.close(fig)
    logger.info("wrote %s", ", ".join(sorted(p.name for p in out.iterdir())))
    return metrics


@hydra.main(config_path="config", config_name="segment", version_base="1.3")
def main(cfg: DictConfig) -> None:
    logger.info("config:\n%s", OmegaConf.to_yaml(cfg))
    torch.manual_seed(cfg.discovery.seed)
    with recipe_guard(cfg.output_dir, checkpoints="(no checkpoints: this recipe reruns whole)"):
        run(cfg)


if __name__ == "__main__":
    run_recipe_main(main)  # Hydra's refusals (an unknown key, a wrong type) as one line too
