"""K options over a vector of bytes (an Atari RAM, say), each byte one-hot encoded: the DDO paper's Atari networks.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.2, encode the 128 bytes of
an Atari RAM one-hot (128 x 256 inputs) for all policies; the authors' ``AtariRAMModel`` follows it with dense tanh
layers. A dense layer on the one-hot vector is a sum of one learned vector per byte position and value, an
``nn.Embedding(256, d)`` per position summed over the positions, so the 32768-dimensional vector is never built:
:class:`OneHotByteOptions` gathers those rows (one ``nn.EmbeddingBag`` for every network of every option).

Read as ``bytes / 255`` instead, a byte is one number on a line: ``0x80`` (a flag) lies next to ``0x7F``, and a
policy that depends on exact values (a counter, an object's kind) is far harder to fit. On the paper's games the
one-hot options fit their greedy demonstrator about as well as the demonstrator's own epsilon-greedy policy does;
``bytes / 255`` options do not (``docs/atari_experiments.md``, "Faithful protocol").
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from torchrl_options.checks import check_int, check_positive_number
from torchrl_options.modules._features import (
    activation_class,
    as_key_list,
    check_module_keys,
    hidden_sizes,
    key_to_config,
    ObservationModule,
)

__all__ = ["OneHotByteOptions", "bytes_from_observation"]

NUM_BYTE_VALUES = 256


def bytes_from_observation(x: torch.Tensor, *, value_scale: float = 1.0, name: NestedKey = "observation") -> torch.Tensor:
    """The byte values (``long``, in 0-255) of an observation holding ``bytes * value_scale``, checked.

    Args:
        x (torch.Tensor): integer or floating observation.

    Keyword Args:
        value_scale (float): what each byte was multiplied by (``1 / 255`` for an env that reads its RAM as
            ``bytes / 255``; ``1.0`` for raw bytes).
        name (NestedKey): the entry's name, for the error message.

    Raises:
        ValueError: naming ``name``, when a value is not a whole number in 0-255 once divided by ``value_scale``
            (a float observation that is not a byte vector, NaN, negative or above 255).

    Examples:
        >>> import torch
        >>> bytes_from_observation(torch.tensor([0.0, 0.2, 1.0]), value_scale=1 / 255)
        tensor([  0,  51, 255])
        >>> bytes_from_observation(torch.tensor([3, 300]))
        Traceback (most recent call last):
        ...
        ValueError: 'observation' must hold bytes (whole numbers 0-255 times value_scale=1.0), got 300.0 (as a byte: 300.0).
    """
    if not x.is_floating_point():
        b = x.long()
        bad = (b < 0) | (b >= NUM_BYTE_VALUES)
        if bool(bad.any()):
            first = float(x[bad].reshape(-1)[0])
            raise ValueError(
                f"{name!r} must hold bytes (whole numbers 0-255 times value_scale={value_scale}), got {first} "
                f"(as a byte: {first / value_scale})."
            )
        return b
    scaled = x.double() / value_scale
    rounded = scaled.round()
    bad = ~torch.isfinite(scaled) | ((scaled - rounded).abs() > 1e-3) | (rounded < 0) | (rounded >= NUM_BYTE_VALUES)
    if bool(bad.any()):
        first = float(x[bad].reshape(-1)[0])
        raise ValueError(
            f"{name!r} must hold bytes (whole numbers 0-255 times value_scale={value_scale}), got {first} "
            f"(as a byte: {first / value_scale})."
        )
    return rounded.long()


def _uniform_(t: torch.Tensor, fan_in: int) -> torch.Tensor:
    bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default initialisation
    return nn.init.uniform_(t, -bound, bound)


class _StackedLinear(nn.Module):
    """``n`` independent linear layers applied to ``[..., n, in]``: weights ``[n, out, in]``."""

    def __init__(self, n: int, in_features: int, out_features: int):
        super().__init__()
        self.weight = nn.Parameter(_uniform_(torch.empty(n, out_features, in_features), in_features))
        self.bias = nn.Parameter(_uniform_(torch.empty(n, out_features), in_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.matmul(x.unsqueeze(-2), self.weight.transpose(-1, -2)).squeeze(-2) + self.bias


class OneHotByteOptions(ObservationModule):
    """K discrete-action options over a byte-vector observation, each byte one-hot encoded (the paper's Atari RAM
    encoding), each option with its own control and termination network.

    Every network starts with a dense layer on the one-hot encoding of the ``num_bytes`` bytes (``num_bytes x 256``
    inputs), computed as a sum of embedding rows, then dense layers: ``num_cells`` gives the hidden widths, the
    first being the one-hot layer's (``[64, 64, 64]``: the one-hot layer to 64 units, two more dense layers of 64,
    each followed by ``activation``, then the output layer). The ``2K`` networks share one embedding table (their
    rows side by side), so a forward pass gathers each byte's row once.

    Writes what :class:`~torchrl_options.OptionsMLP` writes, so it runs wherever options run
    (:func:`~torchrl_options.discover_options` with ``options=``, :class:`~torchrl_options.OptionExecutor`,
    :func:`~torchrl_options.save_options`).

    Args:
        num_bytes (int): the observation's length (the concatenated ``in_keys``; 128 for an Atari RAM).
        num_actions (int): A.
        num_options (int): K.

    Keyword Args:
        num_cells (int or sequence of int): hidden widths, the first being the one-hot layer's. Defaults to
            ``[64, 64, 64]``.
        activation (str): defaults to ``"tanh"`` (the paper's).
        value_scale (float): the observation holds ``bytes * value_scale``: ``1.0`` (default) for raw bytes of any
            integer or float dtype, ``1 / 255`` for ``bytes / 255`` (what
            :func:`~torchrl_options.envs.atari.make_atari_ram_env` gives by default). Anything else (a value that is
            not a whole byte once divided by it) is refused with a ``ValueError`` naming the entry.
        in_keys (NestedKey or list): defaults to ``"observation"``.
        out_keys (list of two NestedKey): defaults to ``["option_logits", "termination_logits"]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.modules import OneHotByteOptions
        >>> options = OneHotByteOptions(4, num_actions=3, num_options=2, num_cells=[8])
        >>> ram = torch.tensor([[0, 255, 3, 7]], dtype=torch.uint8)
        >>> td = options(TensorDict(observation=ram, batch_size=[1]))
        >>> td["option_logits"].shape, td["termination_logits"].shape
        (torch.Size([1, 2, 3]), torch.Size([1, 2]))

        The first layer is a dense layer on the one-hot vector (here option 0's control network):

        >>> one_hot = torch.nn.functional.one_hot(ram.long(), 256).flatten(-2).float()  # [1, 4 * 256]
        >>> w = options.embedding.weight[:, :8]  # option 0's control rows, [4 * 256, 8]
        >>> torch.allclose(options.first_layer(ram)[:, 0], one_hot @ w + options.first_bias[0])
        True

        Reading ``bytes / 255`` with ``value_scale=1 / 255`` gives the same outputs; other values are refused:

        >>> scaled = OneHotByteOptions(4, 3, 2, num_cells=[8], value_scale=1 / 255)
        >>> _ = scaled.load_state_dict(options.state_dict())
        >>> td2 = scaled(TensorDict(observation=ram.float() / 255, batch_size=[1]))
        >>> torch.allclose(td2["option_logits"], td["option_logits"])
        True
        >>> scaled(TensorDict(observation=torch.full((1, 4), 0.5), batch_size=[1]))
        Traceback (most recent call last):
        ...
        ValueError: 'observation' must hold bytes (whole numbers 0-255 times value_scale=0.00392156862745098), got 0.5 (as a byte: 127.5).
    """

    def __init__(
        self,
        num_bytes: int,
        num_actions: int,
        num_options: int,
        *,
        num_cells: int | Sequence[int] = (64, 64, 64),
        activation: str = "tanh",
        value_scale: float = 1.0,
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        for name, value in (("num_bytes", num_bytes), ("num_actions", num_actions), ("num_options", num_options)):
            check_int(value, name, minimum=1)
        check_positive_number(value_scale, "value_scale")  # 1.0 for raw bytes, 1/255 for bytes / 255
        cells = hidden_sizes(num_cells)
        if out_keys is None:
            out_keys = ["option_logits", "termination_logits"]
        out_keys = as_key_list(out_keys, "out_keys")
        if len(out_keys) != 2:
            raise ValueError(f"out_keys must name two entries (option logits, termination logits), got {out_keys}.")
        self.in_keys = as_key_list(in_keys, "in_keys")
        self.out_keys = out_keys
        check_module_keys("OneHotByteOptions", self.in_keys, self.out_keys)
        self.num_bytes, self.num_actions, self.num_options = num_bytes, num_actions, num_options
        self.value_scale = float(value_scale)
        self.config = dict(
            num_bytes=num_bytes,
            num_actions=num_actions,
            num_options=num_options,
            num_cells=cells,
            activation=activation,
            value_scale=float(value_scale),
            in_keys=[key_to_config(k) for k in self.in_keys],
            out_keys=[key_to_config(k) for k in self.out_keys],
        )
        K, width = num_options, cells[0]
        # rows [position * 256 + value]; columns: 2K networks (K control, then K termination) of `width` units
        self.embedding = nn.EmbeddingBag(num_bytes * NUM_BYTE_VALUES, 2 * K * width, mode="sum")
        _uniform_(self.embedding.weight, num_bytes)  # a dense layer's initialisation for a num_bytes-hot input
        self.first_bias = nn.Parameter(torch.zeros(2 * K, width))
        self.register_buffer("offsets", torch.arange(num_bytes) * NUM_BYTE_VALUES, persistent=False)
        self.activation = activation_class(activation)()
        self.control = nn.ModuleList(_StackedLinear(K, a, b) for a, b in zip(cells[:-1], cells[1:]))
        self.control.append(_StackedLinear(K, cells[-1], num_actions))
        self.termination = nn.ModuleList(_StackedLinear(K, a, b) for a, b in zip(cells[:-1], cells[1:]))
        self.termination.append(_StackedLinear(K, cells[-1], 1))

    def read_bytes(self, tensordict_or_tensor: TensorDictBase | torch.Tensor) -> torch.Tensor:
        """The observation's bytes, ``long`` ``[..., num_bytes]``, checked (see :func:`bytes_from_observation`)."""
        if isinstance(tensordict_or_tensor, torch.Tensor):
            xs = [(self.in_keys[0], tensordict_or_tensor)]
        else:
            xs = []
            for key in self.in_keys:
                x = tensordict_or_tensor.get(key, None)
                if x is None:
                    raise KeyError(f"{type(self).__name__} reads {key!r}, which is missing from the input tensordict.")
                xs.append((key, x))
        parts = [bytes_from_observation(x, value_scale=self.value_scale, name=key) for key, x in xs]
        b = torch.cat(parts, -1) if len(parts) > 1 else parts[0]
        if b.shape[-1] != self.num_bytes:
            raise ValueError(
                f"{type(self).__name__} was built for {self.num_bytes} bytes, got an observation of {b.shape[-1]} "
                f"(entries {self.in_keys})."
            )
        return b

    def first_layer(self, tensordict_or_tensor: TensorDictBase | torch.Tensor) -> torch.Tensor:
        """The one-hot layer of the ``2K`` networks before its activation: ``[..., 2K, num_cells[0]]`` (control
        networks first)."""
        b = self.read_bytes(tensordict_or_tensor)
        batch = b.shape[:-1]
        out = self.embedding((b.reshape(-1, self.num_bytes) + self.offsets))
        return out.reshape(*batch, *self.first_bias.shape) + self.first_bias

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        h = self.activation(self.first_layer(tensordict))
        K = self.num_options
        logits, term = h[..., :K, :], h[..., K:, :]
        for i, layer in enumerate(self.control):
            logits = layer(logits)
            logits = self.activation(logits) if i < len(self.control) - 1 else logits
        for i, layer in enumerate(self.termination):
            term = layer(term)
            term = self.activation(term) if i < len(self.termination) - 1 else term
        tensordict.set(self.out_keys[0], logits)
        tensordict.set(self.out_keys[1], term.squeeze(-1))
        return tensordict
