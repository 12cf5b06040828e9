"""The settings of the GridWorld recipes (``recipes/config/{two,three,four}_rooms*.yaml``): their Hydra schema
(:class:`GridWorldRecipeConfig`, registered by :func:`store_gridworld_config`), the ``protocol`` merge
(:func:`apply_protocol`) and the checked settings a run reads (:func:`gridworld_settings`).

The schema holds every key the recipes read, with its type: Hydra refuses an unknown key
(``discovery.num_optons=3``) or a value of the wrong type (``dqn.lr=abc``) while composing, naming the key; the
entries of ``settings`` and ``conditions`` (a name each, which the command line may add) are typed when checked. A
section's keys default to ``None``: left out, the reader's default applies (the ``dqn`` section's are
:class:`~torchrl_options.agents.OptionsDQNConfig`'s, the ``discovery`` section's the preset's). What a type cannot
say (ranges, choices, a map's name) each section's ``check`` refuses before any work starts, from the library's own
checks: the env is built, the agent's config made, the discovery settings made as
:class:`~torchrl_options.discovery.DiscoverySettings` (so ``discovery.init`` takes what
:func:`~torchrl_options.discover_options` takes).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from torchrl_options.agents import OptionsDQNConfig, OptionsPPOConfig
from torchrl_options.checks import check_bool, check_choice, check_int, check_number, check_positive_number
from torchrl_options.discovery import check_usage_floor, DiscoverySettings, PAPER_SETTINGS
from torchrl_options.envs import GridWorldEnv
from torchrl_options.experiments.recipe_config import (
    MISSING,
    agent_section,
    check_seeds,
    check_sweep,
    plain_settings,
    structured_settings,
)
from torchrl_options.modules import OptionsMLP

__all__ = [
    "AGENT_SECTIONS",
    "DISCOVERY_PRESETS",
    "GridWorldRecipeConfig",
    "PROTOCOLS",
    "apply_protocol",
    "discovery_iterations",
    "discovery_kwargs",
    "env_kwargs",
    "gridworld_settings",
    "store_gridworld_config",
]

#: ``protocol``: ``"ours"`` (the settings measured best) or ``"paper"`` (every ``paper:`` sub-section merged in)
PROTOCOLS = ("ours", "paper")
#: the DDO settings a recipe's ``discovery.preset`` starts from; the section's own (non-null) keys override them
DISCOVERY_PRESETS = ("paper", "defaults")
_DISCOVERY_KEYS = ("num_cells", "termination_cells", "activation", "init", "batch_size", "lr", "m_steps", "restarts", "tol")
#: the agents' config fields the recipe sets per cell
_PER_CELL = ("mode", "num_envs", "seed")
#: the sections of an agent's settings, where ``None`` is a value (``max_grad_norm: null``) and a key not set is
#: :data:`~torchrl_options.experiments.recipe_config.MISSING`
AGENT_SECTIONS = ("dqn", "ppo")

DQNSection = agent_section(OptionsDQNConfig, "DQNSection", _PER_CELL)
PPOSection = agent_section(OptionsPPOConfig, "PPOSection", _PER_CELL)


# ------------------------------------------------------------------------------------------------- helpers
def env_kwargs(env_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The :class:`~torchrl_options.envs.GridWorldEnv` keyword arguments of an ``env`` section (nulls left out,
    ``start``/``goal`` cells as tuples).

    Examples:
        >>> env_kwargs({"grid": "two-rooms", "start": [1, 2], "goal": None})
        {'grid': 'two-rooms', 'start': (1, 2)}
    """
    kwargs = {k: v for k, v in dict(env_cfg).items() if v is not None}
    for key in ("start", "goal"):
        if isinstance(kwargs.get(key), (list, tuple)):
            kwargs[key] = tuple(int(v) for v in kwargs[key])
    return kwargs


def discovery_kwargs(discovery: Mapping[str, Any]) -> dict[str, Any]:
    """The DDO settings of a recipe's ``discovery`` section shared by one- and multi-level discovery.

    ``discovery.preset`` says what the section leaves out (or sets to null): ``"paper"`` (the default when the
    section has no preset) takes :data:`~torchrl_options.discovery.PAPER_SETTINGS`, so that the recipes reproduce the
    paper's protocol; ``"defaults"`` takes :func:`~torchrl_options.discover_options`'s own defaults.

    Examples:
        >>> discovery_kwargs({"preset": "defaults", "num_options": 4, "lr": 0.1})
        {'num_actions': 4, 'lr': 0.1}
    """
    preset = discovery.get("preset") or "paper"
    base = dict(PAPER_SETTINGS) if preset == "paper" else {}
    base.pop("num_iterations", None)
    base.pop("termination_cells", None)  # as before presets: the termination networks are num_cells wide unless set
    kwargs = {"num_actions": 4, **{k: base[k] for k in _DISCOVERY_KEYS if k in base}}
    for key in _DISCOVERY_KEYS:
        if discovery.get(key) is not None:
            kwargs[key] = discovery[key]
    if isinstance(kwargs.get("num_cells"), list):
        kwargs["num_cells"] = tuple(kwargs["num_cells"])
    return kwargs


def discovery_iterations(discovery: Mapping[str, Any]) -> int:
    """The most DDO iterations: the section's ``num_iterations``, else the preset's (paper: 500; defaults: 1000,
    which the stopping rule usually ends sooner).

    Examples:
        >>> discovery_iterations({"preset": "defaults"}), discovery_iterations({}), discovery_iterations({"num_iterations": 7})
        (1000, 500, 7)
    """
    if discovery.get("num_iterations") is not None:
        return int(discovery["num_iterations"])
    return int(PAPER_SETTINGS["num_iterations"]) if (discovery.get("preset") or "paper") == "paper" else 1000


def apply_protocol(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The recipe config with its ``protocol`` applied: ``"ours"`` (the default) drops every section's ``paper``
    sub-section; ``"paper"`` merges each ``paper`` sub-section into its section (recursively), so that one
    setting, ``protocol=paper``, gives back the paper's protocol (its DDO settings, its greedy rollouts) where the
    recipe's defaults are the ones measured best (``docs/experiments/gridworld.md``). A ``paper`` sub-section left
    at ``None`` is dropped either way.

    Examples:
        >>> cfg = {"protocol": "paper", "discovery": {"preset": "defaults", "num_options": 4, "paper": {"preset": "paper"}}}
        >>> apply_protocol(cfg)["discovery"]
        {'preset': 'paper', 'num_options': 4}
        >>> apply_protocol({**cfg, "protocol": "ours"})["discovery"]
        {'preset': 'defaults', 'num_options': 4}
    """
    protocol = cfg.get("protocol") or "ours"
    check_choice(protocol, "protocol", PROTOCOLS)

    def resolve(section: Any, name: str) -> Any:
        if not isinstance(section, Mapping):
            return section
        out = {k: resolve(v, f"{name}.{k}" if name else k) for k, v in section.items() if k != "paper"}
        paper = section.get("paper")
        if paper is not None and protocol == "paper":
            if not isinstance(paper, Mapping):
                raise ValueError(f"{name + '.' if name else ''}paper must be a section of the paper's settings, got {paper!r}.")
            out = _merge(out, {k: resolve(v, f"{name}.paper.{k}") for k, v in paper.items()})
        return out

    return resolve(dict(cfg), "")


def _merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if value is None:  # a key the paper's section leaves out (the schema's None)
            continue
        out[key] = _merge(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), Mapping) else value
    return out


def _check_sizes(value: Any, name: str) -> None:
    ok = isinstance(value, (list, tuple)) and value and all(isinstance(h, int) and not isinstance(h, bool) and h >= 1
                                                            for h in value)  # fmt: skip
    if not ok:
        raise ValueError(f"{name} must be a list of ints >= 1, got {value!r}.")


def _agent_config(config_cls: type, section: Mapping[str, Any], name: str, **per_cell: Any) -> Any:
    """``config_cls`` built from a section's keys set; its own checks' messages prefixed with the section."""
    values = dict(section)
    if "hidden_sizes" in values:
        _check_sizes(values["hidden_sizes"], f"{name}.hidden_sizes")
        values["hidden_sizes"] = tuple(values["hidden_sizes"])
    try:
        return config_cls(**values, **per_cell)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name}.{err}") from None


def _entry(schema: type, value: Any, name: str) -> Any:
    """A ``settings``/``conditions`` entry as its section's dataclass: an unknown key or a wrong type is refused
    naming it (``conditions.H1u.mdoe``)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if not isinstance(value, Mapping):
        raise ValueError(f"{name} must be a section (a mapping of settings), got {value!r}.")
    try:
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), dict(value)))
    except OmegaConfBaseException as err:
        raise ValueError(f"{name}.{err.full_key}: {str(err.msg).splitlines()[0]}") from None


# ------------------------------------------------------------------------------------------------ sections
@dataclass
class EnvSection:
    """``env``: the :class:`~torchrl_options.envs.GridWorldEnv` arguments (``demos.env``: those that differ for the
    demonstrations); checked by building one env."""

    grid: Optional[str] = None
    task: Optional[str] = None
    noise: Optional[float] = None
    max_steps: Optional[int] = None
    start: Any = None
    goal: Any = None
    subgoals: Any = None
    one_hot: Optional[bool] = None
    normalize: Optional[bool] = None

    def check(self, name: str, base: EnvSection | None = None) -> None:
        """Builds the env of this section (over ``base``'s keys, for ``demos.env``): its checks name the argument."""
        check_int(self.max_steps, f"{name}.max_steps", minimum=1, allow_none=True)
        check_number(self.noise, f"{name}.noise", lo=0.0, hi=1.0, allow_none=True)
        kwargs = {**env_kwargs(dataclasses.asdict(base) if base else {}), **env_kwargs(dataclasses.asdict(self))}
        if "grid" not in kwargs:
            raise ValueError(f"{name}.grid must name a map, got None.")
        try:
            GridWorldEnv(**kwargs, batch_size=[1], seed=0).close()
        except (ValueError, TypeError, KeyError) as err:
            raise ValueError(f"{name}: {err}") from None


@dataclass
class DemosSection:
    """``demos``: ``num`` value-iteration demonstrations of ``length`` steps, on the ``env`` with ``env``'s keys
    changed."""

    num: Optional[int] = None
    length: Optional[int] = None
    env: Optional[EnvSection] = None

    def check(self, name: str, env: EnvSection) -> None:
        check_int(self.num, f"{name}.num", minimum=1)
        check_int(self.length, f"{name}.length", minimum=1)
        if self.env is not None:
            self.env.check(f"{name}.env", base=env)


@dataclass
class DiscoveryFields:
    """The DDO settings of a ``discovery`` section (and of its ``paper:`` sub-section): ``preset`` (one of
    :data:`DISCOVERY_PRESETS`) gives what is left at ``None`` (:func:`discovery_kwargs`); ``num_iterations``
    (:func:`discovery_iterations`), ``upper_level_iterations`` (a hierarchy's upper levels; ``None``: as the
    lowest). The others are :func:`~torchrl_options.discover_options`'s arguments of the same names
    (``usage_floor``: one-level discovery only, so conditions with ``levels`` above 1 refuse it)."""

    num_options: Optional[int] = None
    preset: Optional[str] = None
    num_iterations: Optional[int] = None
    upper_level_iterations: Optional[int] = None
    num_cells: Any = None
    termination_cells: Any = None
    activation: Optional[str] = None
    init: Optional[str] = None
    batch_size: Optional[int] = None
    lr: Optional[float] = None
    m_steps: Optional[int] = None
    restarts: Optional[int] = None
    tol: Optional[float] = None
    usage_floor: Optional[float] = None

    def check(self, name: str) -> None:
        """The settings as :class:`~torchrl_options.discovery.DiscoverySettings` (the library's checks and
        choices) and the options network they describe (its width and activation)."""
        check_choice(self.preset or "paper", f"{name}.preset", DISCOVERY_PRESETS)
        check_int(self.num_options, f"{name}.num_options", minimum=1)
        check_int(self.upper_level_iterations, f"{name}.upper_level_iterations", minimum=0, allow_none=True)
        if self.lr is not None:
            check_positive_number(self.lr, f"{name}.lr")
        check_usage_floor(self.usage_floor, f"{name}.usage_floor")
        settings = dataclasses.asdict(self)
        kwargs = discovery_kwargs(settings)
        try:
            DiscoverySettings(self.num_options, num_iterations=discovery_iterations(settings), **kwargs)
            if kwargs.get("num_cells", 8) != "auto":
                OptionsMLP(
                    2, 4, self.num_options, num_cells=kwargs.get("num_cells", 8),
                    termination_cells=kwargs.get("termination_cells"), activation=kwargs.get("activation", "tanh"),
                )  # fmt: skip
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name}.{err}") from None


@dataclass
class DiscoverySection(DiscoveryFields):
    """``discovery``: :class:`DiscoveryFields`, and the paper's where they differ (``paper``, merged in by
    ``protocol=paper``)."""

    paper: Optional[DiscoveryFields] = None


@dataclass
class GreedySection:
    """A ``greedy`` setting's rollouts of the pre-trained agent: ``num`` of ``length`` steps, with ``epsilon`` (a
    number in [0, 1], or ``"agent"``: the agent's own final rate), ``keep``: ``"all"`` or ``"rewarded"``."""

    num: Optional[int] = None
    length: Optional[int] = None
    epsilon: Any = None
    keep: Optional[str] = None

    def check(self, name: str) -> None:
        check_int(self.num, f"{name}.num", minimum=1)
        check_int(self.length, f"{name}.length", minimum=1)
        if self.epsilon != "agent":
            try:
                check_number(self.epsilon, f"{name}.epsilon", lo=0.0, hi=1.0, allow_none=True)
            except (TypeError, ValueError):
                what = "'agent' or a number in [0, 1]"
                raise ValueError(f"{name}.epsilon must be {what}, got {self.epsilon!r}.") from None
        check_choice(self.keep or "all", f"{name}.keep", ("all", "rewarded"))


@dataclass
class SettingFields:
    """A setting: ``source`` ``"supervisor"`` (value-iteration demonstrations) or ``"greedy"`` (rollouts of an
    agent pre-trained with actions only for ``pretrain_episodes``, per ``greedy``)."""

    source: Optional[str] = None
    pretrain_episodes: Optional[int] = None
    greedy: Optional[GreedySection] = None

    def check(self, name: str, algorithm: str) -> None:
        check_choice(self.source, f"{name}.source", ("supervisor", "greedy"))
        if self.source == "greedy":
            if algorithm == "ppo":
                raise ValueError(f"{name} pre-trains a DQN agent (source: greedy); algorithm=ppo runs supervised "
                                 "settings only.")  # fmt: skip
            check_int(self.pretrain_episodes, f"{name}.pretrain_episodes", minimum=1)
            if self.greedy is None:
                raise ValueError(f"{name}.greedy must be a section (num, length, epsilon, keep), got None.")
            self.greedy.check(f"{name}.greedy")


@dataclass
class SettingSection(SettingFields):
    """A ``settings`` entry: :class:`SettingFields`, and the paper's (``paper``, merged in by ``protocol=paper``)."""

    paper: Optional[SettingFields] = None


@dataclass
class ConditionSection:
    """A ``conditions`` entry: ``mode`` (``"actions"``, ``"options"``, ``"both"``), ``meta_control`` of the
    discovery (``None``: ``"uniform"``), ``num_options`` and ``levels`` (``None``: ``discovery.num_options``, one
    level), ``episodes`` (``None``: the recipe's)."""

    mode: Optional[str] = None
    meta_control: Optional[str] = None
    num_options: Optional[int] = None
    levels: Optional[int] = None
    episodes: Optional[int] = None

    def check(self, name: str) -> None:
        check_choice(self.mode, f"{name}.mode", ("actions", "options", "both"))
        check_choice(self.meta_control or "uniform", f"{name}.meta_control", ("uniform", "learned"))
        for key in ("num_options", "levels", "episodes"):
            check_int(getattr(self, key), f"{name}.{key}", minimum=1, allow_none=True)


@dataclass
class LoggerSection:
    """``logger``: a TorchRL logger per cell (``backend``: ``csv``, ``tensorboard``, ``wandb``, ``mlflow``, or
    ``""`` for none)."""

    backend: Optional[str] = None
    exp_name: Optional[str] = None
    project_name: Optional[str] = None
    offline: Optional[bool] = None


@dataclass
class PicturesSection:
    """``pictures``: the option pictures and videos of the first seed."""

    num_starts: Optional[int] = None
    max_length: Optional[int] = None
    target: Optional[List[int]] = None
    video: Optional[bool] = None


@dataclass
class SummarySection:
    """``summary``: the windows of the summary table and curves, and an optional episodes-to-a-return table."""

    final_window: Optional[int] = None
    smooth_window: Optional[int] = None
    curve_window: Optional[int] = None
    reach_return: Optional[float] = None
    reach_window: Optional[int] = None


@dataclass
class RecipeScale:
    """One recipe's entry of a ``scale`` (``recipes/config/scale/*.yaml``), which the recipe's YAML interpolates."""

    conditions: Optional[List[str]] = None
    seeds: Any = None
    episodes: Optional[int] = None
    settings: Optional[List[str]] = None
    demos: Optional[int] = None
    backend: Optional[str] = None
    ddo_iterations: Optional[int] = None
    ddo_max_iterations: Optional[int] = None
    rollouts: Optional[int] = None
    greedy_trajectories: Optional[int] = None
    pretrain_episodes: Optional[int] = None


@dataclass
class ScaleSection:
    """``scale``: a named budget for every GridWorld recipe."""

    name: str = MISSING
    four_rooms: RecipeScale = field(default_factory=RecipeScale)
    four_rooms_ppo: RecipeScale = field(default_factory=RecipeScale)
    two_rooms: RecipeScale = field(default_factory=RecipeScale)
    three_rooms: RecipeScale = field(default_factory=RecipeScale)


# ------------------------------------------------------------------------------------------------- schema
@dataclass
class GridWorldRecipeConfig:
    """The schema of a GridWorld recipe: every key of ``recipes/config/four_rooms.yaml`` (which explains each one)
    and its siblings. ``algorithm``: ``None``/``"dqn"`` (the ``dqn`` section) or ``"ppo"`` (the ``ppo`` section);
    ``protocol``: one of :data:`PROTOCOLS` (``None``: ``"ours"``); ``log_file``: the log's name in ``out_dir``
    (``None``: ``recipe.log``)."""

    scale: ScaleSection = field(default_factory=ScaleSection)
    algorithm: Optional[str] = None
    out_dir: str = MISSING
    seeds: Any = MISSING
    episodes: int = MISSING
    settings_to_run: List[str] = MISSING
    conditions_to_run: List[str] = MISSING
    env: EnvSection = field(default_factory=EnvSection)
    num_envs: int = MISSING
    demos: Optional[DemosSection] = None
    protocol: Optional[str] = None
    discovery: DiscoverySection = field(default_factory=DiscoverySection)
    dqn: Optional[DQNSection] = None  # type: ignore[valid-type]
    ppo: Optional[PPOSection] = None  # type: ignore[valid-type]
    # name -> SettingSection / ConditionSection: typed when checked, so that the command line can add one
    # (``+conditions.H1x={mode: both}``), which OmegaConf refuses into a dict of dataclasses
    settings: Dict[str, Any] = field(default_factory=dict)
    conditions: Dict[str, Any] = field(default_factory=dict)
    checkpoint_every: int = 100
    backend: str = "serial"
    num_workers: Optional[int] = None
    ray_address: Optional[str] = None
    stop_after_cells: Optional[int] = None
    allow_changed_settings: bool = False
    progress: bool = True
    verbose: bool = False
    logger: LoggerSection = field(default_factory=LoggerSection)
    pictures: PicturesSection = field(default_factory=PicturesSection)
    summary: SummarySection = field(default_factory=SummarySection)
    log_file: Optional[str] = None

    def check(self, agent: Mapping[str, Any] | None = None) -> None:
        """Refuses, naming it, the first setting out of range (after ``protocol`` was applied); ``agent``: the keys
        set in the ``dqn`` (or ``ppo``) section (the dataclass holds them as not set, ``???``)."""
        check_int(self.episodes, "episodes", minimum=1)
        check_seeds(self.seeds)
        check_int(self.num_envs, "num_envs", minimum=1)
        check_int(self.checkpoint_every, "checkpoint_every", minimum=1)
        check_int(self.stop_after_cells, "stop_after_cells", minimum=0, allow_none=True)
        check_sweep(self.backend, self.num_workers)
        for name in ("allow_changed_settings", "progress", "verbose"):
            check_bool(getattr(self, name), name)
        if not self.out_dir:
            raise ValueError(f"out_dir must be a folder name, got {self.out_dir!r}.")
        if self.log_file is not None and (not self.log_file or "/" in self.log_file or "\\" in self.log_file):
            raise ValueError(f"log_file must be a file name (written in out_dir), got {self.log_file!r}.")
        algorithm = self.algorithm or "dqn"
        check_choice(algorithm, "algorithm", ("dqn", "ppo"))
        self._check_names("settings_to_run", self.settings_to_run, self.settings, "settings")
        self._check_names("conditions_to_run", self.conditions_to_run, self.conditions, "conditions")
        for name in self.settings_to_run:
            _entry(SettingSection, self.settings[name], f"settings.{name}").check(f"settings.{name}", algorithm)
        for name in self.conditions_to_run:
            condition = _entry(ConditionSection, self.conditions[name], f"conditions.{name}")
            condition.check(f"conditions.{name}")
            if (condition.levels or 1) > 1 and self.discovery.usage_floor is not None:
                raise ValueError(
                    f"discovery.usage_floor={self.discovery.usage_floor} applies to one-level discovery, but condition "
                    f"{name!r} discovers {condition.levels} levels; leave it out of conditions_to_run or set "
                    "discovery.usage_floor=null."
                )
        self.discovery.check("discovery")
        self.env.check("env")
        if self.demos is not None:
            self.demos.check("demos", self.env)
        for section in ("final_window", "smooth_window", "curve_window", "reach_window"):
            check_int(getattr(self.summary, section), f"summary.{section}", minimum=1, allow_none=True)
        for section in ("num_starts", "max_length"):
            check_int(getattr(self.pictures, section), f"pictures.{section}", minimum=1, allow_none=True)
        self._check_agent(algorithm, agent)

    @staticmethod
    def _check_names(key: str, names: list[str], known: Mapping[str, Any], what: str) -> None:
        if not names:
            raise ValueError(f"{key} must be a non-empty list of {what}, got {list(names)!r}.")
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"{key}: unknown {what} {unknown}; defined: {sorted(known)}.")

    def _check_agent(self, algorithm: str, section: Mapping[str, Any] | None) -> None:
        """The ``dqn`` (or ``ppo``) section, as the agent's config; a collector batch of whole steps of the envs."""
        if section is None:
            raise ValueError(f"{algorithm} must be a section of the agent's settings, got None.")
        config_cls = OptionsPPOConfig if algorithm == "ppo" else OptionsDQNConfig
        config = _agent_config(config_cls, section, algorithm)
        if config.frames_per_batch % self.num_envs:
            raise ValueError(
                f"{algorithm}.frames_per_batch must be a multiple of num_envs ({self.num_envs}), got "
                f"{config.frames_per_batch}: a batch holds whole steps of every env."
            )


def gridworld_settings(cfg: Any) -> dict[str, Any]:
    """The checked settings of a GridWorld recipe, as the run reads them: ``cfg`` (the composed Hydra config, or a
    plain mapping of the same keys) through :class:`GridWorldRecipeConfig` (unknown keys and wrong types refused,
    naming the key), ``protocol`` applied (:func:`apply_protocol`), every value checked
    (:meth:`GridWorldRecipeConfig.check`), as plain dicts without the keys not set (``None``, or ``???`` in the
    ``dqn``/``ppo`` sections, where ``None`` is a value).

    Raises:
        ValueError: naming the first bad setting, e.g. ``episodes must be an int >= 1, got -5.``
        omegaconf.errors.OmegaConfBaseException: an unknown key or a wrong type (with the key as ``full_key``).

    Examples:
        >>> from hydra import compose, initialize_config_dir
        >>> from pathlib import Path
        >>> import torchrl_options
        >>> config_dir = Path(torchrl_options.__file__).parents[1] / "recipes" / "config"
        >>> with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        ...     cfg = compose("four_rooms", overrides=["scale=tiny", "protocol=paper"])
        >>> settings = gridworld_settings(cfg)
        >>> settings["discovery"]["preset"], settings["settings"]["exploration"]["greedy"]["keep"]
        ('paper', 'all')
        >>> gridworld_settings({**settings, "episodes": -5})
        Traceback (most recent call last):
        ...
        ValueError: episodes must be an int >= 1, got -5.
    """
    from omegaconf import OmegaConf

    plain = apply_protocol(plain_settings(structured_settings(GridWorldRecipeConfig, cfg), keep_none=AGENT_SECTIONS))
    rest = {k: v for k, v in plain.items() if k not in AGENT_SECTIONS}  # the agent's keys: checked as its config
    agent = plain.get(plain.get("algorithm") or "dqn")
    OmegaConf.to_object(structured_settings(GridWorldRecipeConfig, rest)).check(agent)
    return plain


def store_gridworld_config(name: str = "gridworld_schema") -> None:
    """Registers :class:`GridWorldRecipeConfig` in Hydra's ``ConfigStore`` as ``name``: the schema that the
    GridWorld recipes' YAML files name first in their ``defaults``. Importing this module registers it when
    ``hydra-core`` is installed.

    Examples:
        >>> from hydra.core.config_store import ConfigStore
        >>> store_gridworld_config()
        >>> ConfigStore.instance().load("gridworld_schema.yaml").node.checkpoint_every
        100
    """
    if not isinstance(name, str) or not name:
        raise TypeError(f"store_gridworld_config: name must be a non-empty str, got {name!r}.")
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=name, node=GridWorldRecipeConfig)


try:  # the recipes' YAML names the schema: registered on import, for the recipes and for compose() in tests
    store_gridworld_config()
except ImportError:  # pragma: no cover - hydra-core is the `recipes` extra
    pass
