"""Training objectives: the DDO loss."""
from torchrl_options.objectives.ddo import DDOLoss, option_log_probs

__all__ = ["DDOLoss", "option_log_probs"]
