"""Data utilities: decision-level (SMDP) transitions for Q-learning and policy gradients over options, and the one-step transitions of
the primitive actions that options took."""
from torchrl_options.data.intra_option import intra_option_transitions, option_suffix_transitions
from torchrl_options.data.on_policy import OnPolicyDecisions
from torchrl_options.data.segments import rewarded_segments
from torchrl_options.data.smdp import SMDPTransform, SMDPTransitions, smdp_transitions

__all__ = [
    "OnPolicyDecisions",
    "SMDPTransform",
    "SMDPTransitions",
    "intra_option_transitions",
    "option_suffix_transitions",
    "rewarded_segments",
    "smdp_transitions",
]
