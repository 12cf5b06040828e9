"""DDOLoss: the negative log-likelihood of demonstrations under K options, trained by Expectation-Gradient."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.inference import forward_backward
from torchrl_options.inference.forward_backward import BACKENDS
from torchrl_options.objectives.common import (
    BatchChecks,
    check_network_output,
    DDOLossBase,
    meta_control_log_probs,
    prepare_trajectories,
    terminal_flags,
)

__all__ = ["DDOLoss", "meta_control_log_probs", "option_log_probs", "prepare_trajectories", "terminal_flags"]


def _key_name(key: NestedKey) -> str:
    return repr(key)


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
    checks: BatchChecks | None = None,
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
        checks (BatchChecks, optional): where to record the value checks of the actions (read back by the caller
            with its own, in one synchronisation); ``None``: checked here.

    Raises:
        ValueError: naming ``action_key`` for actions outside the action space or of the wrong shape or dtype, and
            naming the output key when the options wrote neither discrete nor Gaussian outputs.

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
    if not isinstance(action, torch.Tensor):
        raise TypeError(f"{_key_name(action_key)} must be a tensor of actions, got {type(action).__name__}.")
    if mask is None:
        mask = torch.ones(batch, dtype=torch.bool, device=action.device)
    own_checks = checks is None
    checks = BatchChecks() if own_checks else checks
    if action_space == "auto":
        if option_logits_key in outputs.keys(include_nested=True):
            action_space = "categorical"
        elif option_loc_key in outputs.keys(include_nested=True):
            action_space = "continuous"
        else:
            raise ValueError(
                f"the options module wrote neither {option_logits_key!r} (discrete options) nor {option_loc_key!r} "
                f"(Gaussian options); it wrote {sorted(map(str, outputs.keys(True, True)))}."
            )
    if action_space == "categorical":
        logits = outputs.get(option_logits_key, None)
        if logits is None:
            raise ValueError(f"the options module did not write {option_logits_key!r} (discrete options).")
        A = logits.shape[-1]
        if logits.ndim != len(batch) + 2 or logits.shape[:-2] != batch:
            raise ValueError(
                f"{option_logits_key!r} must have shape [*batch, K, A] with batch {tuple(batch)}, got {tuple(logits.shape)}."
            )
        if action.shape == (*batch, A) and A > 1:
            # one-hot actions (TorchRL's OneHot spec)
            one_hot = (((action == 0) | (action == 1)).all(-1) & (action.sum(-1) == 1)) | ~mask
            checks.add(
                ~one_hot.all(),
                lambda: f"{_key_name(action_key)}: one-hot actions must have exactly one 1 per valid step.",
            )
            index = torch.where(mask, action.long().argmax(-1), 0)
        else:
            if action.shape == (*batch, 1):
                action = action.squeeze(-1)
            if action.shape != batch or action.is_floating_point() or action.is_complex():
                raise ValueError(
                    f"{_key_name(action_key)} must hold integer actions of shape {tuple(batch)} (or with a trailing "
                    f"1), or one-hot actions of shape {(*batch, A)}, got {action.dtype} {tuple(action.shape)}."
                )
            action = action.long()
            bad = ((action < 0) | (action >= A)) & mask
            checks.add(
                bad.any(),
                lambda: (
                    f"{_key_name(action_key)} holds {action[bad][0].item()}, outside the options' action space "
                    f"[0, {A}) given by {option_logits_key!r}."
                ),
            )
            # clamped: an out-of-range action fails the check above before anything reads this
            index = torch.where(mask, action, 0).clamp(0, A - 1)
        if own_checks:
            checks.raise_if_any()
        logp = logits.log_softmax(-1)
        return logp.gather(-1, index[..., None, None].expand(*batch, logp.shape[-2], 1)).squeeze(-1)
    if action_space == "continuous":
        loc, scale = outputs.get(option_loc_key, None), outputs.get(option_scale_key, None)
        if loc is None or scale is None:
            raise ValueError(
                f"Gaussian options must write {option_loc_key!r} and {option_scale_key!r}; the options module wrote "
                f"{sorted(map(str, outputs.keys(True, True)))}."
            )
        D = loc.shape[-1]
        if action.shape != (*batch, D) or not action.is_floating_point():
            raise ValueError(
                f"{_key_name(action_key)} must be a float tensor of shape {(*batch, D)} for Gaussian options of "
                f"dimension {D}, got {action.dtype} {tuple(action.shape)}."
            )
        action = torch.where(mask.unsqueeze(-1), action.to(loc.dtype), 0.0)
        checks.add(
            ~torch.isfinite(action).all(), lambda: f"{_key_name(action_key)} holds NaN or inf at a valid step."
        )
        if own_checks:
            checks.raise_if_any()
        dist = torch.distributions.Normal(loc, scale, validate_args=False)
        return dist.log_prob(action.unsqueeze(-2)).sum(-1)
    raise ValueError(f"action_space must be 'auto', 'categorical' or 'continuous', got {action_space!r}.")


class DDOLoss(DDOLossBase):
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
        diagnostics (bool): write the diagnostics below (default ``True``); otherwise only ``loss_ddo`` and
            ``log_likelihood_per_step``.
        backend (str): the backend of :func:`~torchrl_options.forward_backward`. Defaults to ``"auto"``.

    The diagnostics written next to ``loss_ddo`` are detached: ``log_likelihood_per_step``, ``option_duration``
    (valid steps per expected option start), ``option_entropy`` (entropy, in nats, of the posterior option usage)
    and ``termination_probability`` (posterior mean of ``psi`` of the active option).

    The loss keeps TorchRL's ``LossModule`` contract (see :class:`~torchrl_options.objectives.DDOLossBase`): the
    networks are registered with ``convert_to_functional`` (``options_params``, ``meta_control_params``), padding
    is excluded by ``tensor_keys.mask`` and :attr:`loss_mask_key`, and the loss takes keyword tensors too.

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

        TorchRL's masking convention and keyword call:

        >>> data["my", "valid"] = torch.arange(T).expand(B, T) < 15  # the last 5 steps are padding
        >>> loss.loss_mask_key = ("my", "valid")
        >>> loss_ddo, *diagnostics = loss(
        ...     observation=data["observation"], expert_action=data["expert_action"],
        ...     next_observation=data["next", "observation"], my_valid=data["my", "valid"])
        >>> torch.allclose(loss_ddo, loss(data[:, :15])["loss_ddo"])
        True
    """

    @dataclass
    class _AcceptedKeys(DDOLossBase._AcceptedKeys):
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
            option_loc (NestedKey): written by Gaussian options, ``[..., K, D]``. Defaults to ``"option_loc"``.
            option_scale (NestedKey): written by Gaussian options, ``[..., K, D]``. Defaults to ``"option_scale"``.
        """

        option_loc: NestedKey = "option_loc"
        option_scale: NestedKey = "option_scale"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_ddo", "log_likelihood_per_step", "option_duration", "option_entropy", "termination_probability"]

    BACKENDS = BACKENDS
    ACTION_SPACES = ("categorical", "continuous")

    def log_probabilities(self, tensordict: TensorDictBase) -> dict[str, torch.Tensor]:
        """The four ``[B, T, K]`` inputs of the E-step, plus the mask and terminal flags, for a ``[B, T]`` batch.

        The batch is checked on the way (one host-device synchronisation for all value checks).

        Returns a dict with ``log_pi``, ``log_term``, ``log_cont``, ``log_eta``, ``mask``, ``terminal`` and
        ``psi_next`` (the termination probabilities at ``s_{t+1}``).

        Raises:
            ValueError: naming the key, for a missing entry, an entry of the wrong shape or dtype, inputs that do
                not fit the networks, NaN/inf at a valid step, an action outside the action space, or network
                outputs of the wrong shape. TypeError for an input that is not a tensordict.
        """
        keys = self.tensor_keys
        checks = BatchChecks()
        tensordict, mask, current, following, action = self._prepare(tensordict, checks)
        B, T = tensordict.batch_size
        both = self._run("options", torch.cat([current.select(*self.options.in_keys), following], 0))
        out, out_next = both[:B], both[B:]
        log_pi = option_log_probs(
            out,
            action,
            action_space=self.action_space,
            option_logits_key=keys.option_logits,
            option_loc_key=keys.option_loc,
            option_scale_key=keys.option_scale,
            action_key=keys.action,
            mask=mask,
            checks=checks,
        )
        K = log_pi.shape[-1]
        term_logits = out_next.get(keys.termination_logits, None)
        if term_logits is None or term_logits.shape != (B, T, K):
            got = "nothing" if term_logits is None else tuple(term_logits.shape)
            raise ValueError(
                f"{keys.termination_logits!r} must have shape [B, T, K] = {(B, T, K)} (K from the control policies), "
                f"got {got}."
            )
        log_eta = self._meta_log_probs(current, K, like=log_pi)
        terminal = terminal_flags(tensordict, keys.terminal, mask, self.terminal_at_end)
        check_network_output(checks, "log pi (from the options' outputs)", log_pi, mask)
        check_network_output(checks, f"options' {keys.termination_logits!r}", term_logits, mask, logits=True)
        check_network_output(checks, f"log eta (meta_control's {keys.meta_logits!r})", log_eta, mask)
        checks.raise_if_any()
        return dict(
            log_pi=log_pi,
            log_term=torch.nn.functional.logsigmoid(term_logits),
            log_cont=torch.nn.functional.logsigmoid(-term_logits),
            log_eta=log_eta,
            mask=mask,
            terminal=terminal,
            psi_next=torch.sigmoid(term_logits),
        )

    def _posterior(self, p: dict[str, torch.Tensor], *, marginals: bool):
        return forward_backward(
            p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"], validate=False,
            backend=self.backend,
        )  # fmt: skip

    def _top_marginals(self, posterior) -> tuple[torch.Tensor, torch.Tensor]:
        return posterior.u, posterior.v
