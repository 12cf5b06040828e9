"""Planted structures with known ground truth, for tests, benchmarks and sanity checks of discovery."""
from torchrl_options.testing.planted import label_accuracy, planted_corridor_demonstrations, write_planted_corridor
from torchrl_options.testing.planted_hierarchy import (
    planted_two_level_demonstrations,
    planted_two_level_log_probabilities,
)
from torchrl_options.testing.planted_suite import (
    best_matching_accuracy,
    planted_gaussian_demonstrations,
    planted_tabular_demonstrations,
    PLANTED_SUITE,
    PlantedProblem,
    posterior_accuracy,
)

__all__ = [
    "best_matching_accuracy",
    "label_accuracy",
    "planted_corridor_demonstrations",
    "planted_gaussian_demonstrations",
    "planted_tabular_demonstrations",
    "planted_two_level_demonstrations",
    "planted_two_level_log_probabilities",
    "PLANTED_SUITE",
    "PlantedProblem",
    "posterior_accuracy",
    "write_planted_corridor",
]
