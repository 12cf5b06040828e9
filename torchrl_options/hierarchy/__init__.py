"""Multi-level hierarchies of options (Fox et al., 2017, section 4.3): exact inference of a level over fixed lower
levels, the hierarchical DDO loss, the :class:`OptionHierarchy` container and one-call discovery."""
from torchrl_options.hierarchy.discover import discover_hierarchy, HierarchyDiscoveryResult
from torchrl_options.hierarchy.hierarchy import load_hierarchy, OptionHierarchy, save_hierarchy
from torchrl_options.hierarchy.inference import hierarchical_forward_backward, HierarchyPosterior, stack_shapes
from torchrl_options.hierarchy.loss import HierarchicalDDOLoss

__all__ = [
    "discover_hierarchy",
    "hierarchical_forward_backward",
    "HierarchicalDDOLoss",
    "HierarchyDiscoveryResult",
    "HierarchyPosterior",
    "load_hierarchy",
    "OptionHierarchy",
    "save_hierarchy",
    "stack_shapes",
]
