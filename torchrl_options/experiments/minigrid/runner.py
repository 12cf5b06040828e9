"""The MiniGrid recipe's driver (``recipes/minigrid.py`` is its Hydra front end): settings checked and recorded, the
segmentation cells, the RL sweep, and the outputs (``summary.md``, ``segmentation.jsonl``, ``results.csv``,
``curves.png``, the log)."""
from __future__ import annotations

import logging
import os
from functools import partial

__all__ = ["run_minigrid", "write_minigrid_outputs"]

logger = logging.getLogger(__name__)


def run_minigrid(settings: dict, *, out_dir: str, backend: str = "serial", num_workers: int | None = None,
                 ray_address: str | None = None, allow_changed_settings: bool = False, progress: bool = True,
                 title: str = "MiniGrid") -> str:
    """Runs the stages of :class:`~torchrl_options.experiments.minigrid.MiniGridConfig` ``settings`` into
    ``out_dir`` and returns the summary (Markdown). Finished segmentation cells (cached options) and RL cells (rows
    of ``results.csv``) are skipped, running RL cells resume from their checkpoints; an ``out_dir`` made with other
    settings is refused unless ``allow_changed_settings``."""
    from torchrl_options.experiments import check_run_settings, ResultsLog, run_sweep
    from torchrl_options.experiments.minigrid.config import MiniGridConfig
    from torchrl_options.experiments.minigrid.pipeline import (
        episode_cut_warning,
        level_options,
        minigrid_cells,
        run_minigrid_cell,
    )

    config = MiniGridConfig.from_dict(settings)
    out_dir = os.path.abspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    check_run_settings(out_dir, {"minigrid": config.cell_settings()}, allow_changes=allow_changed_settings)
    if config.torch_threads:
        import torch

        torch.set_num_threads(config.torch_threads)
    seg_cells = [(lv, s) for lv in config.segmentation_levels for s in range(config.segmentation_seeds)]
    bar = None
    if progress and seg_cells:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(seg_cells), desc="segmentation (demonstrations, DDO, scores)", unit="cell")
    try:
        for level, seed in seg_cells:
            level_options(level, seed, config, out_dir)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    results = ResultsLog(os.path.join(out_dir, "results.csv"))
    cells = minigrid_cells(config)
    cut = episode_cut_warning(config) if cells else None
    if cut is not None:
        logger.warning("%s", cut)
    rl_bar = None
    if progress and cells:
        from tqdm.auto import tqdm

        done = len(results.done_cells() & {(c.setting, c.condition, c.seed) for c in cells})
        rl_bar = tqdm(total=len(cells), initial=done, desc="RL cells", unit="cell")

    def on_result(cell, result):
        logger.info("%s done: %d episodes, %d successes, %.0fs", cell.name, len(result.returns),
                    sum(r > 0 for r in result.returns), result.info.get("seconds", float("nan")))
        if rl_bar is not None:
            rl_bar.update(1)

    try:
        run_sweep(partial(run_minigrid_cell, config=config, out_dir=out_dir, progress=progress and backend == "serial"),
                  cells, results, backend=backend, num_workers=num_workers, ray_address=ray_address,
                  threads_per_worker=config.torch_threads, on_result=on_result)  # fmt: skip
    finally:
        if rl_bar is not None:
            rl_bar.close()
    return write_minigrid_outputs(out_dir, config, title=title)


def write_minigrid_outputs(out_dir: str, config, *, title: str = "MiniGrid") -> str:
    """``summary.md`` (the segmentation scores against the bot's subgoals and skills with the baselines, what the
    options held, the RL table) and ``curves.png``; returns the summary."""
    from torchrl_options.experiments import ResultsLog
    from torchrl_options.experiments.minigrid.rl_summary import plot_success_curves, rl_summary, rl_summary_markdown
    from torchrl_options.experiments.minigrid.summary import composition_markdown, read_records, segmentation_markdown

    records = read_records(os.path.join(out_dir, "segmentation.jsonl"))
    text = f"# {title}\n\n"
    if records:
        text += ("## Segmentation of the BabyAI bot's demonstrations\n\nDDO's options (Viterbi labels of `segment`) "
                 "against the bot's subgoals (type and target) and skills, next to the trivial baselines on the same "
                 "demonstrations; mean [95% Student-t interval] over seeds.\n\n### Against the subgoals\n\n"
                 + segmentation_markdown(records, "subgoal") + "\n### Against the skills\n\n"
                 + segmentation_markdown(records, "skill") + "\n### What the options held (against the subgoal types)"
                 "\n\n" + composition_markdown(records, "subgoal"))  # fmt: skip
    rows = ResultsLog(os.path.join(out_dir, "results.csv")).rows()
    if rows:
        summaries = rl_summary(rows, target=config.success_target, window=config.success_window)
        text += (f"\n## RL on {config.rl_level} ({config.rl_frames} frames per cell)\n\n`A`: actions only; `H1`: "
                 f"actions + options from {config.rl_level}'s demonstrations; `H1t`: actions + options from "
                 f"{config.transfer_source}'s. Success: an episode with a positive return.\n\n"
                 + rl_summary_markdown(summaries, target=config.success_target, window=config.success_window))
        plot_success_curves(rows, os.path.join(out_dir, "curves.png"), title=title)
    with open(os.path.join(out_dir, "summary.md"), "w") as f:
        f.write(text)
    return text
