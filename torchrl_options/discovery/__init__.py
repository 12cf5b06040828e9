"""Option discovery for users: one-call DDO, initialisation, and saving/loading options."""
from torchrl_options.discovery.discover import as_trajectory_batch, discover_options, DiscoveryResult
from torchrl_options.discovery.initialization import kmeans, pretrain_on_clusters
from torchrl_options.discovery.serialization import load_options, save_options

__all__ = [
    "as_trajectory_batch",
    "discover_options",
    "DiscoveryResult",
    "kmeans",
    "load_options",
    "pretrain_on_clusters",
    "save_options",
]
