"""Training objectives: the DDO loss (and the base it shares with the hierarchical loss)."""
from torchrl_options.objectives.common import DDOLossBase
from torchrl_options.objectives.ddo import DDOLoss, option_log_probs

__all__ = ["DDOLoss", "DDOLossBase", "option_log_probs"]
