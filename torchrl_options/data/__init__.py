"""Data utilities: decision-level (SMDP) transitions for Q-learning and policy gradients over options, the one-step transitions of
the primitive actions that options took, and demonstrations stored on disk in a replay buffer and read back as whole
trajectories (for streamed discovery)."""
from torchrl_options.data.demonstrations import (
    demonstration_buffer,
    MANIFEST,
    open_demonstrations,
    write_demonstration_files,
    write_demonstrations,
)
from torchrl_options.data.intra_option import intra_option_transitions, option_suffix_transitions
from torchrl_options.data.on_policy import OnPolicyDecisions
from torchrl_options.data.segments import rewarded_segments
from torchrl_options.data.smdp import SMDPTransform, SMDPTransitions, smdp_transitions
from torchrl_options.data.trajectory_reader import LAYOUTS, TrajectoryReader

__all__ = [
    "demonstration_buffer",
    "LAYOUTS",
    "MANIFEST",
    "OnPolicyDecisions",
    "open_demonstrations",
    "SMDPTransform",
    "SMDPTransitions",
    "intra_option_transitions",
    "option_suffix_transitions",
    "rewarded_segments",
    "smdp_transitions",
    "TrajectoryReader",
    "write_demonstration_files",
    "write_demonstrations",
]
