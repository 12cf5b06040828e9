"""Training objectives: the DDO loss (and the base it shares with the hierarchical loss), and the guard that keeps
step-level option data out of policy-gradient losses."""
from torchrl_options.objectives.common import DDOLossBase
from torchrl_options.objectives.ddo import DDOLoss, option_log_probs
from torchrl_options.objectives.decision_guard import guard_decision_level, is_step_level_option_data, StepLevelDataError

__all__ = [
    "DDOLoss",
    "DDOLossBase",
    "StepLevelDataError",
    "guard_decision_level",
    "is_step_level_option_data",
    "option_log_probs",
]
