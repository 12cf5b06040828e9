"""What the recipes' Hydra schemas share: a settings section derived from an agent's config dataclass (its keys and
types come from the library, not a copy), the seeds and sweep checks, and a composed config as plain settings.

A recipe's YAML names its schema (a dataclass registered in Hydra's ``ConfigStore``) in its ``defaults``: Hydra
then refuses an unknown key or a value of the wrong type while composing, naming the key
(``discovery.num_optons``, ``dqn.lr=abc``); the value checks a type cannot say (ranges, choices) are the schema's
``check`` methods, run before any work starts.
"""
from __future__ import annotations

import dataclasses
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, List, Literal, Optional

from torchrl_options.checks import check_choice, check_int

__all__ = [
    "BACKENDS",
    "MISSING",
    "agent_section",
    "check_seeds",
    "check_sweep",
    "plain_settings",
    "structured_settings",
]

#: the sweep backends of :func:`~torchrl_options.experiments.run_sweep`
BACKENDS = ("serial", "local", "ray")
#: OmegaConf's mark of a value not set (``omegaconf.MISSING``)
MISSING = "???"


def _schema_type(hint: Any) -> Any:
    """The OmegaConf type of a config field's annotation: ``X | None`` as ``X``, a ``Literal`` of strings as
    ``str``, a tuple or list of ints as ``List[int]``, anything else OmegaConf cannot type (a ``NestedKey``) as
    ``Any``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        return _schema_type(rest[0]) if len(rest) == 1 else Any
    if origin is Literal:
        return str if all(isinstance(a, str) for a in args) else Any
    if origin in (tuple, list) and args and args[0] is int:
        return List[int]
    return hint if hint in (bool, int, float, str) else Any


def agent_section(config_cls: type, name: str, exclude: tuple[str, ...]) -> type:
    """The schema of a recipe section that holds the fields of ``config_cls`` (an agent's config dataclass, e.g.
    :class:`~torchrl_options.agents.OptionsDQNConfig`) but ``exclude`` (those the recipe sets per cell): every key
    optional and not set (:data:`MISSING`: left out of :func:`plain_settings`, so ``config_cls``'s default
    applies), while a key set to ``None`` is passed on as ``None`` (``max_grad_norm: null``: no clipping). The
    section's values are checked by building ``config_cls`` from them.

    Examples:
        >>> from torchrl_options.agents import OptionsDQNConfig
        >>> DQN = agent_section(OptionsDQNConfig, "DQNSection", exclude=("mode", "num_envs", "seed"))
        >>> DQN().lr == MISSING, "mode" in {f.name for f in dataclasses.fields(DQN)}
        (True, False)
    """
    hints = typing.get_type_hints(config_cls)
    entries = [
        (f.name, Optional[_schema_type(hints[f.name])], dataclasses.field(default=MISSING))
        for f in dataclasses.fields(config_cls) if f.name not in exclude
    ]  # fmt: skip
    doc = f"The ``{name}`` section: the fields of :class:`{config_cls.__module__}.{config_cls.__name__}` but {exclude}."
    return dataclasses.make_dataclass(name, entries, namespace={"__doc__": doc})


def check_seeds(value: Any, name: str = "seeds") -> None:
    """A seed count ``>= 1`` or a non-empty list of distinct ints ``>= 0``.

    Examples:
        >>> check_seeds(3), check_seeds([0, 4])
        (None, None)
        >>> check_seeds([1, 1])
        Traceback (most recent call last):
        ...
        ValueError: seeds must not repeat a seed, got [1, 1].
    """
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        if value < 1:
            raise ValueError(f"{name} must be a count >= 1 or a list of ints >= 0, got {value!r}.")
        return
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)) or not value or not all(
        isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 0 for s in value
    ):
        raise ValueError(f"{name} must be a count >= 1 or a non-empty list of ints >= 0, got {value!r}.")
    if len(set(value)) != len(value):
        raise ValueError(f"{name} must not repeat a seed, got {list(value)}.")


def check_sweep(backend: Any, num_workers: Any, prefix: str = "") -> None:
    """A sweep's ``backend`` (one of :data:`BACKENDS`) and ``num_workers`` (an int ``>= 1`` or ``None``)."""
    check_choice(backend, f"{prefix}backend", BACKENDS)
    check_int(num_workers, f"{prefix}num_workers", minimum=1, allow_none=True)


def _drop_unset(value: Any, none: bool) -> Any:
    if isinstance(value, dict):
        return {k: _drop_unset(v, none) for k, v in value.items() if v != MISSING and not (none and v is None)}
    if isinstance(value, list):
        return [_drop_unset(v, none) for v in value]
    return value


def structured_settings(schema: type, cfg: Any) -> Any:
    """``cfg`` (a composed ``DictConfig`` or a plain mapping) merged into ``schema``'s structured config: an
    unknown key or a value of the wrong type raises, naming the key. A ``defaults`` list (a YAML read with
    ``OmegaConf.load`` rather than composed) and the ``hydra`` section are left out. Needs ``omegaconf``."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    if not isinstance(cfg, Mapping):
        raise TypeError(f"a recipe config must be a mapping (a DictConfig or a dict), got {type(cfg).__name__}.")
    cfg = {k: v for k, v in cfg.items() if k not in ("defaults", "hydra")}
    return OmegaConf.merge(OmegaConf.structured(schema), cfg)


def plain_settings(cfg: Any, keep_none: tuple[str, ...] = ()) -> dict[str, Any]:
    """A config as plain nested dicts and lists, interpolations resolved, the keys not set (:data:`MISSING`) and
    those set to ``None`` left out: the default of whatever reads the setting applies. In the top-level sections
    named in ``keep_none`` (an agent's settings, :func:`agent_section`) ``None`` is a value and stays.

    Examples:
        >>> plain_settings({"dqn": {"lr": 0.01, "max_grad_norm": None, "gamma": "???"}, "num_workers": None})
        {'dqn': {'lr': 0.01}}
        >>> plain_settings({"dqn": {"lr": 0.01, "max_grad_norm": None, "gamma": "???"}}, keep_none=("dqn",))
        {'dqn': {'lr': 0.01, 'max_grad_norm': None}}
    """
    if not isinstance(cfg, Mapping):
        raise TypeError(f"a recipe config must be a mapping, got {type(cfg).__name__}.")
    if type(cfg).__name__ == "DictConfig":
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(cfg, resolve=True)
    cfg = _to_plain(cfg)
    return {k: _drop_unset(v, none=k not in keep_none) for k, v in cfg.items() if v != MISSING and v is not None}


def _to_plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_plain(v) for v in value]
    return value
