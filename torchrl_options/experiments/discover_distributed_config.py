"""The settings of the data-parallel discovery recipe (``recipes/config/discover_distributed.yaml``): its Hydra
schema (:class:`DiscoverDistributedConfig`, registered by :func:`store_discover_distributed_config`) and the
checked config the recipe reads (:func:`discover_distributed_settings`).

Hydra refuses an unknown key or a value of the wrong type while composing; :meth:`DiscoverDistributedConfig.check`
refuses the values out of range before any process group is made, the discovery settings through
:class:`~torchrl_options.discovery.DiscoverySettings` (so ``discovery.init`` takes what
:func:`~torchrl_options.discover_options` takes, and ``chunk_trajectories`` needs ``m_steps=1`` there too).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Optional

from torchrl_options.checks import check_bool, check_choice, check_int, check_positive_number
from torchrl_options.discovery import DiscoverySettings
from torchrl_options.experiments.recipe_config import structured_settings
from torchrl_options.modules import hidden_sizes

__all__ = ["DiscoverDistributedConfig", "discover_distributed_settings", "store_discover_distributed_config"]

#: ``device``: each process's GPU when CUDA is there (``auto``), the CPU, or the process's GPU
DEVICES = ("auto", "cpu", "cuda")
#: ``backend``: the process group's (``auto``: nccl on CUDA, gloo on the CPU)
BACKENDS = ("auto", "gloo", "nccl")


@dataclass
class DistributedData:
    """``data``: a demonstration directory's ``path`` (``None``: planted corridor demonstrations of
    ``planted_trajectories`` x ``planted_length`` steps, written from ``seed``)."""

    path: Optional[str] = None
    planted_trajectories: int = 64
    planted_length: int = 1000
    seed: int = 0


@dataclass
class DistributedDiscovery:
    """``discovery``: :func:`~torchrl_options.discover_options`' settings of the same names."""

    num_options: int = 8
    batch_size: Optional[int] = 16
    chunk_trajectories: Optional[int] = None
    eval_trajectories: int = 64
    m_steps: int = 5
    lr: float = 0.03
    num_iterations: int = 200
    tol: Optional[float] = 1e-4
    patience: Optional[int] = None
    restarts: Optional[int] = 1
    init: str = "auto"
    num_cells: Any = 8
    seed: int = 0

    def check(self, name: str) -> None:
        """The settings as :class:`~torchrl_options.discovery.DiscoverySettings` (the library's checks), the
        learning rate and the options' hidden sizes (checked where the networks are built)."""
        check_positive_number(self.lr, f"{name}.lr")
        values = dataclasses.asdict(self)
        values["num_cells"] = tuple(hidden_sizes(values["num_cells"], f"{name}.num_cells"))
        try:
            DiscoverySettings(**values)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name}.{err}") from None


@dataclass
class DiscoverDistributedConfig:
    """The schema of the data-parallel recipe: the sections of ``recipes/config/discover_distributed.yaml``
    (which explains each key), ``device`` (one of :data:`DEVICES`), ``backend`` (one of :data:`BACKENDS`),
    ``threads`` (torch threads per process), ``output_dir`` and ``progress``."""

    data: DistributedData = field(default_factory=DistributedData)
    discovery: DistributedDiscovery = field(default_factory=DistributedDiscovery)
    device: str = "auto"
    backend: str = "auto"
    threads: int = 1
    output_dir: str = "outputs/discover_distributed"
    progress: bool = True

    def check(self) -> None:
        """Refuses, naming it, the first setting out of range."""
        if self.data.path is not None and not self.data.path:
            raise ValueError("data.path must be a demonstration directory or null, got ''.")
        check_int(self.data.planted_trajectories, "data.planted_trajectories", minimum=1)
        check_int(self.data.planted_length, "data.planted_length", minimum=1)
        check_int(self.data.seed, "data.seed", minimum=0)
        self.discovery.check("discovery")
        check_choice(self.device, "device", DEVICES)
        check_choice(self.backend, "backend", BACKENDS)
        if self.backend == "nccl" and self.device == "cpu":
            raise ValueError("backend=nccl needs device=cuda (or auto on a CUDA machine), got device=cpu.")
        check_int(self.threads, "threads", minimum=1)
        check_bool(self.progress, "progress")
        if not self.output_dir:
            raise ValueError(f"output_dir must be a folder name, got {self.output_dir!r}.")


def discover_distributed_settings(cfg: Any) -> Any:
    """The data-parallel recipe's config (composed, or read with ``OmegaConf.load``) through
    :class:`DiscoverDistributedConfig` (unknown keys and wrong types refused, naming the key) and checked
    (:meth:`DiscoverDistributedConfig.check`): an OmegaConf ``DictConfig`` of the schema's keys.

    Raises:
        ValueError: naming the first bad setting.

    Examples:
        >>> discover_distributed_settings({"discovery": {"num_options": 4}}).discovery.num_options
        4
        >>> discover_distributed_settings({"threads": 0})
        Traceback (most recent call last):
        ...
        ValueError: threads must be an int >= 1, got 0.
    """
    from omegaconf import OmegaConf

    cfg = structured_settings(DiscoverDistributedConfig, cfg)
    OmegaConf.to_object(cfg).check()
    return cfg


def store_discover_distributed_config(name: str = "discover_distributed_schema") -> None:
    """Registers :class:`DiscoverDistributedConfig` in Hydra's ``ConfigStore`` as ``name``, the schema that
    ``recipes/config/discover_distributed.yaml`` names first in its ``defaults``. Importing this module registers
    it when ``hydra-core`` is installed.

    Examples:
        >>> from hydra.core.config_store import ConfigStore
        >>> store_discover_distributed_config()
        >>> ConfigStore.instance().load("discover_distributed_schema.yaml").node.discovery.num_options
        8
    """
    if not isinstance(name, str) or not name:
        raise TypeError(f"store_discover_distributed_config: name must be a non-empty str, got {name!r}.")
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=name, node=DiscoverDistributedConfig)


try:  # discover_distributed.yaml names the schema: registered on import
    store_discover_distributed_config()
except ImportError:  # pragma: no cover - hydra-core is the `recipes` extra
    pass
