"""Planted structures with known ground truth, for tests, benchmarks and sanity checks of discovery."""
from torchrl_options.testing.planted import label_accuracy, planted_corridor_demonstrations
from torchrl_options.testing.planted_hierarchy import (
    planted_two_level_demonstrations,
    planted_two_level_log_probabilities,
)

__all__ = ["label_accuracy", "planted_corridor_demonstrations", "planted_two_level_demonstrations",
           "planted_two_level_log_probabilities"]
