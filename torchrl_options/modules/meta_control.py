"""Meta-control policies ``eta(h | s)``: which option to start when the previous one terminates.

DDO (Fox et al., 2017, section 4.3) discovers options either with a fixed uniform meta-control (H1u, H2u),
which decouples a level from the levels above it, or with a learned one (H1s, H2s). Both write
``"meta_logits"`` ``[..., K]``; ``eta = softmax(meta_logits)``.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.modules import MLP

from torchrl_options.modules._features import (
    activation_class,
    as_key_list,
    check_module_keys,
    check_sizes,
    hidden_sizes,
    key_to_config,
    ObservationModule,
)

__all__ = ["MetaControlMLP", "UniformMetaControl"]


class MetaControlMLP(ObservationModule):
    """A learned meta-control policy: an MLP from the observation to ``meta_logits`` ``[..., K]``.

    Args:
        in_features (int): size of the concatenated observation features.
        num_options (int): K.

    Keyword Args:
        num_cells (int or sequence of int): hidden sizes. Defaults to ``2`` (the paper's four-rooms networks).
        activation (str): defaults to ``"tanh"``.
        in_keys (NestedKey or list): defaults to ``"observation"``.
        out_key (NestedKey): defaults to ``"meta_logits"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import MetaControlMLP
        >>> eta = MetaControlMLP(in_features=4, num_options=3)
        >>> eta(TensorDict({"observation": torch.randn(5, 4)}, [5]))["meta_logits"].shape
        torch.Size([5, 3])
    """

    def __init__(
        self,
        in_features: int,
        num_options: int,
        *,
        num_cells: int | Sequence[int] = 2,
        activation: str = "tanh",
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_key: NestedKey = "meta_logits",
    ) -> None:
        super().__init__()
        check_sizes(in_features=in_features, num_options=num_options)
        self.in_keys = as_key_list(in_keys, "in_keys")
        self.out_keys = as_key_list([out_key], "out_key")
        check_module_keys("MetaControlMLP", self.in_keys, self.out_keys)
        self.num_options = num_options
        cells = hidden_sizes(num_cells)
        self.config = dict(
            in_features=in_features,
            num_options=num_options,
            num_cells=cells,
            activation=activation,
            in_keys=[key_to_config(k) for k in self.in_keys],
            out_key=key_to_config(out_key),
        )
        self.net = MLP(
            in_features=in_features, out_features=num_options, num_cells=cells, activation_class=activation_class(activation)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.net(self.features(tensordict)))
        return tensordict


class UniformMetaControl(ObservationModule):
    """The fixed uniform meta-control ``eta(h | s) = 1 / K`` (no parameters): zeros as ``meta_logits``.

    Args:
        num_options (int): K.

    Keyword Args:
        in_keys (NestedKey or list): a key whose leading dimensions give the batch shape (its last dimension is
            the feature dimension). Defaults to ``"observation"``.
        out_key (NestedKey): defaults to ``"meta_logits"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import UniformMetaControl
        >>> UniformMetaControl(3)(TensorDict({"observation": torch.randn(2, 4)}, [2]))["meta_logits"]
        tensor([[0., 0., 0.],
                [0., 0., 0.]])
    """

    def __init__(
        self,
        num_options: int,
        *,
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_key: NestedKey = "meta_logits",
    ) -> None:
        super().__init__()
        check_sizes(num_options=num_options)
        self.in_keys = as_key_list(in_keys, "in_keys")[:1]
        self.out_keys = as_key_list([out_key], "out_key")
        check_module_keys("UniformMetaControl", self.in_keys, self.out_keys)
        self.num_options = num_options
        self.config = dict(
            num_options=num_options,
            in_keys=[key_to_config(k) for k in self.in_keys],
            out_key=key_to_config(out_key),
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = tensordict.get(self.in_keys[0])
        dtype = x.dtype if x.is_floating_point() else torch.get_default_dtype()
        tensordict.set(self.out_keys[0], torch.zeros(*x.shape[:-1], self.num_options, dtype=dtype, device=x.device))
        return tensordict
