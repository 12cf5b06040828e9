"""Data utilities: decision-level (SMDP) transitions for Q-learning over options."""
from torchrl_options.data.smdp import SMDPTransitions, smdp_transitions

__all__ = ["SMDPTransitions", "smdp_transitions"]
