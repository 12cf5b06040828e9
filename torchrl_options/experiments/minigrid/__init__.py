"""Options discovered from the BabyAI bot's demonstrations on MiniGrid (issue 50).

By job: :mod:`~torchrl_options.experiments.minigrid.demonstrations` (the bot's episodes labelled with its subgoals),
:mod:`~torchrl_options.experiments.minigrid.scoring` (scores against the subgoals, trivial baselines, what the
options held), :mod:`~torchrl_options.experiments.minigrid.segmentation` (one measurement: demonstrations, DDO,
``segment``, scores), :mod:`~torchrl_options.experiments.minigrid.summary` (tables over seeds),
:mod:`~torchrl_options.experiments.minigrid.config` (:class:`MiniGridConfig`, the recipe's schema),
:mod:`~torchrl_options.experiments.minigrid.pipeline` (cached options, resumable RL cells),
:mod:`~torchrl_options.experiments.minigrid.rl_summary` (success rates, frames to reach, curves) and
:mod:`~torchrl_options.experiments.minigrid.runner` (the recipe's driver). ``minigrid`` is imported only where a
level is made.
"""
from torchrl_options.experiments.minigrid.config import (
    ALGORITHMS,
    MiniGridConfig,
    OPTION_CONDITIONS,
    store_minigrid_config,
)
from torchrl_options.experiments.minigrid.demonstrations import (
    bot_demonstrations,
    BotDemonstrations,
    load_demonstrations,
    save_demonstrations,
    SKILLS,
    skill_name,
    SUBGOAL_TYPES,
    subgoal_name,
    TARGETS,
    with_previous_action,
)
from torchrl_options.experiments.minigrid.pipeline import level_options, minigrid_cells, run_minigrid_cell
from torchrl_options.experiments.minigrid.rl_summary import (
    frames_to_reach,
    plot_success_curves,
    rl_summary,
    rl_summary_markdown,
)
from torchrl_options.experiments.minigrid.runner import run_minigrid, write_minigrid_outputs
from torchrl_options.experiments.minigrid.scoring import (
    baseline_scores,
    option_composition,
    option_information,
    segmentation_scores,
)
from torchrl_options.experiments.minigrid.segmentation import option_factory, segmentation_cell
from torchrl_options.experiments.minigrid.summary import (
    composition_markdown,
    coverage_markdown,
    information_markdown,
    segmentation_markdown,
    segmentation_summary,
)

__all__ = [
    "ALGORITHMS",
    "baseline_scores",
    "bot_demonstrations",
    "BotDemonstrations",
    "composition_markdown",
    "coverage_markdown",
    "frames_to_reach",
    "information_markdown",
    "level_options",
    "load_demonstrations",
    "minigrid_cells",
    "MiniGridConfig",
    "OPTION_CONDITIONS",
    "option_composition",
    "option_information",
    "option_factory",
    "plot_success_curves",
    "rl_summary",
    "rl_summary_markdown",
    "run_minigrid",
    "run_minigrid_cell",
    "save_demonstrations",
    "segmentation_cell",
    "segmentation_markdown",
    "segmentation_scores",
    "segmentation_summary",
    "SKILLS",
    "skill_name",
    "store_minigrid_config",
    "SUBGOAL_TYPES",
    "subgoal_name",
    "TARGETS",
    "with_previous_action",
    "write_minigrid_outputs",
]
