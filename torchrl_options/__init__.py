"""torchrl-options: options (temporally extended actions) for TorchRL, and DDO.

DDO is Discovery of Deep Options: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep
Options", arXiv:1703.08294, 2017.
"""
from torchrl_options.discovery import (
    as_trajectory_batch,
    discover_options,
    DiscoveryResult,
    load_options,
    save_options,
)
from torchrl_options.inference import (
    forward_backward,
    ForwardBackwardOutput,
    most_likely_options,
    viterbi,
    ViterbiOutput,
)
from torchrl_options.modules import GaussianOptionsMLP, MetaControlMLP, OptionsMLP, UniformMetaControl
from torchrl_options.objectives import DDOLoss, option_log_probs

__version__ = "0.1.0"

__all__ = [
    "as_trajectory_batch",
    "DDOLoss",
    "discover_options",
    "DiscoveryResult",
    "forward_backward",
    "ForwardBackwardOutput",
    "GaussianOptionsMLP",
    "load_options",
    "MetaControlMLP",
    "most_likely_options",
    "option_log_probs",
    "OptionsMLP",
    "save_options",
    "UniformMetaControl",
    "viterbi",
    "ViterbiOutput",
]
