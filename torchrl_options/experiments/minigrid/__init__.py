"""Options discovered from the BabyAI bot's demonstrations on MiniGrid (issue 50): demonstrations labelled with
the bot's subgoals (:mod:`~torchrl_options.experiments.minigrid.demonstrations`)."""
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
)

__all__ = [
    "bot_demonstrations",
    "BotDemonstrations",
    "load_demonstrations",
    "save_demonstrations",
    "SKILLS",
    "skill_name",
    "SUBGOAL_TYPES",
    "subgoal_name",
    "TARGETS",
]
