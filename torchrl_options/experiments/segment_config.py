"""The settings of the segmentation recipe (``recipes/config/segment.yaml``): its Hydra schema
(:class:`SegmentRecipeConfig`, registered by :func:`store_segment_config`) and the checked config the recipe reads
(:func:`segment_settings`).

Hydra refuses an unknown key or a value of the wrong type while composing; :meth:`SegmentRecipeConfig.check`
refuses the values out of range before any work, the discovery settings through
:class:`~torchrl_options.discovery.DiscoverySettings` (so ``discovery.init`` takes what
:func:`~torchrl_options.discover_options` takes).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, List, Optional

from torchrl_options.checks import check_bool, check_choice, check_int, check_positive_number
from torchrl_options.discovery import DiscoverySettings
from torchrl_options.discovery.settings import ACTION_SPACES
from torchrl_options.experiments.recipe_config import structured_settings

__all__ = ["SegmentRecipeConfig", "segment_settings", "store_segment_config"]

#: the data the recipe segments: a demo source, or trajectories from a file
SOURCES = ("continuous", "gridworld", "file")
#: ``data.format``: :func:`~torchrl_options.segmentation.load_trajectories`' formats
FORMATS = ("auto", "npz", "hdf5", "tensordict")


@dataclass
class SegmentData:
    """``data``: ``source`` (one of :data:`SOURCES`); a file's ``path`` and ``format``; a demo's
    ``num_trajectories``, ``length`` (GridWorld demo) and ``grid``; the demo's ``seed``."""

    source: str = "continuous"
    path: Optional[str] = None
    format: str = "auto"
    num_trajectories: int = 32
    length: Optional[int] = None
    grid: str = "diamond"
    seed: Optional[int] = None


@dataclass
class SegmentDiscovery:
    """``discovery``: :func:`~torchrl_options.discover_options`' settings of the same names (``num_options``
    ``None``: 8 for the GridWorld demo, 4 otherwise; ``action_space`` ``"auto"``: from the actions' dtype)."""

    num_options: Optional[int] = None
    action_space: str = "auto"
    meta_control: str = "uniform"
    init: str = "random"
    num_cells: List[int] = field(default_factory=lambda: [16])
    termination_cells: Optional[List[int]] = None
    init_scale: Optional[float] = None
    num_iterations: int = 300
    lr: float = 0.01
    m_steps: int = 1
    restarts: Optional[int] = 1
    tol: Optional[float] = None
    batch_size: Optional[int] = None
    seed: Optional[int] = None

    def check(self, name: str) -> None:
        """The settings as :class:`~torchrl_options.discovery.DiscoverySettings` (the library's checks)."""
        check_int(self.num_options, f"{name}.num_options", minimum=1, allow_none=True)
        check_choice(self.action_space, f"{name}.action_space", ("auto", *ACTION_SPACES))
        if self.init_scale is not None:
            check_positive_number(self.init_scale, f"{name}.init_scale")
        for key in ("num_cells", "termination_cells"):
            sizes = getattr(self, key)
            if sizes is not None and (not sizes or any(c < 1 for c in sizes)):
                raise ValueError(f"{name}.{key} must be a non-empty list of ints >= 1, got {list(sizes)!r}.")
        check_positive_number(self.lr, f"{name}.lr")
        check_int(self.seed, f"{name}.seed", minimum=0, allow_none=True)
        values = {k: v for k, v in dataclasses.asdict(self).items() if k not in ("action_space", "init_scale", "lr")}
        try:
            DiscoverySettings(**{**values, "num_options": self.num_options or 1, "num_cells": tuple(self.num_cells)})
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name}.{err}") from None


@dataclass
class SegmentMethod:
    """``segmentation``: the decoding ``method`` (``"viterbi"``, ``"posterior"``), what counts as a ``boundary``
    (``"change"``, ``"switch"``), the metrics' ``window`` (``None``: 1 for the GridWorld demo, 2 otherwise), the
    random baseline's ``baseline_samples`` and the data's ``reference_key`` of true boundaries."""

    method: str = "viterbi"
    boundary: str = "change"
    window: Optional[int] = None
    baseline_samples: int = 100
    reference_key: Any = "true_switch"


@dataclass
class SegmentPlot:
    """``plot``: the rows of ``segmentation.png``."""

    max_trajectories: int = 10


@dataclass
class SegmentRecipeConfig:
    """The schema of the segmentation recipe: the sections of ``recipes/config/segment.yaml`` (which explains each
    key), ``output_dir`` and ``progress``."""

    data: SegmentData = field(default_factory=SegmentData)
    discovery: SegmentDiscovery = field(default_factory=SegmentDiscovery)
    segmentation: SegmentMethod = field(default_factory=SegmentMethod)
    plot: SegmentPlot = field(default_factory=SegmentPlot)
    output_dir: str = "outputs/segment"
    progress: bool = True

    def check(self) -> None:
        """Refuses, naming it, the first setting out of range."""
        data = self.data
        check_choice(data.source, "data.source", SOURCES)
        check_choice(data.format, "data.format", FORMATS)
        if data.source == "file" and not data.path:
            raise ValueError("data.source=file needs data.path=<file or directory>.")
        if data.source != "file":
            check_int(data.num_trajectories, "data.num_trajectories", minimum=1)
            check_int(data.length, "data.length", minimum=1, allow_none=True)
        check_int(data.seed, "data.seed", minimum=0, allow_none=True)
        self.discovery.check("discovery")
        s = self.segmentation
        check_choice(s.method, "segmentation.method", ("viterbi", "posterior"))
        check_choice(s.boundary, "segmentation.boundary", ("change", "switch"))
        check_int(s.window, "segmentation.window", minimum=0, allow_none=True)
        check_int(s.baseline_samples, "segmentation.baseline_samples", minimum=1)
        check_int(self.plot.max_trajectories, "plot.max_trajectories", minimum=1)
        check_bool(self.progress, "progress")
        if not self.output_dir:
            raise ValueError(f"output_dir must be a folder name, got {self.output_dir!r}.")


def segment_settings(cfg: Any) -> Any:
    """The segmentation recipe's config (composed, or read with ``OmegaConf.load``) through
    :class:`SegmentRecipeConfig` (unknown keys and wrong types refused, naming the key) and checked
    (:meth:`SegmentRecipeConfig.check`): an OmegaConf ``DictConfig`` of the schema's keys.

    Raises:
        ValueError: naming the first bad setting.

    Examples:
        >>> segment_settings({"data": {"num_trajectories": 3}}).data.num_trajectories
        3
        >>> segment_settings({"data": {"source": "continuous", "num_trajectories": 0}})
        Traceback (most recent call last):
        ...
        ValueError: data.num_trajectories must be an int >= 1, got 0.
    """
    from omegaconf import OmegaConf

    cfg = structured_settings(SegmentRecipeConfig, cfg)
    OmegaConf.to_object(cfg).check()
    return cfg


def store_segment_config(name: str = "segment_schema") -> None:
    """Registers :class:`SegmentRecipeConfig` in Hydra's ``ConfigStore`` as ``name``, the schema that
    ``recipes/config/segment.yaml`` names first in its ``defaults``. Importing this module registers it when
    ``hydra-core`` is installed.

    Examples:
        >>> from hydra.core.config_store import ConfigStore
        >>> store_segment_config()
        >>> ConfigStore.instance().load("segment_schema.yaml").node.discovery.num_iterations
        300
    """
    if not isinstance(name, str) or not name:
        raise TypeError(f"store_segment_config: name must be a non-empty str, got {name!r}.")
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=name, node=SegmentRecipeConfig)


try:  # segment.yaml names the schema: registered on import
    store_segment_config()
except ImportError:  # pragma: no cover - hydra-core is the `recipes` extra
    pass
