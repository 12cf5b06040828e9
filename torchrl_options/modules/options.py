"""K options as one TensorDict module: control policies and termination conditions evaluated in one pass.

An option (Sutton, Precup and Singh, 1999) is a control policy ``pi_h(a | s)`` with a termination condition
``psi_h(s)``. DDO (Fox et al., 2017, arXiv:1703.08294) learns K of them from demonstrations. Every part of
this package that uses options reads only these entries, so hand-written options are first-class:

- ``"option_logits"`` ``[..., K, A]``: the logits of each option's control policy over A discrete actions;
- ``"termination_logits"`` ``[..., K]``: ``psi_h(s) = sigmoid(termination_logits[..., h])``;
- for continuous actions, ``"option_loc"`` and ``"option_scale"`` ``[..., K, D]`` (a Gaussian per option).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MLP, MultiAgentMLP

from torchrl_options.checks import check_bool, check_number
from torchrl_options.modules._features import (
    activation_class,
    as_key_list,
    check_module_keys,
    check_sizes,
    hidden_sizes,
    key_to_config,
    ObservationModule,
)

__all__ = ["OptionsMLP", "GaussianOptionsMLP"]


def _ensemble(in_features: int, out_features: int, num_options: int, cells: list[int], activation: str) -> nn.Module:
    # K independent MLPs with stacked parameters (TorchRL's MultiAgentMLP); see _ensemble_forward.
    return MultiAgentMLP(
        n_agent_inputs=in_features,
        n_agent_outputs=out_features,
        n_agents=num_options,
        centralized=False,
        share_params=False,
        depth=len(cells),
        num_cells=cells,
        activation_class=activation_class(activation),
    )


def _ensemble_forward(net: MultiAgentMLP, x: torch.Tensor) -> torch.Tensor:
    """``net`` applied to the features ``x`` [..., F] shared by its K networks: [..., K, out].

    The same function as ``net(x.unsqueeze(-2).expand(..., K, F))`` (TorchRL vmaps its layers over the stacked
    parameters), written as batched matrix products over the stacked parameters: a few operations instead of a
    vmap, which dominates the cost of the small networks of options inside an env step. The first layer is one
    product for the K networks; each later layer is K products over all inputs at once (a ``[K, N, in]`` by
    ``[K, in, out]`` ``bmm``, not ``N * K`` vector-matrix products: 2x faster for 2 hidden units on 1851 inputs,
    18x for ``[64, 64]``). Outputs may be non-contiguous (option-major memory). Falls back to ``net`` for layers
    other than ``Linear`` and parameter-free activations.
    """
    plan = net.__dict__.get("_ensemble_plan")  # the layers, inspected once per network (not on every step)
    if plan is None:
        layers = list(net._empty_net.named_children())
        batched = all(isinstance(m, nn.Linear) or not any(True for _ in m.parameters()) for _, m in layers)
        plan = net.__dict__["_ensemble_plan"] = (layers, batched)
    layers, batched = plan
    if not batched:
        K = net.n_agents
        return net(x.unsqueeze(-2).expand(*x.shape[:-1], K, x.shape[-1]))
    params = net.params
    first = True
    for name, layer in layers:
        if isinstance(layer, nn.Linear):
            weight, bias = params.get((name, "weight")), params.get((name, "bias"))  # [K, out, in], [K, out]
            if first:  # one product for the K networks: [..., F] @ [F, K * out]
                x = torch.matmul(x, weight.flatten(0, 1).T).unflatten(-1, weight.shape[:2])
                first = False
            else:  # [K, N, in] @ [K, in, out] over the N = prod(...) inputs, back to [..., K, out]
                lead, K = x.shape[:-2], weight.shape[0]
                x = torch.bmm(x.reshape(lead.numel(), K, x.shape[-1]).transpose(0, 1), weight.transpose(-1, -2))
                x = x.transpose(0, 1).reshape(*lead, K, weight.shape[1])
            x = x + bias if bias is not None else x
        else:
            x = layer(x)
    return x


class OptionsMLP(ObservationModule):
    """K discrete-action options, each an MLP control policy and an MLP termination condition.

    With ``architecture="separate"`` (the paper's choice) every option has its own control network and its own
    termination network; the K networks of each kind are evaluated in one batched pass. With
    ``architecture="shared"`` one trunk feeds K control heads and K termination heads. The paper's four-rooms
    options use one hidden layer of 2 tanh units (``num_cells=2``); its Atari RAM options three dense tanh layers
    (``num_cells=[64, 64, 64]``, say).

    Reference: Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, sections 4 and 5.

    Args:
        in_features (int): size of the concatenated observation features.
        num_actions (int): A, the number of discrete actions.
        num_options (int): K, the number of options.

    Keyword Args:
        num_cells (int or sequence of int): hidden layer sizes. Defaults to ``2`` (one layer of 2 units).
        termination_cells (int or sequence of int, optional): hidden layer sizes of the termination networks, when
            they should differ from the control networks' (``architecture="separate"`` only). Defaults to
            ``num_cells``.
        activation (str): ``"tanh"`` (default), ``"relu"``, ``"elu"``, ...
        architecture (str): ``"separate"`` (default) or ``"shared"``.
        in_keys (NestedKey or list): observation keys, concatenated. Defaults to ``"observation"``.
        out_keys (list of two NestedKey): where to write the option logits and the termination logits.
            Defaults to ``["option_logits", "termination_logits"]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP
        >>> options = OptionsMLP(in_features=4, num_actions=5, num_options=3)
        >>> td = options(TensorDict({"observation": torch.randn(10, 4)}, [10]))
        >>> td["option_logits"].shape, td["termination_logits"].shape
        (torch.Size([10, 3, 5]), torch.Size([10, 3]))
    """

    def __init__(
        self,
        in_features: int,
        num_actions: int,
        num_options: int,
        *,
        num_cells: int | Sequence[int] = 2,
        termination_cells: int | Sequence[int] | None = None,
        activation: str = "tanh",
        architecture: str = "separate",
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        if out_keys is None:
            out_keys = ["option_logits", "termination_logits"]
        check_sizes(in_features=in_features, num_actions=num_actions, num_options=num_options)
        if architecture not in ("separate", "shared"):
            raise ValueError(f"architecture must be 'separate' or 'shared', got {architecture!r}.")
        out_keys = as_key_list(out_keys, "out_keys")
        if len(out_keys) != 2:
            raise ValueError(f"out_keys must name two entries (option logits, termination logits), got {out_keys}.")
        self.in_keys = as_key_list(in_keys, "in_keys")
        self.out_keys = out_keys
        check_module_keys("OptionsMLP", self.in_keys, self.out_keys)
        cells = hidden_sizes(num_cells)
        if termination_cells is not None and architecture != "separate":
            raise ValueError(
                f"termination_cells needs architecture='separate' (the shared trunk feeds every head), got "
                f"architecture={architecture!r}."
            )
        term_cells = cells if termination_cells is None else hidden_sizes(termination_cells, "termination_cells")
        self.num_options, self.num_actions = num_options, num_actions
        self.architecture = architecture
        self.config = dict(
            in_features=in_features,
            num_actions=num_actions,
            num_options=num_options,
            num_cells=cells,
            termination_cells=term_cells if architecture == "separate" else None,
            activation=activation,
            architecture=architecture,
            in_keys=[key_to_config(k) for k in self.in_keys],
            out_keys=[key_to_config(k) for k in self.out_keys],
        )
        if architecture == "separate":
            self.control = _ensemble(in_features, num_actions, num_options, cells, activation)
            self.termination = _ensemble(in_features, 1, num_options, term_cells, activation)
        else:
            act = activation_class(activation)
            self.trunk = MLP(
                in_features=in_features,
                out_features=cells[-1],
                num_cells=cells[:-1],
                activation_class=act,
                activate_last_layer=True,
            )
            self.heads = nn.Linear(cells[-1], num_options * (num_actions + 1))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = self.features(tensordict)
        K, A = self.num_options, self.num_actions
        if self.architecture == "separate":
            logits = _ensemble_forward(self.control, x)
            term = _ensemble_forward(self.termination, x).squeeze(-1)
        else:
            out = self.heads(self.trunk(x)).unflatten(-1, (K, A + 1))
            logits, term = out[..., :A], out[..., A]
        tensordict.set(self.out_keys[0], logits)
        tensordict.set(self.out_keys[1], term)
        return tensordict


class GaussianOptionsMLP(ObservationModule):
    """K continuous-action options: Gaussian control policies and sigmoid termination conditions.

    The paper's discussion notes that DDO's derivation holds for continuous actions. Each option h has a mean
    network ``mu_h(s)`` and a learned state-independent log-scale per action dimension (``state_dependent_scale``
    makes it an output of the network); its termination network is as in :class:`OptionsMLP`.

    Args:
        in_features (int): size of the concatenated observation features.
        action_dim (int): D, the dimension of the continuous action.
        num_options (int): K.

    Keyword Args:
        num_cells (int or sequence of int): hidden sizes. Defaults to ``[64, 64]``.
        termination_cells (int or sequence of int, optional): hidden sizes of the termination networks, when they
            should differ from the mean networks'. Defaults to ``num_cells``.
        activation (str): defaults to ``"tanh"``.
        init_scale (float): initial standard deviation. Defaults to ``1.0``.
        min_scale (float): lower bound of the standard deviation, keeping the likelihood bounded (a Gaussian
            whose scale collapses on one point has unbounded density). Defaults to ``1e-3``.
        state_dependent_scale (bool): defaults to ``False``.
        in_keys (NestedKey or list): defaults to ``"observation"``.
        out_keys (list of three NestedKey): defaults to ``["option_loc", "option_scale", "termination_logits"]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import GaussianOptionsMLP
        >>> options = GaussianOptionsMLP(in_features=3, action_dim=2, num_options=4)
        >>> td = options(TensorDict({"observation": torch.randn(7, 3)}, [7]))
        >>> td["option_loc"].shape, td["option_scale"].shape, td["termination_logits"].shape
        (torch.Size([7, 4, 2]), torch.Size([7, 4, 2]), torch.Size([7, 4]))
    """

    def __init__(
        self,
        in_features: int,
        action_dim: int,
        num_options: int,
        *,
        num_cells: int | Sequence[int] = (64, 64),
        termination_cells: int | Sequence[int] | None = None,
        activation: str = "tanh",
        init_scale: float = 1.0,
        min_scale: float = 1e-3,
        state_dependent_scale: bool = False,
        in_keys: NestedKey | Sequence[NestedKey] = "observation",
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        if out_keys is None:
            out_keys = ["option_loc", "option_scale", "termination_logits"]
        check_sizes(in_features=in_features, action_dim=action_dim, num_options=num_options)
        check_number(init_scale, "init_scale", lo=0.0, hi=math.inf, lo_open=True, hi_open=True)
        check_number(min_scale, "min_scale", lo=0.0, hi=math.inf, lo_open=True, hi_open=True)
        check_bool(state_dependent_scale, "state_dependent_scale")
        if init_scale <= min_scale or min_scale <= 0:
            raise ValueError(f"need 0 < min_scale < init_scale, got min_scale={min_scale}, init_scale={init_scale}.")
        out_keys = as_key_list(out_keys, "out_keys")
        if len(out_keys) != 3:
            raise ValueError(f"out_keys must name three entries (loc, scale, termination logits), got {out_keys}.")
        self.in_keys = as_key_list(in_keys, "in_keys")
        self.out_keys = out_keys
        check_module_keys("GaussianOptionsMLP", self.in_keys, self.out_keys)
        cells = hidden_sizes(num_cells)
        term_cells = cells if termination_cells is None else hidden_sizes(termination_cells, "termination_cells")
        self.num_options, self.action_dim = num_options, action_dim
        self.min_scale = min_scale
        self.state_dependent_scale = state_dependent_scale
        self.config = dict(
            in_features=in_features,
            action_dim=action_dim,
            num_options=num_options,
            num_cells=cells,
            termination_cells=term_cells,
            activation=activation,
            init_scale=init_scale,
            min_scale=min_scale,
            state_dependent_scale=state_dependent_scale,
            in_keys=[key_to_config(k) for k in self.in_keys],
            out_keys=[key_to_config(k) for k in self.out_keys],
        )
        out = 2 * action_dim if state_dependent_scale else action_dim
        self.control = _ensemble(in_features, out, num_options, cells, activation)
        self.termination = _ensemble(in_features, 1, num_options, term_cells, activation)
        # softplus(raw) + min_scale == init_scale at initialisation
        raw = torch.log(torch.expm1(torch.tensor(init_scale - min_scale)))
        self.raw_scale = nn.Parameter(torch.full((num_options, action_dim), float(raw)))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = self.features(tensordict)
        D = self.action_dim
        out = _ensemble_forward(self.control, x)
        if self.state_dependent_scale:
            loc, raw = out[..., :D], out[..., D:] + self.raw_scale
        else:
            loc, raw = out, self.raw_scale.expand_as(out)
        scale = nn.functional.softplus(raw) + self.min_scale
        tensordict.set(self.out_keys[0], loc)
        tensordict.set(self.out_keys[1], scale)
        tensordict.set(self.out_keys[2], _ensemble_forward(self.termination, x).squeeze(-1))
        return tensordict
