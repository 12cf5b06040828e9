"""Saving and loading discovered options: weights plus the configuration needed to rebuild them."""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase

from torchrl_options.checkpoints import load_file, save_file
from torchrl_options.modules import GaussianOptionsMLP, MetaControlMLP, OneHotByteOptions, OptionsMLP, UniformMetaControl

__all__ = [
    "save_options",
    "load_options",
    "module_to_dict",
    "module_from_dict",
    "check_metadata",
    "describe_payload",
    "write_payload",
]

_FORMAT = "torchrl_options/options-v1"
_CLASSES: dict[str, type] = {
    cls.__name__: cls for cls in (OptionsMLP, GaussianOptionsMLP, OneHotByteOptions, MetaControlMLP, UniformMetaControl)
}


def _keys_from_config(value: Any) -> Any:
    # nested keys are stored as lists (tuples are not plain data); turn them back into tuples
    if isinstance(value, list):
        return [tuple(v) if isinstance(v, list) else v for v in value]
    return value


def module_to_dict(module: TensorDictModuleBase) -> dict:
    """The class name, configuration and weights of one of this package's modules, as plain data.

    Raises:
        ValueError: for a module that does not carry a ``config`` (a hand-written module): save it with
            ``torch.save`` instead.
    """
    name = type(module).__name__
    if _CLASSES.get(name) is not type(module) or not isinstance(getattr(module, "config", None), dict):
        article = "an" if name[:1].lower() in "aeiou" else "a"
        raise ValueError(
            f"cannot save {article} {name} by configuration: only {sorted(_CLASSES)} can be rebuilt from a file. Save "
            "a hand-written module with torch.save(module.state_dict(), ...) and rebuild it in code."
        )
    return {"class": name, "config": dict(module.config), "state_dict": {k: v.detach().cpu() for k, v in module.state_dict().items()}}


def module_from_dict(entry: dict, source: str = "the file") -> TensorDictModuleBase:
    """Rebuilds a module saved by :func:`module_to_dict`.

    Raises:
        ValueError: naming ``source``, if the entry is not one of this package's modules, its configuration does
            not build one, or its weights do not fit the configuration.
    """
    if not isinstance(entry, dict) or not {"class", "config", "state_dict"} <= set(entry):
        raise ValueError(f"{source}: a module entry must hold 'class', 'config' and 'state_dict', got {_describe(entry)}.")
    cls = _CLASSES.get(entry.get("class"))
    if cls is None:
        raise ValueError(f"{source}: unknown module class {entry.get('class')!r}; expected one of {sorted(_CLASSES)}.")
    if not isinstance(entry["config"], dict) or not isinstance(entry["state_dict"], dict):
        raise ValueError(f"{source}: the {cls.__name__} entry's 'config' and 'state_dict' must be dicts.")
    config = dict(entry["config"])
    for key in ("in_keys", "out_keys"):
        if key in config:
            config[key] = _keys_from_config(config[key])
    if isinstance(config.get("out_key"), list):
        config["out_key"] = tuple(config["out_key"])
    try:
        module = _build(cls, config)
    except (TypeError, ValueError, KeyError, RuntimeError) as err:
        raise ValueError(f"{source}: the stored {cls.__name__} configuration does not build one: {err}") from None
    try:
        module.load_state_dict(entry["state_dict"])
    except (RuntimeError, ValueError, KeyError) as err:
        detail = " ".join(str(err).split())[:300]
        raise ValueError(
            f"{source}: the stored {cls.__name__} weights disagree with its stored configuration {config}: {detail}"
        ) from None
    return module


def _build(cls: type, config: dict) -> TensorDictModuleBase:
    if cls is OptionsMLP:
        return cls(config.pop("in_features"), config.pop("num_actions"), config.pop("num_options"), **config)
    if cls is OneHotByteOptions:
        return cls(config.pop("num_bytes"), config.pop("num_actions"), config.pop("num_options"), **config)
    if cls is GaussianOptionsMLP:
        return cls(config.pop("in_features"), config.pop("action_dim"), config.pop("num_options"), **config)
    if cls is MetaControlMLP:
        return cls(config.pop("in_features"), config.pop("num_options"), **config)
    return cls(config.pop("num_options"), **config)


def describe_payload(value: Any) -> str:
    """A short description of what a file held, for the error messages of the loaders."""
    if isinstance(value, dict):
        fmt = value.get("format")
        if isinstance(fmt, str):
            return f"a file of format {fmt!r}"
        return f"a dict with keys {sorted(map(str, value))[:12]}"
    return type(value).__name__


_describe = describe_payload


def check_metadata(metadata: Any) -> dict:
    """``metadata`` as a dict of plain data (what a file read without pickle can hold); ``None`` is ``{}``.

    Raises:
        TypeError: not a mapping, or an entry that is not plain data (numbers, strings, ``None``, lists, tuples,
            dicts with string keys, tensors).
    """
    if metadata is None:
        return {}
    if not isinstance(metadata, Mapping):
        raise TypeError(f"metadata must be None or a dict of plain data, got {type(metadata).__name__}.")
    _check_plain(metadata, "metadata")
    return dict(metadata)


def _check_plain(value: Any, name: str) -> None:
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_plain(v, f"{name}[{i}]")
        return
    if isinstance(value, Mapping):
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{name} has a key {k!r} ({type(k).__name__}); only string keys are plain data.")
            _check_plain(v, f"{name}[{k!r}]")
        return
    raise TypeError(
        f"{name} is {type(value).__name__}: only plain data (numbers, strings, None, lists, dicts, tensors) can be "
        "saved and read back without pickle."
    )


def write_payload(payload: dict, path: str | os.PathLike, what: str) -> None:
    """Writes a file's plain-data ``payload`` to ``path`` atomically (a killed run leaves the old file or none,
    never half a file), refusing a directory or a missing folder with an error naming the path."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{os.fspath(target)}: expected a file name for the {what} file, got a directory.")
    if not target.parent.is_dir():
        raise ValueError(f"{os.fspath(target)}: cannot write the {what} file: the folder {os.fspath(target.parent)} does not exist.")
    save_file(payload, target)


def save_options(
    options: TensorDictModuleBase,
    path: str | os.PathLike,
    *,
    meta_control: TensorDictModuleBase | None = None,
    metadata: dict | None = None,
) -> None:
    """Saves discovered options (and optionally their meta-control) to ``path``.

    The file holds plain data (class names, configurations, tensors) and loads with ``weights_only=True``; it is
    written atomically (a run killed while saving leaves the old file or none, never half a file).

    Args:
        options (TensorDictModuleBase): an :class:`~torchrl_options.OptionsMLP`,
            :class:`~torchrl_options.GaussianOptionsMLP` or :class:`~torchrl_options.modules.OneHotByteOptions`.
        path (str or PathLike): the file to write.

    Keyword Args:
        meta_control (TensorDictModuleBase, optional): saved next to the options.
        metadata (dict, optional): plain data to keep with them (e.g. the discovery settings).

    Examples:
        >>> import tempfile, os, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP, save_options, load_options
        >>> options = OptionsMLP(4, 3, 2)
        >>> path = os.path.join(tempfile.mkdtemp(), "options.pt")
        >>> save_options(options, path)
        >>> loaded = load_options(path)
        >>> td = TensorDict({"observation": torch.randn(2, 4)}, [2])
        >>> torch.equal(options(td.clone())["option_logits"], loaded(td.clone())["option_logits"])
        True
    """
    if not isinstance(options, TensorDictModuleBase):
        raise TypeError(f"save_options: options must be an options module (TensorDictModuleBase), got {type(options).__name__}.")
    if meta_control is not None and not isinstance(meta_control, TensorDictModuleBase):
        raise TypeError(f"save_options: meta_control must be None or a TensorDictModuleBase, got {type(meta_control).__name__}.")
    payload = {"format": _FORMAT, "options": module_to_dict(options), "metadata": check_metadata(metadata)}
    if meta_control is not None:
        payload["meta_control"] = module_to_dict(meta_control)
    write_payload(payload, path, "options")


def load_options(path: str | os.PathLike, *, with_meta_control: bool = False, map_location=None):
    """Loads options saved by :func:`save_options`.

    Args:
        path (str or PathLike): the file.

    Keyword Args:
        with_meta_control (bool): also return the meta-control module (``None`` if none was saved) and the
            metadata, as ``(options, meta_control, metadata)``.
        map_location: passed to :func:`torch.load`.

    Raises:
        ValueError: naming the file, if it is missing (also a ``FileNotFoundError``), empty, truncated or
            corrupt, needs pickle, is not an options file of this package, or its stored configuration disagrees
            with its weights. Nothing in the file is unpickled: it loads with ``weights_only=True``.

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import MetaControlMLP, OptionsMLP, save_options
        >>> path = os.path.join(tempfile.mkdtemp(), "options.pt")
        >>> save_options(OptionsMLP(4, 3, 2), path, meta_control=MetaControlMLP(4, 2), metadata={"K": 2})
        >>> options, meta, metadata = load_options(path, with_meta_control=True)
        >>> type(meta).__name__, metadata
        ('MetaControlMLP', {'K': 2})
    """
    payload = load_file(path, what="options", map_location=map_location)
    source = os.fspath(path)
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(
            f"{source}: not an options file written by torchrl_options.save_options (expected format {_FORMAT!r}, "
            f"got {_describe(payload)})."
        )
    if "options" not in payload:
        raise ValueError(f"{source}: the options file has no 'options' entry.")
    options = module_from_dict(payload["options"], source)
    if not with_meta_control:
        return options
    meta = payload.get("meta_control")
    return options, (module_from_dict(meta, source) if meta is not None else None), payload.get("metadata", {})
