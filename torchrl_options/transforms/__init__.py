"""Environment transforms: running options inside TorchRL envs."""
from torchrl_options.transforms.decision_counter import DecisionCounter
from torchrl_options.transforms.option_executor import OptionExecutor

__all__ = ["DecisionCounter", "OptionExecutor"]
