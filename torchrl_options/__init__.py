"""torchrl-options: options (temporally extended actions) for TorchRL, and DDO.

DDO is Discovery of Deep Options: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep
Options", arXiv:1703.08294, 2017.

The folders: ``inference`` (the E-step and decoding), ``modules`` (options and meta-control as TensorDict
modules), ``objectives`` (``DDOLoss``), ``discovery`` (one-call discovery, initialisation, save/load),
``hierarchy`` (multi-level discovery), ``transforms`` (``OptionExecutor``), ``data`` (SMDP transitions and
decision-level batches for PPO), ``agents`` (DQN and PPO over actions and options), ``envs`` (GridWorld, Atari RAM), ``segmentation``, ``experiments``
(what the recipes share) and ``testing`` (planted structures).
"""
from torchrl_options.agents import OptionsDQN, OptionsDQNConfig, OptionsPPO, OptionsPPOConfig
from torchrl_options.data import OnPolicyDecisions, smdp_transitions, SMDPTransform, SMDPTransitions
from torchrl_options.discovery import (
    as_trajectory_batch,
    discover_options,
    DiscoveryResult,
    load_options,
    save_options,
)
from torchrl_options.envs import generate_demonstrations, GridWorldEnv, ValueIterationSupervisor
from torchrl_options.hierarchy import (
    discover_hierarchy,
    HierarchicalDDOLoss,
    hierarchical_forward_backward,
    load_hierarchy,
    OptionHierarchy,
    save_hierarchy,
)
from torchrl_options.inference import (
    forward_backward,
    ForwardBackwardOutput,
    most_likely_options,
    viterbi,
    ViterbiOutput,
)
from torchrl_options.modules import GaussianOptionsMLP, MetaControlMLP, OptionsMLP, UniformMetaControl
from torchrl_options.objectives import DDOLoss, guard_decision_level, option_log_probs
from torchrl_options.segmentation import boundary_metrics, segment, Segmentation
from torchrl_options.transforms import DecisionCounter, OptionExecutor

__version__ = "0.1.0"

__all__ = [
    "as_trajectory_batch",
    "boundary_metrics",
    "DDOLoss",
    "DecisionCounter",
    "discover_hierarchy",
    "discover_options",
    "DiscoveryResult",
    "forward_backward",
    "ForwardBackwardOutput",
    "GaussianOptionsMLP",
    "generate_demonstrations",
    "GridWorldEnv",
    "guard_decision_level",
    "hierarchical_forward_backward",
    "HierarchicalDDOLoss",
    "load_hierarchy",
    "load_options",
    "MetaControlMLP",
    "most_likely_options",
    "OnPolicyDecisions",
    "option_log_probs",
    "OptionExecutor",
    "OptionHierarchy",
    "OptionsDQN",
    "OptionsDQNConfig",
    "OptionsMLP",
    "OptionsPPO",
    "OptionsPPOConfig",
    "save_hierarchy",
    "save_options",
    "segment",
    "Segmentation",
    "smdp_transitions",
    "SMDPTransform",
    "SMDPTransitions",
    "UniformMetaControl",
    "ValueIterationSupervisor",
    "viterbi",
    "ViterbiOutput",
]
