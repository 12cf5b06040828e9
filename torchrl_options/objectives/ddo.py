"""DDOLoss: the negative log-likelihood of demonstrations under K options, trained by Expectation-Gradient."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from torchrl_options.inference import forward_backward

__all__ = ["DDOLoss", "meta_control_log_probs", "option_log_probs", "prepare_trajectories", "terminal_flags"]


def _key_name(key: NestedKey) -> str:
    return repr(key)


def _unique_keys(keys) -> list[NestedKey]:
    out = []
    for k in keys:
        if k not in out:
            out.append(k)
    return out


def option_log_probs(
    outputs: TensorDictBase,
    action: torch.Tensor,
    *,
    action_space: str = "auto",
    option_logits_key: NestedKey = "option_logits",
    option_loc_key: NestedKey = "option_loc",
    option_scale_key: NestedKey = "option_scale",
    action_key: NestedKey = "action",
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Each option's log-probability of the action taken, ``log pi_h(a_t | s_t)``, shape ``[*batch, K]``.

    Args:
        outputs (TensorDictBase): an options module's output: ``option_logits`` ``[*batch, K, A]`` (discrete) or
            ``option_loc``/``option_scale`` ``[*batch, K, D]`` (Gaussian).
        action (Tensor): the actions, ``[*batch]`` or ``[*batch, 1]`` integers or ``[*batch, A]`` one-hot
            (discrete), or ``[*batch, D]`` (continuous).

    Keyword Args:
        action_space (str): ``"categorical"``, ``"continuous"`` or ``"auto"`` (by the entries present).
        option_logits_key, option_loc_key, option_scale_key (NestedKey): where the options wrote their outputs.
        action_key (NestedKey): the action's key, used in error messages.
        mask (Tensor, optional): ``[*batch]`` bool, the valid entries; padded actions may hold anything.

    Raises:
        ValueError: naming ``action_key`` for actions outside the action space or of the wrong shape.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> out = TensorDict({"option_logits": torch.zeros(3, 2, 4)}, [3])
        >>> option_log_probs(out, torch.tensor([0, 1, 3]))
        tensor([[-1.3863, -1.3863],
                [-1.3863, -1.3863],
                [-1.3863, -1.3863]])
    """
    batch = outputs.batch_size
    if mask is None:
        mask = torch.ones(batch, dtype=torch.bool, device=action.device)
    if action_space == "auto":
        if option_logits_key in outputs.keys(include_nested=True):
            action_space = "categorical"
        elif option_loc_key in outputs.keys(include_nested=True):
            action_space = "continuous"
        else:
            raise KeyError(
                f"the options module wrote neither {option_logits_key!r} (discrete options) nor {option_loc_key!r} "
                "(Gaussian options)."
            )
    if action_space == "categorical":
        logits = outputs.get(option_logits_key)
        A = logits.shape[-1]
        if logits.shape[:-2] != batch:
            raise ValueError(
                f"{option_logits_key!r} must have shape [*batch, K, A] with batch {tuple(batch)}, got {tuple(logits.shape)}."
            )
        if action.shape == (*batch, A) and A > 1:
            # one-hot actions (TorchRL's OneHot spec)
            one_hot = (((action == 0) | (action == 1)).all(-1) & (action.sum(-1) == 1)) | ~mask
            if not one_hot.all():
                raise ValueError(f"{_key_name(action_key)}: one-hot actions must have exactly one 1 per valid step.")
            index = torch.where(mask, action.long().argmax(-1), 0)
        else:
            if action.shape == (*batch, 1):
                action = action.squeeze(-1)
            if action.shape != batch or action.is_floating_point():
                raise ValueError(
                    f"{_key_name(action_key)} must hold integer actions of shape {tuple(batch)} (or with a trailing "
                    f"1), or one-hot actions of shape {(*batch, A)}, got {action.dtype} {tuple(action.shape)}."
                )
            action = action.long()
            bad = ((action < 0) | (action >= A)) & mask
            if bad.any():
                raise ValueError(
                    f"{_key_name(action_key)} holds {action[bad][0].item()}, outside the options' action space "
                    f"[0, {A}) given by {option_logits_key!r}."
                )
            index = torch.where(mask, action, 0)
        logp = logits.log_softmax(-1)
        return logp.gather(-1, index[..., None, None].expand(*batch, logp.shape[-2], 1)).squeeze(-1)
    if action_space == "continuous":
        loc, scale = outputs.get(option_loc_key), outputs.get(option_scale_key)
        D = loc.shape[-1]
        if action.shape != (*batch, D):
            raise ValueError(
                f"{_key_name(action_key)} must have shape {(*batch, D)} for Gaussian options of dimension {D}, got "
                f"{tuple(action.shape)}."
            )
        action = torch.where(mask.unsqueeze(-1), action.to(loc.dtype), 0.0)
        if not torch.isfinite(action).all():
            raise ValueError(f"{_key_name(action_key)} holds NaN or inf at a valid step.")
        dist = torch.distributions.Normal(loc, scale, validate_args=False)
        return dist.log_prob(action.unsqueeze(-2)).sum(-1)
    raise ValueError(f"action_space must be 'auto', 'categorical' or 'continuous', got {action_space!r}.")


def prepare_trajectories(
    tensordict: TensorDictBase,
    obs_keys: list[NestedKey],
    mask_key: NestedKey,
    *,
    owner: str = "DDOLoss",
) -> tuple[TensorDictBase, torch.Tensor, TensorDictBase, TensorDictBase]:
    """Checks a batch of trajectories and splits out what option networks read at ``s_t`` and ``s_{t+1}``.

    Args:
        tensordict (TensorDictBase): ``[B, T]`` trajectories (or one ``[T]`` trajectory).
        obs_keys (list of NestedKey): the entries the networks read, under the root and under ``"next"``.
        mask_key (NestedKey): the ``[B, T]`` bool validity mask (a missing entry means all valid).

    Keyword Args:
        owner (str): named in error messages.

    Returns:
        ``(tensordict [B, T], mask [B, T], current, following)``: ``current`` and ``following`` hold the
        ``obs_keys`` at ``s_t`` and ``s_{t+1}`` with padding replaced by zeros (padding may hold anything, and
        zeros keep NaN out of the networks' gradients).

    Raises:
        ValueError: for a batch that is not ``[B, T]``, an empty batch, a mask that is not a non-empty prefix of
            each row, or NaN/inf in a valid observation, naming the key. KeyError for a missing observation.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.randn(2, 3, 4), "next": {"observation": torch.randn(2, 3, 4)}},
        ...                   [2, 3])
        >>> td, mask, current, following = prepare_trajectories(data, ["observation"], ("collector", "mask"))
        >>> mask.all().item(), current["observation"].shape
        (True, torch.Size([2, 3, 4]))
    """
    if tensordict.ndim == 1:
        tensordict = tensordict.unsqueeze(0)
    if tensordict.ndim != 2:
        raise ValueError(
            f"{owner} expects trajectories as a [B, T] tensordict, got batch_size {tuple(tensordict.batch_size)}."
        )
    B, T = tensordict.batch_size
    if B == 0 or T == 0:
        raise ValueError(f"{owner} got an empty batch of trajectories (batch_size {(B, T)}).")
    mask = tensordict.get(mask_key, None)
    if mask is None:
        mask = torch.ones(B, T, dtype=torch.bool, device=tensordict.device)
    else:
        if mask.shape == (B, T, 1):
            mask = mask.squeeze(-1)
        if mask.shape != (B, T) or mask.dtype != torch.bool:
            raise ValueError(f"{mask_key!r} must be a bool tensor of shape {(B, T)}, got {mask.dtype} {tuple(mask.shape)}.")
        if not mask[:, 0].all() or (mask[:, 1:] & ~mask[:, :-1]).any():
            raise ValueError(
                f"{mask_key!r} must mark a non-empty prefix of each trajectory as valid (padding at the end only)."
            )
    current = tensordict.select(*obs_keys, strict=False)
    following = tensordict.get("next").select(*obs_keys, strict=False)
    for key in obs_keys:
        for name, source in ((key, current), (("next", key) if isinstance(key, str) else ("next", *key), following)):
            x = source.get(key, None)
            if x is None:
                raise KeyError(f"{owner} needs {name!r} (an input of the option networks) in the trajectories.")
            if x.is_floating_point():
                bad = ~torch.isfinite(x).reshape(B, T, -1).all(-1) & mask
                if bad.any():
                    b, t = bad.nonzero()[0].tolist()
                    raise ValueError(f"{name!r} holds NaN or inf at valid step (b, t) = ({b}, {t}).")
            valid = mask.view(B, T, *([1] * (x.ndim - 2)))
            source.set(key, torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device)))
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
    meta = meta_control(tensordict.select(*meta_control.in_keys)).get(meta_logits_key)
    if meta.shape != (B, T, num_options):
        raise ValueError(
            f"{meta_logits_key!r} must have shape [B, T, K] = {(B, T, num_options)}: the meta-control must choose "
            f"among the {num_options} options, got {tuple(meta.shape)}."
        )
    return meta.log_softmax(-1)


def terminal_flags(tensordict: TensorDictBase, terminal_key: NestedKey, mask: torch.Tensor, enabled: bool) -> torch.Tensor:
    """``[B]`` bool: the ``terminal_key`` flag at each row's last valid step (all False when disabled or absent).

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
        terminal = flag.reshape(B, T).bool().gather(1, (mask.sum(1) - 1).unsqueeze(1)).squeeze(1)
    return terminal


class DDOLoss(LossModule):
    r"""The DDO loss: negative log-likelihood of demonstration trajectories under a set of options.

    Discovery of Deep Options (Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options",
    arXiv:1703.08294, 2017) fits K options ``<pi_h, psi_h>`` and a meta-control policy ``eta`` to trajectories
    ``xi = (s_0, a_0, ..., s_T)`` by maximising

    .. math::
        L[\theta; \xi] = \log \sum_\zeta P_\theta(\zeta, \xi),

    over the latent option sequence and switch indicators ``zeta``. Its gradient is the Expectation-Gradient of
    section 4.2,

    .. math::
        \nabla L = \sum_{t,h} v_t(h) \nabla \log\eta(h|s_t) + u_t(h) \nabla \log\pi_h(a_t|s_t)
                   + (u_t(h) - w_t(h)) \nabla \log\psi_h(s_{t+1}) + w_t(h) \nabla \log(1-\psi_h(s_{t+1})),

    with the posterior marginals ``u, v, w`` of :func:`~torchrl_options.forward_backward`, which computes the
    likelihood exactly and returns this gradient from its backward pass. The loss is ``-L`` divided by the
    number of valid steps (``reduction="mean"``).

    Inputs are trajectories as a ``[B, T]`` TensorDict, the layout TorchRL hands out (a ``SliceSampler`` batch
    reshaped to ``[num_slices, slice_len]``, :func:`~torchrl.collectors.utils.split_trajectories`, or a
    ``Collector`` with ``traj_format="padded"``): observations at ``s_t`` and under ``"next"`` at ``s_{t+1}``,
    the action taken, a validity mask and, optionally, a flag saying the trajectory ends with its option
    terminating. Termination is evaluated at ``s_{t+1}`` (the next observation), as in the paper's model.

    Args:
        options (TensorDictModuleBase): writes ``option_logits`` ``[..., K, A]`` (or ``option_loc``/
            ``option_scale`` ``[..., K, D]``) and ``termination_logits`` ``[..., K]`` from the observation.
        meta_control (TensorDictModuleBase, optional): writes ``meta_logits`` ``[..., K]``. ``None`` fixes the
            meta-control to uniform (the paper's H1u); a learned module is trained jointly (H1s).

    Keyword Args:
        action_space (str): ``"auto"`` (default, by the entries the options write), ``"categorical"`` or
            ``"continuous"``.
        terminal_at_end (bool): read the ``terminal`` key at each row's last valid step and, where it is set,
            multiply the likelihood by ``psi_h(s_T)``. Defaults to ``True``; a missing key means ``False``.
        reduction (str): ``"mean"`` (per valid step, default), ``"sum"``, or ``"none"`` (per trajectory, ``[B]``).

    The diagnostics written next to ``loss_ddo`` are detached: ``log_likelihood_per_step``, ``option_duration``
    (valid steps per expected option start), ``option_entropy`` (entropy, in nats, of the posterior option usage)
    and ``termination_probability`` (posterior mean of ``psi`` of the active option).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> B, T, A, K = 4, 20, 3, 2
        >>> data = TensorDict({
        ...     "observation": torch.randn(B, T, 5),
        ...     "action": torch.randint(A, (B, T)),
        ...     "next": {"observation": torch.randn(B, T, 5)},
        ...     ("collector", "mask"): torch.ones(B, T, dtype=torch.bool),
        ... }, [B, T])
        >>> loss = DDOLoss(OptionsMLP(5, A, K))
        >>> out = loss(data)
        >>> out["loss_ddo"].backward()
        >>> sorted(out.keys())
        ['log_likelihood_per_step', 'loss_ddo', 'option_duration', 'option_entropy', 'termination_probability']

        Keys are configurable:

        >>> data.rename_key_("action", "expert_action")
        TensorDict(...)
        >>> loss.set_keys(action="expert_action")
        >>> loss(data)["loss_ddo"].shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (change them with :meth:`set_keys`).

        Attributes:
            action (NestedKey): the action taken at each step. Defaults to ``"action"``.
            option_logits (NestedKey): written by discrete options, ``[..., K, A]``. Defaults to ``"option_logits"``.
            option_loc (NestedKey): written by Gaussian options, ``[..., K, D]``. Defaults to ``"option_loc"``.
            option_scale (NestedKey): written by Gaussian options, ``[..., K, D]``. Defaults to ``"option_scale"``.
            termination_logits (NestedKey): ``[..., K]``, ``psi = sigmoid``. Defaults to ``"termination_logits"``.
            meta_logits (NestedKey): ``[..., K]``, ``eta = softmax``. Defaults to ``"meta_logits"``.
            mask (NestedKey): ``[B, T]`` bool, the valid steps (a prefix of each row); a missing entry means all
                valid. Defaults to ``("collector", "mask")``.
            terminal (NestedKey): ``[B, T]`` bool, read at each row's last valid step: the trajectory ends with its
                option terminating. Defaults to ``("next", "terminated")``.
        """

        action: NestedKey = "action"
        option_logits: NestedKey = "option_logits"
        option_loc: NestedKey = "option_loc"
        option_scale: NestedKey = "option_scale"
        termination_logits: NestedKey = "termination_logits"
        meta_logits: NestedKey = "meta_logits"
        mask: NestedKey = ("collector", "mask")
        terminal: NestedKey = ("next", "terminated")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_ddo", "log_likelihood_per_step", "option_duration", "option_entropy", "termination_probability"]

    def __init__(
        self,
        options: TensorDictModuleBase,
        meta_control: TensorDictModuleBase | None = None,
        *,
        action_space: str = "auto",
        terminal_at_end: bool = True,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}.")
        if action_space not in ("auto", "categorical", "continuous"):
            raise ValueError(f"action_space must be 'auto', 'categorical' or 'continuous', got {action_space!r}.")
        k_opt = getattr(options, "num_options", None)
        k_meta = getattr(meta_control, "num_options", None)
        if k_opt is not None and k_meta is not None and k_opt != k_meta:
            raise ValueError(
                f"options has num_options={k_opt} but meta_control has num_options={k_meta}: they must match."
            )
        self.options = options
        self.meta_control = meta_control
        self.action_space = action_space
        self.terminal_at_end = terminal_at_end
        self.reduction = reduction
        self._in_keys = None

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def set_keys(self, **kwargs) -> None:
        super().set_keys(**kwargs)
        self._in_keys = None

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            obs = list(self.options.in_keys)
            if self.meta_control is not None:
                obs += list(self.meta_control.in_keys)
            keys = obs + [("next", k) if isinstance(k, str) else ("next", *k) for k in self.options.in_keys]
            keys += [self.tensor_keys.action, self.tensor_keys.mask, self.tensor_keys.terminal]
            self._in_keys = _unique_keys(keys)
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    def log_probabilities(self, tensordict: TensorDictBase) -> dict[str, torch.Tensor]:
        """The four ``[B, T, K]`` inputs of the E-step, plus the mask and terminal flags, for a ``[B, T]`` batch.

        Returns a dict with ``log_pi``, ``log_term``, ``log_cont``, ``log_eta``, ``mask``, ``terminal`` and
        ``psi_next`` (the termination probabilities at ``s_{t+1}``).
        """
        keys = self.tensor_keys
        tensordict, mask, current, following = prepare_trajectories(tensordict, list(self.options.in_keys), keys.mask)
        B, T = tensordict.batch_size
        both = self.options(torch.cat([current, following], 0))
        out, out_next = both[:B], both[B:]

        action = tensordict.get(keys.action, None)
        if action is None:
            raise KeyError(f"DDOLoss needs the action taken at {keys.action!r}.")
        log_pi = option_log_probs(
            out,
            action,
            action_space=self.action_space,
            option_logits_key=keys.option_logits,
            option_loc_key=keys.option_loc,
            option_scale_key=keys.option_scale,
            action_key=keys.action,
            mask=mask,
        )
        K = log_pi.shape[-1]
        term_logits = out_next.get(keys.termination_logits)
        if term_logits.shape != (B, T, K):
            raise ValueError(
                f"{keys.termination_logits!r} must have shape [B, T, K] = {(B, T, K)} (K from the control policies), "
                f"got {tuple(term_logits.shape)}."
            )
        log_term = torch.nn.functional.logsigmoid(term_logits)
        log_cont = torch.nn.functional.logsigmoid(-term_logits)
        log_eta = meta_control_log_probs(self.meta_control, tensordict, K, keys.meta_logits, like=log_pi)
        terminal = terminal_flags(tensordict, keys.terminal, mask, self.terminal_at_end)
        return dict(
            log_pi=log_pi,
            log_term=log_term,
            log_cont=log_cont,
            log_eta=log_eta,
            mask=mask,
            terminal=terminal,
            psi_next=torch.sigmoid(term_logits),
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        p = self.log_probabilities(tensordict)
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
        mask = p["mask"]
        n_steps = mask.sum()
        ll = fb.log_likelihood
        if self.reduction == "mean":
            loss = -ll.sum() / n_steps
        elif self.reduction == "sum":
            loss = -ll.sum()
        else:
            loss = -ll
        with torch.no_grad():
            usage = fb.u.sum((0, 1)) / n_steps
            entropy = -(usage * usage.clamp_min(torch.finfo(usage.dtype).tiny).log()).sum()
            out = TensorDict(
                {
                    "loss_ddo": loss,
                    "log_likelihood_per_step": ll.detach().sum() / n_steps,
                    "option_duration": n_steps / fb.v.sum(),
                    "option_entropy": entropy,
                    "termination_probability": (fb.u * p["psi_next"]).sum() / n_steps,
                },
                batch_size=[],
            )
        out.set("loss_ddo", loss)
        return out
