"""Shared plumbing of the observation-reading modules: input concatenation, activations, configs."""
from __future__ import annotations

from collections.abc import Sequence
from numbers import Integral

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from torchrl_options.checks import check_distinct_keys, check_int, check_nested_key

_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
    "identity": nn.Identity,
}


def activation_class(name: str) -> type[nn.Module]:
    """Returns the activation class registered under ``name`` (``"tanh"``, ``"relu"``, ``"elu"``, ...)."""
    try:
        return _ACTIVATIONS[name.lower()]
    except KeyError:
        raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {name!r}.") from None


def as_key_list(keys: NestedKey | Sequence[NestedKey], name: str) -> list[NestedKey]:
    if isinstance(keys, (str, tuple)):
        keys = [keys]
    if not isinstance(keys, Sequence):
        raise TypeError(f"{name} must be a NestedKey or a list of them, got {type(keys).__name__}.")
    keys = list(keys)
    if not keys:
        raise ValueError(f"{name} must name at least one key.")
    return [check_nested_key(k, f"{name}[{i}]") for i, k in enumerate(keys)]


def check_module_keys(owner: str, in_keys: Sequence[NestedKey], out_keys: Sequence[NestedKey]) -> None:
    """Refuses two outputs on one entry, or an output written over an input (the module would overwrite what it
    reads)."""
    named = {f"out_keys[{i}]": k for i, k in enumerate(out_keys)}
    named.update({f"in_keys[{i}]": k for i, k in enumerate(in_keys)})
    check_distinct_keys(named, owner, allow_same=[(f"in_keys[{i}]", f"in_keys[{j}]") for i in range(len(in_keys))
                                                 for j in range(len(in_keys))])  # fmt: skip


def check_sizes(**sizes: int) -> None:
    """Each size a positive int (``TypeError`` for another type)."""
    for name, value in sizes.items():
        check_int(value, name)
        if value < 1:
            raise ValueError(f"{name} must be a positive int, got {value}.")


def key_to_config(key: NestedKey) -> str | list[str]:
    """A key as plain data for a module's ``config``: nested keys (tuples) become lists."""
    return list(key) if isinstance(key, tuple) else key


def hidden_sizes(num_cells: int | Sequence[int], name: str = "num_cells") -> list[int]:
    """Hidden layer sizes as a list of positive ints (``num_cells`` of the modules); ``name`` is the argument named
    in the error.

    Examples:
        >>> hidden_sizes(8), hidden_sizes((64, 64))
        ([8], [64, 64])
    """
    cells = [num_cells] if isinstance(num_cells, Integral) and not isinstance(num_cells, bool) else num_cells
    if isinstance(cells, (str, bytes)) or not isinstance(cells, Sequence):
        raise TypeError(f"{name} must be an int or a sequence of ints, got {num_cells!r}.")
    if not cells or any(isinstance(c, bool) or not isinstance(c, Integral) or c < 1 for c in cells):
        raise ValueError(f"{name} must be one positive int or a non-empty sequence of them, got {num_cells!r}.")
    return [int(c) for c in cells]


class ObservationModule(TensorDictModuleBase):
    """Base of the modules that read observation keys, concatenated along the last dimension.

    Subclasses record the constructor arguments in ``self.config`` (plain Python values only) so that
    :func:`~torchrl_options.save_options` can rebuild them.
    """

    config: dict

    def features(self, tensordict: TensorDictBase) -> torch.Tensor:
        xs = []
        for key in self.in_keys:
            x = tensordict.get(key, None)
            if x is None:
                raise KeyError(f"{type(self).__name__} reads {key!r}, which is missing from the input tensordict.")
            xs.append(x)
        dtype = self.param_dtype()
        xs = [x.to(dtype) for x in xs]
        x = torch.cat(xs, -1) if len(xs) > 1 else xs[0]
        expected = self.config.get("in_features")
        if expected is not None and x.shape[-1] != expected:
            raise ValueError(
                f"{type(self).__name__} was built for in_features={expected}, got {x.shape[-1]} features from "
                f"{self.in_keys} (shape {list(x.shape)})."
            )
        device = self.param_device()
        if device is not None and x.device != device:
            raise ValueError(
                f"{type(self).__name__}: the input {self.in_keys} is on device {x.device}, the module's parameters "
                f"on {device}; move one of them (module.to(device) or data.to(device))."
            )
        return x

    def param_dtype(self) -> torch.dtype:
        for p in self.parameters():
            return p.dtype
        return torch.get_default_dtype()

    def param_device(self) -> torch.device | None:
        for p in self.parameters():
            return p.device
        return None

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.config.items())
