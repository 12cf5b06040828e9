"""Option discovery for users: one-call DDO (:func:`discover_options`), its settings and stages, initialisation, and
saving/loading options."""
from torchrl_options.discovery.batch import as_trajectory_batch
from torchrl_options.discovery.discover import discover, discover_options
from torchrl_options.discovery.fit import converged_at, fit_ddo
from torchrl_options.discovery.networks import default_options, Networks
from torchrl_options.discovery.settings import (
    AUTO_RESTARTS,
    CONTINUOUS_PATIENCE,
    DEFAULT_PATIENCE,
    DEFAULT_RESTARTS,
    DiscoverySettings,
    INITS,
    PAPER_SETTINGS,
)
from torchrl_options.discovery.stages import DiscoveryResult
from torchrl_options.discovery.diagnostics import (
    option_diagnostics,
    OptionDiagnostics,
    options_in_use,
    restart_disagreement,
    UNUSED_SHARE,
)
from torchrl_options.discovery.initialization import (
    change_points,
    clone_from_labels,
    kmeans,
    pretrain_on_clusters,
    pretrain_on_segments,
)
from torchrl_options.discovery.serialization import load_options, save_options
from torchrl_options.discovery.tabulated import TabulatedDDO, unique_rows
from torchrl_options.discovery.usage_floor import check_usage_floor, UsageFloor

__all__ = [
    "as_trajectory_batch",
    "AUTO_RESTARTS",
    "change_points",
    "clone_from_labels",
    "CONTINUOUS_PATIENCE",
    "converged_at",
    "default_options",
    "DEFAULT_PATIENCE",
    "DEFAULT_RESTARTS",
    "INITS",
    "discover",
    "discover_options",
    "DiscoveryResult",
    "DiscoverySettings",
    "fit_ddo",
    "kmeans",
    "load_options",
    "Networks",
    "option_diagnostics",
    "options_in_use",
    "OptionDiagnostics",
    "PAPER_SETTINGS",
    "pretrain_on_clusters",
    "pretrain_on_segments",
    "restart_disagreement",
    "save_options",
    "TabulatedDDO",
    "unique_rows",
    "UsageFloor",
    "check_usage_floor",
]
