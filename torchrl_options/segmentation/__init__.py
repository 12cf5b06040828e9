"""Segmentation of demonstrations into the options that produced them (Fox et al., 2017, section 5.3).

:func:`segment` decodes trajectories with discovered options (posterior, Viterbi option sequence, boundaries);
:mod:`~torchrl_options.segmentation.metrics` scores boundaries against a reference (the paper's boundary
accuracy, precision/recall/F1, the random baseline); :mod:`~torchrl_options.segmentation.generators` plants
skills with known boundaries (continuous pick-and-place, GridWorld sub-goal tours);
:mod:`~torchrl_options.segmentation.io` loads demonstrations from files; :func:`plot_segmentation` draws
them like the paper's figure 5.
"""
from torchrl_options.segmentation.generators import (
    dead_ends,
    default_subgoals,
    diamond_map,
    gridworld_subgoal_demonstrations,
    REACH_GRASP_SKILLS,
    reach_grasp_demonstrations,
    room_centers,
)
from torchrl_options.segmentation.io import (
    load_trajectories,
    save_trajectories,
    trajectories_from_arrays,
    TrajectoryFileError,
)
from torchrl_options.segmentation.metrics import (
    as_boundary_lists,
    boundary_accuracy,
    boundary_metrics,
    boundary_precision_recall_f1,
    BoundaryScores,
    expected_random_accuracy,
    random_baseline,
    random_boundaries,
)
from torchrl_options.segmentation.plot import plot_segmentation
from torchrl_options.segmentation.segment import boundaries_from_options, segment, Segmentation

__all__ = [
    "as_boundary_lists",
    "dead_ends",
    "default_subgoals",
    "diamond_map",
    "boundaries_from_options",
    "boundary_accuracy",
    "boundary_metrics",
    "boundary_precision_recall_f1",
    "BoundaryScores",
    "expected_random_accuracy",
    "gridworld_subgoal_demonstrations",
    "load_trajectories",
    "plot_segmentation",
    "random_baseline",
    "random_boundaries",
    "REACH_GRASP_SKILLS",
    "reach_grasp_demonstrations",
    "room_centers",
    "save_trajectories",
    "segment",
    "Segmentation",
    "trajectories_from_arrays",
    "TrajectoryFileError",
]
