"""DDOLossBase: what the DDO losses (one level, or one level over fixed lower levels) share.

TorchRL's ``LossModule`` contract (``torchrl/objectives/common.py``, with ``BCLoss`` and ``DQNLoss`` as the
examples): configurable keys through ``set_keys``, networks registered by ``convert_to_functional`` (so that
``reset_parameters_recursive``, ``get_stateful_net`` and ``from_stateful_net`` work), masking by
``loss_mask_key``, and a ``forward`` that also takes keyword tensors through ``@dispatch``. On top of it: the
batch checks of DDO's ``[B, T]`` trajectories, gathered in one pass with one host-device synchronisation, the
reductions and the posterior diagnostics.
"""
from __future__ import annotations

import math
from copy import deepcopy
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from tensordict import is_tensor_collection, TensorDict, TensorDictBase
from tensordict.nn import dispatch, TensorDictModuleBase, TensorDictParams
from tensordict.utils import NestedKey
from torchrl.objectives.common import AUTO_LOSS_MASK_KEYS, LossModule

from torchrl_options.checks import check_bool

__all__ = [
    "BatchChecks",
    "check_network_output",
    "DDOLossBase",
    "ddo_diagnostics",
    "meta_control_log_probs",
    "next_key",
    "prepare_trajectories",
    "terminal_flags",
]

_REDUCTIONS = ("mean", "sum", "none")


def next_key(key: NestedKey) -> NestedKey:
    """``key`` under ``"next"``: ``"observation"`` -> ``("next", "observation")``.

    Examples:
        >>> next_key(("obs", "pos"))
        ('next', 'obs', 'pos')
    """
    return ("next", key) if isinstance(key, str) else ("next", *key)


def _unique(keys) -> list:
    out = []
    for k in keys:
        if k not in out:
            out.append(k)
    return out


class BatchChecks:
    """Value checks of a batch, evaluated on its device and read back in one host-device synchronisation.

    Each :meth:`add` records a 0-d bool tensor (``True``: the check failed) and a function building the error
    message (called only on failure, where extra synchronisations no longer matter). :meth:`raise_if_any` reads all
    flags at once and raises a ``ValueError`` with the first failed check's message.

    Examples:
        >>> import torch
        >>> checks = BatchChecks()
        >>> x = torch.tensor([1.0, float("nan")])
        >>> checks.add(~torch.isfinite(x).all(), lambda: "'x' holds NaN")
        >>> checks.raise_if_any()
        Traceback (most recent call last):
            ...
        ValueError: 'x' holds NaN
    """

    def __init__(self) -> None:
        self._flags: list[torch.Tensor] = []
        self._messages: list[Callable[[], str]] = []

    def add(self, failed: torch.Tensor, message: Callable[[], str]) -> None:
        self._flags.append(failed.reshape(()))
        self._messages.append(message)

    def raise_if_any(self) -> None:
        if not self._flags:
            return
        device = self._flags[0].device
        failed = torch.stack([f.to(device) for f in self._flags]).tolist()  # the one synchronisation
        self._flags, messages = [], self._messages
        self._messages = []
        for bad, message in zip(failed, messages):
            if bad:
                raise ValueError(message())


def _first_bad_step(bad: torch.Tensor) -> str:
    b, t = bad.nonzero()[0].tolist()
    return f"(b, t) = ({b}, {t})"


def prepare_trajectories(
    tensordict: TensorDictBase,
    obs_keys: Sequence[NestedKey],
    mask_key: NestedKey | list[NestedKey],
    *,
    owner: str = "DDOLoss",
    current_keys: Sequence[NestedKey] = (),
    checks: BatchChecks | None = None,
) -> tuple[TensorDictBase, torch.Tensor, TensorDictBase, TensorDictBase]:
    """Checks a batch of trajectories and splits out what option networks read at ``s_t`` and ``s_{t+1}``.

    Args:
        tensordict (TensorDictBase): ``[B, T]`` trajectories (or one ``[T]`` trajectory).
        obs_keys (sequence of NestedKey): the entries the networks read, under the root and under ``"next"``.
        mask_key (NestedKey or list of NestedKey): the ``[B, T]`` bool validity mask, or a list of them (the valid
            steps are those valid in every one present). A missing entry means all valid.

    Keyword Args:
        owner (str): named in error messages.
        current_keys (sequence of NestedKey): entries read at ``s_t`` only (a meta-control's inputs).
        checks (BatchChecks, optional): where to record the value checks (NaN at a valid step, a mask that is
            not a prefix), so that the caller reads them with its own in one synchronisation. ``None``: checked
            here.

    Returns:
        ``(tensordict [B, T], mask [B, T], current, following)``: ``current`` and ``following`` hold the
        ``obs_keys`` at ``s_t`` and ``s_{t+1}`` (``current`` also the ``current_keys``) with padding replaced by
        zeros (padding may hold anything, and zeros keep NaN out of the networks' gradients).

    Raises:
        TypeError: for an input that is not a tensordict, or an entry that is not a tensor.
        ValueError: naming the key, for a batch that is not ``[B, T]``, an empty batch, a mask of the wrong dtype
            or shape or that is not a non-empty prefix of each row, a missing observation, a next observation of
            another shape than the observation, or NaN/inf in an observation at a valid step.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.randn(2, 3, 4), "next": {"observation": torch.randn(2, 3, 4)}},
        ...                   [2, 3])
        >>> td, mask, current, following = prepare_trajectories(data, ["observation"], ("collector", "mask"))
        >>> mask.all().item(), current["observation"].shape
        (True, torch.Size([2, 3, 4]))
    """
    if not is_tensor_collection(tensordict):
        raise TypeError(f"{owner} expects trajectories as a [B, T] TensorDict, got {type(tensordict).__name__}.")
    if tensordict.ndim == 1:
        tensordict = tensordict.unsqueeze(0)
    if tensordict.ndim != 2:
        raise ValueError(
            f"{owner} expects trajectories as a [B, T] tensordict, got batch_size {tuple(tensordict.batch_size)}."
        )
    B, T = tensordict.batch_size
    if B == 0 or T == 0:
        raise ValueError(f"{owner} got an empty batch of trajectories (batch_size {(B, T)}).")
    own_checks = checks is None
    checks = BatchChecks() if own_checks else checks
    mask = None
    for key in mask_key if isinstance(mask_key, list) else [mask_key]:
        m = tensordict.get(key, None)
        if m is None:
            continue
        if not isinstance(m, torch.Tensor):
            raise TypeError(
                f"{key!r} (a validity mask) must be a bool tensor of shape {(B, T)}, got {type(m).__name__}."
            )
        if m.shape == (B, T, 1):
            m = m.squeeze(-1)
        if m.shape != (B, T) or m.dtype != torch.bool:
            raise ValueError(f"{key!r} must be a bool tensor of shape {(B, T)}, got {m.dtype} {tuple(m.shape)}.")
        not_prefix = ~m[:, 0] | (m[:, 1:] & ~m[:, :-1]).any(1)
        checks.add(
            not_prefix.any(),
            lambda key=key, rows=not_prefix: (
                f"{key!r} must mark a non-empty prefix of each trajectory as valid (padding at the end only); row "
                f"{rows.nonzero()[0].item()} is not."
            ),
        )
        mask = m if mask is None else mask & m
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool, device=tensordict.device)
    following_root = tensordict.get("next", None)
    if following_root is None or not is_tensor_collection(following_root):
        raise ValueError(
            f"{owner} needs the next observations {[next_key(k) for k in obs_keys]} under 'next', missing from the "
            "trajectories."
        )
    obs_keys, current_keys = list(obs_keys), [k for k in current_keys if k not in obs_keys]
    current = tensordict.select(*obs_keys, *current_keys, strict=False)
    following = following_root.select(*obs_keys, strict=False)
    entries = [(key, key, current) for key in obs_keys + current_keys]
    entries += [(key, next_key(key), following) for key in obs_keys]
    for key, name, source in entries:
        x = source.get(key, None)
        if x is None:
            raise ValueError(
                f"{owner} needs {name!r} (an input of the networks), missing from the trajectories; they hold "
                f"{sorted(map(str, tensordict.keys(include_nested=True, leaves_only=True)))}."
            )
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name!r} (an input of the networks) must be a tensor, got {type(x).__name__}.")
        if x.is_complex():
            raise ValueError(f"{name!r} must hold real numbers, got {x.dtype}.")
        if name != key:
            shape = current.get(key).shape
            if x.shape != shape:
                raise ValueError(
                    f"{name!r} has shape {tuple(x.shape)} but {key!r} has shape {tuple(shape)}: the next observation "
                    "must have the observation's shape."
                )
        if x.is_floating_point():
            bad = ~torch.isfinite(x).reshape(B, T, -1).all(-1) & mask
            checks.add(
                bad.any(), lambda name=name, bad=bad: f"{name!r} holds NaN or inf at valid step {_first_bad_step(bad)}."
            )
        valid = mask.view(B, T, *([1] * (x.ndim - 2)))
        source.set(key, torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device)))
    if own_checks:
        checks.raise_if_any()
    return tensordict, mask, current, following


def meta_control_log_probs(
    meta_control: TensorDictModuleBase | None,
    tensordict: TensorDictBase,
    num_options: int,
    meta_logits_key: NestedKey,
    *,
    like: torch.Tensor,
) -> torch.Tensor:
    """``log eta(h | s_t)`` ``[B, T, K]``: uniform when ``meta_control`` is ``None``, else its log-softmax.

    Raises:
        ValueError: naming ``meta_logits_key`` when the meta-control does not choose among ``num_options``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.zeros(2, 3, 4)}, [2, 3])
        >>> meta_control_log_probs(None, td, 4, "meta_logits", like=torch.zeros(())).exp()[0, 0]
        tensor([0.2500, 0.2500, 0.2500, 0.2500])
    """
    B, T = tensordict.batch_size
    if meta_control is None:
        return torch.full((B, T, num_options), -math.log(num_options), dtype=like.dtype, device=like.device)
    meta = _output(meta_control(tensordict.select(*meta_control.in_keys)), meta_logits_key, "meta_control")
    if meta.shape != (B, T, num_options):
        raise ValueError(
            f"{meta_logits_key!r} must have shape [B, T, K] = {(B, T, num_options)}: the meta-control must choose "
            f"among the {num_options} options, got {tuple(meta.shape)}."
        )
    return meta.log_softmax(-1)


def terminal_flags(
    tensordict: TensorDictBase, terminal_key: NestedKey, mask: torch.Tensor, enabled: bool
) -> torch.Tensor:
    """``[B]`` bool: the ``terminal_key`` flag at each row's last valid step (all False when disabled or absent).

    Raises:
        ValueError: naming ``terminal_key`` when it is not ``[B, T]`` (or ``[B, T, 1]``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> mask = torch.tensor([[True, True, True], [True, True, False]])
        >>> td = TensorDict({("next", "terminated"): torch.tensor([[0, 0, 1], [0, 1, 0]]).bool()}, [2, 3])
        >>> terminal_flags(td, ("next", "terminated"), mask, enabled=True)
        tensor([True, True])
    """
    B, T = mask.shape
    terminal = torch.zeros(B, dtype=torch.bool, device=mask.device)
    flag = tensordict.get(terminal_key, None) if enabled else None
    if flag is not None:
        if not isinstance(flag, torch.Tensor) or flag.shape not in ((B, T), (B, T, 1)):
            shape = tuple(flag.shape) if isinstance(flag, torch.Tensor) else type(flag).__name__
            raise ValueError(
                f"{terminal_key!r} must be a [B, T] (or [B, T, 1]) flag with [B, T] = {(B, T)}, got {shape}."
            )
        # clamped: a row without valid steps fails the mask check before anything reads this
        last = (mask.sum(1) - 1).clamp_min(0)
        terminal = flag.reshape(B, T).bool().gather(1, last.unsqueeze(1)).squeeze(1)
    return terminal


def ddo_diagnostics(
    u: torch.Tensor, v: torch.Tensor, psi_next: torch.Tensor, n_steps: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The posterior diagnostics of the DDO losses, detached: ``option_duration`` (valid steps per expected option
    start), ``option_entropy`` (entropy, in nats, of the posterior option usage) and ``termination_probability``
    (posterior mean of ``psi`` of the active option at ``s_{t+1}``).

    Args:
        u, v (Tensor): ``[B, T, K]`` posterior marginals of the active option and of an option start (zero on
            padding).
        psi_next (Tensor): ``[B, T, K]`` termination probabilities at ``s_{t+1}``.
        n_steps (Tensor): the number of valid steps.

    Examples:
        >>> import torch
        >>> u = torch.tensor([[[1.0, 0.0], [0.5, 0.5]]])
        >>> v = torch.tensor([[[1.0, 0.0], [0.0, 0.5]]])
        >>> d = ddo_diagnostics(u, v, torch.full((1, 2, 2), 0.25), torch.tensor(2))
        >>> round(d["option_duration"].item(), 4), round(d["option_entropy"].item(), 4)
        (1.3333, 0.5623)
    """
    with torch.no_grad():
        usage = u.sum((0, 1)) / n_steps
        entropy = -(usage * usage.clamp_min(torch.finfo(usage.dtype).tiny).log()).sum()
        return {
            "option_duration": n_steps / v.sum(),
            "option_entropy": entropy,
            "termination_probability": (u * psi_next).sum() / n_steps,
        }


def check_network_output(
    checks: BatchChecks, name: str, x: torch.Tensor, mask: torch.Tensor, *, logits: bool = False
) -> None:
    """Records the check that a network's log-probabilities ``x`` ``[B, T, ...]`` hold no NaN or +inf at a valid
    step (``-inf`` is a probability of zero) in ``checks``; with ``logits=True``, no NaN (``x`` are logits).

    Examples:
        >>> import torch
        >>> checks = BatchChecks()
        >>> check_network_output(checks, "log pi", torch.full((1, 2, 3), float("nan")), torch.tensor([[True, False]]))
        >>> checks.raise_if_any()
        Traceback (most recent call last):
            ...
        ValueError: log pi holds NaN or +inf at valid step (b, t) = (0, 0): the networks' outputs must be finite.
    """
    B, T = mask.shape
    bad = torch.isnan(x) if logits else torch.isnan(x) | (x == float("inf"))
    bad = bad.reshape(B, T, -1).any(-1) & mask
    checks.add(
        bad.any(),
        lambda: (
            f"{name} holds NaN{'' if logits else ' or +inf'} at valid step {_first_bad_step(bad)}: the networks' "
            "outputs must be finite."
        ),
    )


def _output(out: TensorDictBase, key: NestedKey, name: str) -> torch.Tensor:
    x = out.get(key, None)
    if x is None:
        raise ValueError(f"{name} did not write {key!r}; it wrote {sorted(map(str, out.keys(True, True)))}.")
    return x


class DDOLossBase(LossModule):
    """Base of :class:`~torchrl_options.DDOLoss` and :class:`~torchrl_options.hierarchy.HierarchicalDDOLoss`.

    It keeps TorchRL's ``LossModule`` contract:

    - keys: a ``_AcceptedKeys`` dataclass changed with :meth:`set_keys`; :attr:`in_keys` lists every entry read;
    - networks: ``options`` (and a learned ``meta_control``) are registered with ``convert_to_functional``: their
      parameters live in ``options_params`` (``meta_control_params``), so ``reset_parameters_recursive()``,
      ``get_stateful_net("options")`` and ``from_stateful_net("options", net)`` work and ``state_dict()``,
      ``.to(...)`` and dtype casts carry them. The parameters are the modules' own (not copies): an optimizer over
      ``loss.parameters()`` trains ``loss.options``;
    - masks: the valid steps are those valid in ``tensor_keys.mask`` and in the entries named by
      :attr:`loss_mask_key` (TorchRL's convention: ``"auto"``, the default, reads ``("collector", "mask")`` and
      ``"shifted_valid"`` where present; a key reads that entry; ``None`` adds nothing to ``tensor_keys.mask``).
      Every mask present must mark a non-empty prefix of each trajectory (DDO's model has no gaps);
    - calls: ``loss(td)`` returns a TensorDict of ``loss_ddo`` and diagnostics; ``loss(observation=...,
      action=..., next_observation=...)`` (keys from :attr:`in_keys`, nested keys joined by ``"_"``) returns the
      tensors of :attr:`out_keys` in order (``@dispatch``, as TorchRL's losses).

    One call checks its batch in one pass: shapes, dtypes and keys before the networks run, values (NaN/inf at valid
    steps, mask prefixes, actions in range) read back together in one host-device synchronisation.

    Subclasses implement :meth:`log_probabilities` (the E-step inputs, checked), :meth:`_posterior` and
    :meth:`_top_marginals`.

    Every subclass takes these keyword arguments.

    Keyword Args:
        action_space (str): ``"auto"`` or one of the subclass's action spaces.
        terminal_at_end (bool): read ``tensor_keys.terminal`` at each row's last valid step and, where set,
            terminate the active option(s) at ``s_T``. Defaults to ``True``; a missing key means ``False``.
        reduction (str): ``"mean"`` (per valid step, default), ``"sum"`` or ``"none"`` (per trajectory, ``[B]``).
        diagnostics (bool): write the posterior diagnostics next to ``loss_ddo`` and ``log_likelihood_per_step``.
            Defaults to ``True``.
        backend (str): the E-step's backend, one of the subclass's ``BACKENDS``. Defaults to ``"auto"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> loss = DDOLoss(OptionsMLP(3, 4, 2))
        >>> isinstance(loss, DDOLossBase), loss.functional, loss.mask_keys
        (True, True, [('collector', 'mask'), 'shifted_valid'])
        >>> net = loss.get_stateful_net("options")  # a copy holding the loss's parameters
        >>> loss.reset_parameters_recursive()  # new parameters for the loss (and its options module)
        >>> loss.from_stateful_net("options", net)  # back to the copied ones
        >>> torch.equal(net.control.params["0", "weight"], loss.options_params["control", "params", "0", "weight"])
        True
        >>> data = TensorDict({"observation": torch.randn(2, 5, 3), "action": torch.randint(4, (2, 5)),
        ...                    "next": {"observation": torch.randn(2, 5, 3)}}, [2, 5])
        >>> data["observation"][0, 0] = float("nan")
        >>> loss(data)
        Traceback (most recent call last):
            ...
        ValueError: 'observation' holds NaN or inf at valid step (b, t) = (0, 0).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (change them with :meth:`set_keys`).

        Attributes:
            action (NestedKey): the action taken at each step. Defaults to ``"action"``.
            option_logits (NestedKey): written by discrete options, ``[..., K, A]``. Defaults to ``"option_logits"``.
            termination_logits (NestedKey): ``[..., K]``, ``psi = sigmoid``. Defaults to ``"termination_logits"``.
            meta_logits (NestedKey): ``[..., K]``, ``eta = softmax``. Defaults to ``"meta_logits"``.
            mask (NestedKey): ``[B, T]`` bool, the valid steps (a prefix of each row); a missing entry means all
                valid. Read with the entries of :attr:`loss_mask_key`. Defaults to ``("collector", "mask")``.
            terminal (NestedKey): ``[B, T]`` bool, read at each row's last valid step: the trajectory ends with its
                option terminating. Defaults to ``("next", "terminated")``.
        """

        action: NestedKey = "action"
        option_logits: NestedKey = "option_logits"
        termination_logits: NestedKey = "termination_logits"
        meta_logits: NestedKey = "meta_logits"
        mask: NestedKey = ("collector", "mask")
        terminal: NestedKey = ("next", "terminated")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    # subclasses list their out_keys (all of them, with diagnostics) as a class attribute

    options: TensorDictModuleBase
    options_params: TensorDictParams
    target_options_params: TensorDictParams
    meta_control: TensorDictModuleBase | None
    meta_control_params: TensorDictParams
    target_meta_control_params: TensorDictParams

    #: the E-step backends the subclass accepts
    BACKENDS: tuple[str, ...] = ("auto",)
    #: the action spaces the subclass accepts (besides ``"auto"``)
    ACTION_SPACES: tuple[str, ...] = ("categorical",)

    def __init__(
        self,
        options: TensorDictModuleBase,
        meta_control: TensorDictModuleBase | None = None,
        *,
        action_space: str = "auto",
        terminal_at_end: bool = True,
        reduction: str = "mean",
        diagnostics: bool = True,
        backend: str = "auto",
    ) -> None:
        name = type(self).__name__
        if not isinstance(options, TensorDictModuleBase):
            raise TypeError(f"{name}: options must be a TensorDictModuleBase, got {type(options).__name__}.")
        if meta_control is not None and not isinstance(meta_control, TensorDictModuleBase):
            raise TypeError(
                f"{name}: meta_control must be a TensorDictModuleBase or None, got {type(meta_control).__name__}."
            )
        if reduction not in _REDUCTIONS:
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}.")
        spaces = ("auto", *self.ACTION_SPACES)
        if action_space not in spaces:
            raise ValueError(f"action_space must be one of {spaces}, got {action_space!r}.")
        if not isinstance(backend, str) or backend not in self.BACKENDS:
            raise ValueError(f"backend must be one of {self.BACKENDS}, got {backend!r}.")
        for arg, value in (("terminal_at_end", terminal_at_end), ("diagnostics", diagnostics)):
            check_bool(value, arg)
        k_opt = getattr(options, "num_options", None)
        k_meta = getattr(meta_control, "num_options", None)
        if k_opt is not None and k_meta is not None and k_opt != k_meta:
            raise ValueError(
                f"options has num_options={k_opt} but meta_control has num_options={k_meta}: they must match."
            )
        super().__init__()
        self._in_keys = None
        self.convert_to_functional(options, "options")
        if meta_control is not None:
            self.convert_to_functional(meta_control, "meta_control")
        else:
            self.meta_control = None
        self.action_space = action_space
        self.terminal_at_end = terminal_at_end
        self.reduction = reduction
        self.backend = backend
        self.diagnostics = diagnostics

    # ----------------------------------------------------------------- settings
    @property
    def diagnostics(self) -> bool:
        """Whether the posterior diagnostics are written (they set :attr:`out_keys`)."""
        return self._diagnostics

    @diagnostics.setter
    def diagnostics(self, value: bool) -> None:
        check_bool(value, "diagnostics")
        self._diagnostics = value
        self.out_keys = list(type(self)._out_keys) if value else ["loss_ddo", "log_likelihood_per_step"]

    @property
    def loss_mask_key(self) -> NestedKey | Literal["auto"] | None:
        """TorchRL's masking convention (see :class:`~torchrl.objectives.LossModule`): ``"auto"`` (default),
        a key, or ``None``; read together with ``tensor_keys.mask`` (see :attr:`mask_keys`)."""
        return LossModule.loss_mask_key.fget(self)

    @loss_mask_key.setter
    def loss_mask_key(self, value: NestedKey | Literal["auto"] | None) -> None:
        LossModule.loss_mask_key.fset(self, value)
        self._in_keys = None

    @property
    def mask_keys(self) -> list[NestedKey]:
        """The validity masks read, in order: ``tensor_keys.mask``, then :attr:`loss_mask_key`'s entries. A step is
        valid when every mask present says so."""
        extra = self.loss_mask_key
        extra = () if extra is None else AUTO_LOSS_MASK_KEYS if extra == "auto" else (extra,)
        return _unique([self.tensor_keys.mask, *extra])

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def set_keys(self, **kwargs) -> None:
        super().set_keys(**kwargs)
        self._in_keys = None

    def _option_modules(self) -> list[TensorDictModuleBase]:
        """The modules evaluated at ``s_t`` and ``s_{t+1}`` (their ``in_keys`` are read under ``"next"`` too)."""
        return [self.options]

    def _obs_keys(self) -> list[NestedKey]:
        return _unique(k for m in self._option_modules() for k in m.in_keys)

    def _meta_keys(self) -> list[NestedKey]:
        return [] if self.meta_control is None else list(self.meta_control.in_keys)

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            obs = self._obs_keys()
            keys = obs + self._meta_keys() + [next_key(k) for k in obs]
            keys += [self.tensor_keys.action, *self.mask_keys, self.tensor_keys.terminal]
            self._in_keys = _unique(keys)
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    def get_stateful_net(self, network_name: str, copy: bool | None = None) -> TensorDictModuleBase:
        """A stateful version of ``options`` or ``meta_control`` holding the loss's parameters.

        As :meth:`torchrl.objectives.LossModule.get_stateful_net`, but the parameters are written into the module's
        own tensors (in place), so that ``net.parameters()`` are the ones its forward reads (TorchRL's version swaps
        them in, which modules keeping their parameters in a nested ``TensorDictParams``, such as
        ``MultiAgentMLP``, do not list in ``parameters()``).

        Args:
            network_name (str): ``"options"`` or ``"meta_control"``.
            copy (bool, optional): return a deep copy (default) rather than the loss's module.
        """
        if getattr(self, network_name, None) is None or f"{network_name}_params" not in self._modules:
            raise ValueError(
                f"network_name must name a network of the loss ('options', 'meta_control'), got {network_name!r}."
            )
        net = getattr(self, network_name)
        if copy is None or copy:
            net = deepcopy(net)
        TensorDict.from_module(net).data.update_(getattr(self, f"{network_name}_params").data)
        return net

    # ------------------------------------------------------------------ helpers
    def _run(self, name: str, tensordict: TensorDictBase) -> TensorDictBase:
        """Runs ``options`` or ``meta_control`` with the loss's parameters (``<name>_params``)."""
        module = getattr(self, name)
        with getattr(self, f"{name}_params").to_module(module):
            return _call_checked(name, module, tensordict)

    def _prepare(self, tensordict: TensorDictBase, checks: BatchChecks):
        """Shape/key checks, the zero-padded inputs of the networks and the actions; value checks go to ``checks``."""
        tensordict, mask, current, following = prepare_trajectories(
            tensordict, self._obs_keys(), self.mask_keys, owner=type(self).__name__, current_keys=self._meta_keys(),
            checks=checks,
        )  # fmt: skip
        for j, module in enumerate(self._option_modules()):
            _check_in_features(self._module_name(j), module, current)
        if self.meta_control is not None:
            _check_in_features("meta_control", self.meta_control, current)
        key = self.tensor_keys.action
        action = tensordict.get(key, None)
        if action is None:
            raise ValueError(f"{type(self).__name__} needs the action taken at {key!r}, missing from the trajectories.")
        if not isinstance(action, torch.Tensor):
            raise TypeError(f"{key!r} must be a tensor of actions, got {type(action).__name__}.")
        return tensordict, mask, current, following, action

    def _module_name(self, j: int) -> str:
        return "options"

    def _meta_log_probs(self, current: TensorDictBase, num_options: int, like: torch.Tensor) -> torch.Tensor:
        if self.meta_control is None:
            return meta_control_log_probs(None, current, num_options, self.tensor_keys.meta_logits, like=like)
        with self.meta_control_params.to_module(self.meta_control):
            return meta_control_log_probs(
                _CheckedModule("meta_control", self.meta_control), current, num_options, self.tensor_keys.meta_logits,
                like=like,
            )  # fmt: skip

    # ------------------------------------------------------------------ the loss
    def log_probabilities(self, tensordict: TensorDictBase) -> dict[str, Any]:
        """The E-step inputs of a ``[B, T]`` batch, after checking it (one synchronisation)."""
        raise NotImplementedError

    def _posterior(self, p: dict[str, Any], *, marginals: bool):
        """The E-step on :meth:`log_probabilities`' output: an object with ``log_likelihood`` ``[B]``."""
        raise NotImplementedError

    def _top_marginals(self, posterior) -> tuple[torch.Tensor, torch.Tensor]:
        """``(u, v)`` ``[B, T, K]`` of the trained options."""
        raise NotImplementedError

    def _extra_diagnostics(self, p: dict[str, Any], posterior, n_steps: torch.Tensor) -> dict[str, torch.Tensor]:
        return {}

    def loss_outputs(self, p: dict[str, Any], posterior) -> TensorDictBase:
        """``loss_ddo`` (reduced as :attr:`reduction` says), ``log_likelihood_per_step`` and, with
        :attr:`diagnostics`, the posterior diagnostics, from :meth:`log_probabilities`' output and its posterior."""
        n_steps = p["mask"].sum()
        ll = posterior.log_likelihood
        if self.reduction == "mean":
            loss = -ll.sum() / n_steps
        elif self.reduction == "sum":
            loss = -ll.sum()
        else:
            loss = -ll
        out = {"loss_ddo": loss, "log_likelihood_per_step": ll.detach().sum() / n_steps}
        if self.diagnostics:
            u, v = self._top_marginals(posterior)
            out.update(ddo_diagnostics(u, v, p["psi_next"], n_steps))
            with torch.no_grad():
                out.update(self._extra_diagnostics(p, posterior, n_steps))
        return TensorDict(out, batch_size=[])

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The loss of a ``[B, T]`` batch of trajectories (or of one ``[T]`` trajectory).

        Args:
            tensordict (TensorDictBase): the trajectories; the entries read are :attr:`in_keys`.

        Returns:
            A TensorDict with ``loss_ddo`` (differentiable) and the detached diagnostics of :attr:`out_keys`.
        """
        p = self.log_probabilities(tensordict)
        return self.loss_outputs(p, self._posterior(p, marginals=self.diagnostics))


def _check_in_features(name: str, module: TensorDictModuleBase, current: TensorDictBase) -> None:
    """For modules recording ``config["in_features"]`` (this package's MLPs, which concatenate their inputs along the
    last dimension): the inputs must be ``[B, T, F_i]`` with ``sum(F_i) == in_features``."""
    config = getattr(module, "config", None)
    n = config.get("in_features") if isinstance(config, dict) else None
    if not isinstance(n, int):
        return
    keys = list(module.in_keys)
    shapes = [tuple(current.get(k).shape) for k in keys]
    if any(len(s) != 3 for s in shapes) or sum(s[-1] for s in shapes) != n:
        described = ", ".join(f"{k!r}: {s}" for k, s in zip(keys, shapes))
        raise ValueError(
            f"{name} was built for in_features={n} (inputs [B, T, F] concatenated along the last dimension), but its "
            f"inputs have shapes {described}."
        )


def _call_checked(name: str, module: TensorDictModuleBase, tensordict: TensorDictBase) -> TensorDictBase:
    try:
        return module(tensordict)
    except (RuntimeError, IndexError) as err:
        shapes = {str(k): tuple(v.shape) for k, v in tensordict.items(True, True)}
        raise ValueError(f"{name} failed on its inputs {shapes}: {err}") from err


class _CheckedModule:
    """A module call whose torch errors name the module and its input shapes."""

    def __init__(self, name: str, module: TensorDictModuleBase) -> None:
        self.name, self.module, self.in_keys = name, module, module.in_keys

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        return _call_checked(self.name, self.module, tensordict)
