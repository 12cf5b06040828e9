"""K options over a one-hot egocentric grid view: small convolutional networks, as the DDO paper's surgical options.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.3, discover options from
images with convolutional networks. :class:`GridConvOptions` does the same on a MiniGrid-style view: the observation
is a flat vector whose first ``channels * view * view`` features are a channels-first one-hot grid (what
:class:`~torchrl_options.envs.minigrid.MiniGridOneHot` writes) and whose remaining features (the agent's direction,
say) join the convolution's output before the dense layers. An :class:`~torchrl_options.OptionsMLP` on the same
vector sees the 980 view features as unrelated inputs; the convolution shares its filters across the cells.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from torchrl_options.modules._features import (
    activation_class,
    as_key_list,
    hidden_sizes,
    key_to_config,
    ObservationModule,
)

__all__ = ["GridConvOptions"]


class _StackedLinear(nn.Module):
    """``n`` independent linear layers applied to ``[..., n, in]``: weights ``[n, in, out]``."""

    def __init__(self, n: int, in_features: int, out_features: int):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default initialisation
        self.weight = nn.Parameter(torch.empty(n, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(n, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("...ni,nio->...no", x, self.weight) + self.bias


class GridConvOptions(ObservationModule):
    """K discrete-action options, each reading a one-hot grid view through a small convolutional network.

    The observation (the concatenated ``in_keys``) is ``[..., channels * view_size**2 + extra_features]``: a
    channels-first grid flattened, then extra features. With ``architecture="shared"`` (default) one convolutional
    torso feeds ``2K`` dense heads (K control, K termination), each with its own dense layers; with ``"separate"``
    each of the ``2K`` networks has its own filters too (one grouped convolution: on a CPU about 9 times the time
    of the shared torso per pass over 2000 MiniGrid views, which is why it is not the default). Each network:
    ``len(conv_channels)`` valid 3x3 convolutions (``activation`` after each), flattened, the extra features
    appended, then dense layers of ``num_cells`` units and the output (A logits, or one termination logit).

    Writes ``option_logits`` ``[..., K, A]`` and ``termination_logits`` ``[..., K]``, so it runs wherever options
    run (:func:`~torchrl_options.discover_options` with ``options=``, :class:`~torchrl_options.OptionExecutor`).

    Args:
        num_actions (int): A.
        num_options (int): K.

    Keyword Args:
        channels (int): channels of the one-hot grid. Defaults to 20 (MiniGrid's object type, colour, state).
        view_size (int): the grid is ``view_size x view_size``. Defaults to 7.
        extra_features (int): features after the grid. Defaults to 4 (the one-hot direction).
        conv_channels (sequence of int): output channels of each 3x3 convolution. Defaults to ``[8, 8]``.
        num_cells (int or sequence of int): hidden dense widths after the convolutions. Defaults to ``[32]``.
        activation (str): defaults to ``"relu"``.
        architecture (str): ``"shared"`` (default) or ``"separate"``.
        in_keys (NestedKey or list): defaults to ``"observation"``.
        out_keys (list of two NestedKey): defaults to ``["option_logits", "termination_logits"]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.modules import GridConvOptions
        >>> options = GridConvOptions(num_actions=7, num_options=3)
        >>> td = options(TensorDict(observation=torch.rand(5, 20 * 49 + 4), batch_size=[5]))
        >>> td["option_logits"].shape, td["termination_logits"].shape
        (torch.Size([5, 3, 7]), torch.Size([5, 3]))
    """

    def __init__(
        self,
        num_actions: int,
        num_options: int,
        *,
        channels: int = 20,
        view_size: int = 7,
        extra_features: int = 4,
        conv_channels: Sequence[int] = (8, 8),
        num_cells: int | Sequence[int] = (32,),
        activation: str = "relu",
        architecture: str = "shared",
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        from torchrl_options.checks import check_choice, check_int

        super().__init__()
        for name, value, minimum in (("num_actions", num_actions, 1), ("num_options", num_options, 1),
                                     ("channels", channels, 1), ("view_size", view_size, 1),
                                     ("extra_features", extra_features, 0)):  # fmt: skip
            check_int(value, name, minimum=minimum)
        check_choice(architecture, "architecture", ("separate", "shared"))
        convs = hidden_sizes(list(conv_channels), "conv_channels") if len(conv_channels) else []
        if view_size - 2 * len(convs) < 1:
            raise ValueError(
                f"conv_channels has {len(convs)} valid 3x3 convolutions, too many for a {view_size}x{view_size} view "
                f"(each removes 2 cells per side); use at most {(view_size - 1) // 2}."
            )
        cells = hidden_sizes(num_cells)
        activation_class(activation)  # refuses an unknown name
        if out_keys is None:
            out_keys = ["option_logits", "termination_logits"]
        out_keys = as_key_list(out_keys, "out_keys")
        if len(out_keys) != 2:
            raise ValueError(f"out_keys must name two entries (option logits, termination logits), got {out_keys}.")
        self.in_keys = as_key_list(in_keys, "in_keys")
        self.out_keys = out_keys
        self.num_actions, self.num_options = num_actions, num_options
        self.channels, self.view_size, self.extra_features = channels, view_size, extra_features
        self.architecture = architecture
        self.config = dict(
            num_actions=num_actions, num_options=num_options, channels=channels, view_size=view_size,
            extra_features=extra_features, conv_channels=convs, num_cells=cells, activation=activation,
            architecture=architecture, in_keys=[key_to_config(k) for k in self.in_keys],
            out_keys=[key_to_config(k) for k in self.out_keys],
        )  # fmt: skip
        K = num_options
        self.groups = 2 * K if architecture == "separate" else 1
        G = self.groups
        act = activation_class(activation)
        layers: list[nn.Module] = []
        c_in = channels
        for c_out in convs:
            layers += [nn.Conv2d(G * c_in, G * c_out, 3, groups=G), act()]
            c_in = c_out
        self.conv = nn.Sequential(*layers)
        side = view_size - 2 * len(convs)
        flat = c_in * side * side + extra_features
        widths = [flat, *cells]
        # 2K heads (K control, K termination), each its own dense layers on its network's features
        self.hidden = nn.ModuleList(_StackedLinear(2 * K, a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.control_out = _StackedLinear(K, widths[-1], num_actions)
        self.termination_out = _StackedLinear(K, widths[-1], 1)
        self.act = act()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = self.features(tensordict)
        n_grid = self.channels * self.view_size**2
        if x.shape[-1] != n_grid + self.extra_features:
            raise ValueError(
                f"GridConvOptions expects {n_grid + self.extra_features} features ({self.channels} x {self.view_size} x "
                f"{self.view_size} grid + {self.extra_features}) in {self.in_keys}, got {x.shape[-1]}."
            )
        lead = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1])
        grid = x[:, :n_grid].reshape(-1, self.channels, self.view_size, self.view_size)
        K, G = self.num_options, self.groups
        if G > 1:
            grid = grid.repeat(1, G, 1, 1)
        h = self.conv(grid).reshape(x.shape[0], G, -1)  # [N, G, features]
        h = torch.cat([h, x[:, None, n_grid:].expand(-1, G, -1)], -1)
        if G == 1:
            h = h.expand(-1, 2 * K, -1)
        for layer in self.hidden:
            h = self.act(layer(h))
        logits = self.control_out(h[:, :K])
        term = self.termination_out(h[:, K:]).squeeze(-1)
        tensordict.set(self.out_keys[0], logits.reshape(*lead, K, self.num_actions))
        tensordict.set(self.out_keys[1], term.reshape(*lead, K))
        return tensordict
