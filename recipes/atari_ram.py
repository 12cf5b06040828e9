"""Atari RAM reproduction of the DDO paper's figure 3: DQN with DDO options against DQN with actions only.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.2. Per game and seed:
phase 1, DQN with primitive actions; phase 2, greedy trajectories of that DQN and DDO with the game's number of
options; phase 3, DQN over actions + options from a reset Q-function (``H1``) against phase 1's DQN continued
with actions only (``A``). See ``torchrl_options.experiments.atari``.

Run:
    python recipes/atari_ram.py preset=smoke game=Seaquest          # about a minute on 2 CPU cores
    python recipes/atari_ram.py preset=gpu-hour game=Pooyan          # about an hour on a 16-core GPU machine
    python recipes/atari_ram.py preset=paper sweep.backend=ray sweep.ray_address=auto
    python recipes/atari_ram.py preset=cores16 "conditions=[A,H1,A0,H1w]"   # with the control and the warm start
    python recipes/atari_ram.py preset=cpu-vec "conditions=[A,H1,H1g]"     # + options that act greedily
    python recipes/atari_ram.py preset=cpu-vec "conditions=[A,H1,H1i]"     # + primitive actions learned inside options
    python recipes/atari_ram.py preset=cores16-vec                        # cores16's budget batched, greedy eval, 12 seeds
    python recipes/atari_ram.py preset=cpu-vec-rr                         # cpu-vec at DQN's usual replay ratio, 8 seeds

Writes to ``out_dir``: ``results.csv`` (one row per episode and cell, re-runs skip finished cells),
``summary.md`` (with aggregates over the games), ``curves.png``, ``aggregates.png``,
``option_frames/<game>/option<h>.{png,avi}`` (figure 4) and per-seed checkpoints.
"""
from __future__ import annotations

import logging
import os
from functools import partial

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_options.experiments import (
    aggregates_markdown,
    check_run_settings,
    plot_aggregates,
    plot_curves,
    ResultsLog,
    run_sweep,
    summarize,
    summary_markdown,
)
from torchrl_options.experiments.recipe_runner import recipe_guard
from torchrl_options.experiments.atari.config import check_atari_recipe_settings
from torchrl_options.experiments.atari import (
    AtariConfig,
    store_atari_config,
    atari_aggregates,
    atari_cells,
    atari_comparison,
    atari_summary_markdown,
    atari_summary_pairs,
    demonstration_fit_markdown,
    greedy_evaluation_markdown,
    option_usage_markdown,
    run_atari_cell,
)

log = logging.getLogger("atari_ram")
store_atari_config()  # the schema of the `atari` section, named in config/atari_ram.yaml's defaults


def run(cfg: DictConfig) -> list:
    """Runs the sweep described by ``cfg`` (the composed Hydra config), writes its outputs, returns the cells that ran
    (finished cells found in ``results.csv`` are skipped; an ``out_dir`` made with other ``atari`` settings is
    refused unless ``allow_changed_settings``)."""
    check_atari_recipe_settings(OmegaConf.to_container(cfg, resolve=True))  # every setting, before any work
    config = AtariConfig.from_dict(OmegaConf.to_container(cfg.atari, resolve=True))
    out_dir = os.path.abspath(cfg.out_dir)
    # finished cells are skipped and phase-1 checkpoints reused: only with the settings they were made with
    check_run_settings(out_dir, {"atari": config.cell_settings()}, allow_changes=bool(cfg.allow_changed_settings))
    with open(os.path.join(out_dir, "config.yaml"), "w") as f:
        f.write(OmegaConf.to_yaml(cfg, resolve=True))
    results = ResultsLog(os.path.join(out_dir, "results.csv"))
    cells = sweep_cells(cfg)
    cell_fn = partial(run_atari_cell, config=config, out_dir=out_dir)
    if config.torch_threads:  # the library sets no thread count: here for a serial sweep, in the workers below
        torch.set_num_threads(config.torch_threads)

    def on_result(cell, result):
        log.info("%s done: %d episodes, mean phase-3 return %.3f, %.0fs", cell.name, len(result.returns),
                 sum(result.returns[config.phase1_episodes:]) / max(len(result.returns) - config.phase1_episodes, 1),
                 result.info.get("seconds", float("nan")))

    ran = run_sweep(
        cell_fn,
        cells,
        results,
        backend=cfg.sweep.backend,
        num_workers=cfg.sweep.num_workers,
        ray_address=cfg.sweep.ray_address,
        threads_per_worker=config.torch_threads or cfg.sweep.threads_per_worker,
        on_result=on_result,
    )
    log.info("%d cells ran, %d were already finished", len(ran), len(cells) - len(ran))
    write_outputs(results, out_dir, cfg, config)
    return ran


def sweep_cells(cfg: DictConfig) -> list:
    """The cells of the sweep: ``game`` (or ``games``) x ``seeds`` (a count, or a list of seeds) x ``conditions``."""
    games = [cfg.game] if cfg.get("game") else list(cfg.games)
    seeds = cfg.seeds
    conditions = list(cfg.get("conditions") or ["A", "H1"])
    return atari_cells(games, int(seeds) if isinstance(seeds, (int, str)) else [int(s) for s in seeds], conditions)


def write_outputs(results: ResultsLog, out_dir: str, cfg: DictConfig, config: AtariConfig) -> None:
    """``summary.md`` (aggregates over games; per game, each pair of conditions that ran, the paper's H1 vs A first;
    option usage; the generic per-condition table), ``curves.png`` and ``aggregates.png``."""
    rows = results.rows()  # read once for every pair
    text = f"# Atari RAM, preset `{cfg.preset_name}`\n\n"
    pairs = atari_summary_pairs({r["condition"] for r in rows})
    agg = atari_aggregates(rows, phase1_episodes=config.phase1_episodes, pairs=pairs)
    if agg is not None:
        text += ("## Aggregates over games (Agarwal et al. 2021)\n\n"
                 + aggregates_markdown(agg, score_name="each run's mean phase-3 training return")
                 + "\nPlotted in `aggregates.png`. Per game, below.\n\n")
        plot_aggregates(agg, os.path.join(out_dir, "aggregates.png"), title="Atari RAM")
    for condition, baseline in pairs:
        comparisons = atari_comparison(rows, phase1_episodes=config.phase1_episodes, final_window=cfg.final_window,
                                       condition=condition, baseline=baseline)
        text += atari_summary_markdown(comparisons, final_window=cfg.final_window,
                                       header=f"## {condition} vs {baseline}") + "\n"
    text += greedy_evaluation_markdown(out_dir, pairs, phase1_episodes=config.phase1_episodes)
    fit = demonstration_fit_markdown(out_dir)
    if fit:
        text += ("\n## Phase 2: the options' fit to their demonstrator, and the demonstrations' quality gate\n\n"
                 "Log-likelihood per step of each seed's greedy demonstrations under its discovered options (uniform "
                 "meta-control, options marginalised), next to the epsilon-greedy demonstrator's own log-probability "
                 "of its (greedy) actions. A demonstrator is degenerate when its demonstrations' mean return is no "
                 "better than a random policy's on the same game.\n\n" + fit)
    usage = option_usage_markdown(out_dir)
    if usage:
        text += "\n## Option usage in phase 3 (from the replay buffer)\n\n" + usage + "\n"
    env = config.env_kwargs()
    skip = env["frame_skip"]
    evaluation = f"every {config.eval_every} episodes, {config.eval_episodes} rollouts" if config.eval_every else "off"
    skip_text = f"{skip[0]}-{skip[1] - 1} (uniform)" if isinstance(skip, (tuple, list)) else str(skip)
    text += (
        f"\nBudget per cell: {config.phase1_episodes} phase-1 episodes (shared), {config.num_demonstrations} "
        f"greedy trajectories, DDO {config.ddo_iterations} iterations, {config.phase3_episodes} phase-3 episodes. "
        f"Env (`env_semantics={config.env_semantics}`): episodes of at most {env['max_episode_steps']} steps of "
        f"{skip_text} frames, sticky actions {env['repeat_action_probability']}, rewards "
        f"{'clipped to [-1, 1]' if env['clip_rewards'] else 'raw'}, up to {env['noop_max']} no-op starts. Q-network "
        f"input `{config.ram_encoding}`, hidden {list(config.hidden_sizes)} tanh; options `{config.option_encoding}`, "
        f"hidden {list(config.options_num_cells)} tanh; discount per {config.discount_per}, gamma {config.gamma}; "
        f"greedy evaluation {evaluation}.\n\n"
        "## Whole runs (phase 1 + phase 3), per condition\n\n"
    )
    text += summary_markdown(summarize(results, final_window=cfg.final_window, smooth_window=cfg.smooth_window),
                             final_window=cfg.final_window)
    with open(os.path.join(out_dir, "summary.md"), "w") as f:
        f.write(text)
    plot_curves(results, os.path.join(out_dir, "curves.png"), smooth_window=cfg.smooth_window, title="Atari RAM")
    print(text)


@hydra.main(version_base="1.3", config_path="config", config_name="atari_ram")
def main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    with recipe_guard(cfg.out_dir, checkpoints="<game>/seed<s>"):  # one line for a bad setting or an interruption
        run(cfg)


if __name__ == "__main__":
    main()
