"""HierarchicalDDOLoss: DDO for level d+1 of a hierarchy, over the fixed options of levels 1..d."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives.common import LossModule

from torchrl_options.hierarchy.hierarchy import OptionHierarchy
from torchrl_options.objectives.ddo import meta_control_log_probs, prepare_trajectories, terminal_flags
from torchrl_options.hierarchy.inference import BACKENDS, hierarchical_forward_backward

__all__ = ["HierarchicalDDOLoss"]


def _next_key(key: NestedKey) -> NestedKey:
    return ("next", key) if isinstance(key, str) else ("next", *key)


class HierarchicalDDOLoss(LossModule):
    r"""The DDO loss of level ``d + 1`` over fixed lower levels: negative exact log-likelihood of demonstrations.

    Deeper hierarchies (Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options",
    arXiv:1703.08294, 2017, section 4.3) are discovered level by level: the options of level ``d + 1`` choose
    among the primitive actions and the options of levels ``1..d`` (already discovered, fixed), which run
    call-and-return, and a meta-control ``eta_{d+1}`` (uniform: H2u; learned: H2s) picks level-``d+1`` options.
    The likelihood

    .. math::
        L[\theta; \xi] = \log \sum_\zeta P_\theta(\zeta, \xi)

    sums over every latent *call-stack* history ``zeta`` of the joint hierarchy, exactly, by
    :func:`~torchrl_options.hierarchy.hierarchical_forward_backward` (linear in T). Its gradient with respect
    to the new level's parameters is the Expectation-Gradient: the posterior expected counts of each choice
    (``pi_h(c | s_t)``, ``c`` a primitive action or a lower option), termination (``psi_h``, ``1 - psi_h``) and
    meta-control choice, times the gradients of their log-probabilities. The lower levels are evaluated under
    ``torch.no_grad``: only the new level (and a learned meta-control) is trained. With no lower level this is
    :class:`~torchrl_options.DDOLoss`.

    Args:
        options (TensorDictModuleBase): the new level's options, writing ``option_logits``
            ``[..., K, A + K_1 + ... + K_d]`` and ``termination_logits`` ``[..., K]`` (an
            :class:`~torchrl_options.OptionsMLP` with ``num_actions = A + K_1 + ... + K_d``).
        lower_levels (OptionHierarchy or sequence of modules): the fixed levels ``1..d``, bottom-up.
        meta_control (TensorDictModuleBase, optional): writes ``meta_logits`` ``[..., K]``; ``None`` fixes it
            uniform.

    Keyword Args:
        num_actions (int, optional): A; defaults to the hierarchy's, or to the level-1 module's ``num_actions``.
        terminal_at_end (bool): read the ``terminal`` key at each row's last valid step; where set, every option on
            the call stack terminates at ``s_T``. Defaults to ``True``.
        reduction (str): ``"mean"`` (per valid step, default), ``"sum"`` or ``"none"`` (``[B]``).
        diagnostics (bool): compute the posterior diagnostics (one more backward pass through the recursion).
            Defaults to ``True``; without them only ``loss_ddo`` and ``log_likelihood_per_step`` are written.
        backend (str): see :func:`~torchrl_options.hierarchy.hierarchical_forward_backward`.

    Outputs: ``loss_ddo`` and the detached ``log_likelihood_per_step``, ``option_duration`` (valid steps per
    expected start of a new-level option), ``option_entropy`` (of the posterior usage of the new level's options),
    ``termination_probability`` (posterior mean of ``psi`` of the active new-level option at ``s_{t+1}``) and
    ``lower_option_usage`` (posterior fraction of steps where the new level's option acts through a lower-level
    option rather than choosing the primitive action itself).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.hierarchy import HierarchicalDDOLoss, OptionHierarchy
        >>> B, T, A, K1, K2 = 4, 12, 3, 2, 2
        >>> data = TensorDict({
        ...     "observation": torch.randn(B, T, 5),
        ...     "action": torch.randint(A, (B, T)),
        ...     "next": {"observation": torch.randn(B, T, 5)},
        ...     ("collector", "mask"): torch.ones(B, T, dtype=torch.bool),
        ... }, [B, T])
        >>> lower = OptionHierarchy(A, [OptionsMLP(5, A, K1)])
        >>> loss = HierarchicalDDOLoss(OptionsMLP(5, A + K1, K2), lower)
        >>> out = loss(data)
        >>> out["loss_ddo"].backward()
        >>> sorted(out.keys())  # doctest: +NORMALIZE_WHITESPACE
        ['log_likelihood_per_step', 'loss_ddo', 'lower_option_usage', 'option_duration', 'option_entropy',
         'termination_probability']
        >>> loss.set_keys(action="expert_action")
        >>> data.rename_key_("action", "expert_action")["expert_action"].shape
        torch.Size([4, 12])
        >>> loss(data)["loss_ddo"].shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (change them with :meth:`set_keys`).

        Attributes:
            action (NestedKey): the primitive action taken at each step. Defaults to ``"action"``.
            option_logits (NestedKey): written by every level's options, ``[..., K_j, N_j]``. Defaults to
                ``"option_logits"``.
            termination_logits (NestedKey): ``[..., K_j]``, ``psi = sigmoid``. Defaults to ``"termination_logits"``.
            meta_logits (NestedKey): ``[..., K]``, ``eta = softmax``. Defaults to ``"meta_logits"``.
            mask (NestedKey): ``[B, T]`` bool, the valid steps (a prefix of each row); missing means all valid.
                Defaults to ``("collector", "mask")``.
            terminal (NestedKey): ``[B, T]`` bool read at each row's last valid step. Defaults to
                ``("next", "terminated")``.
        """

        action: NestedKey = "action"
        option_logits: NestedKey = "option_logits"
        termination_logits: NestedKey = "termination_logits"
        meta_logits: NestedKey = "meta_logits"
        mask: NestedKey = ("collector", "mask")
        terminal: NestedKey = ("next", "terminated")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_ddo",
        "log_likelihood_per_step",
        "option_duration",
        "option_entropy",
        "termination_probability",
        "lower_option_usage",
    ]

    def __init__(
        self,
        options: TensorDictModuleBase,
        lower_levels: OptionHierarchy | Sequence[TensorDictModuleBase],
        meta_control: TensorDictModuleBase | None = None,
        *,
        num_actions: int | None = None,
        terminal_at_end: bool = True,
        reduction: str = "mean",
        diagnostics: bool = True,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}.")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}.")
        if isinstance(lower_levels, OptionHierarchy):
            if num_actions is not None and num_actions != lower_levels.num_actions:
                raise ValueError(
                    f"num_actions={num_actions} but lower_levels (an OptionHierarchy) has {lower_levels.num_actions}."
                )
            hierarchy = lower_levels
        else:
            lower = list(lower_levels)
            if num_actions is None:
                num_actions = getattr(lower[0], "num_actions", None) if lower else getattr(options, "num_actions", None)
                if num_actions is None:
                    raise ValueError("num_actions (A) is needed: the level-1 module has no num_actions attribute.")
            try:
                hierarchy = OptionHierarchy(num_actions, lower)
            except ValueError as err:
                raise ValueError(f"lower_levels: {err}") from None
        level = hierarchy.num_levels + 1
        expected = hierarchy.action_space_sizes[-1]
        n = getattr(options, "num_actions", None)
        if n is not None and n != expected:
            formula = " + ".join(["A"] + [f"K{i}" for i in range(1, level)])
            values = " + ".join(str(v) for v in [hierarchy.num_actions, *hierarchy.num_options])
            raise ValueError(
                f"options has num_actions={n}, but level-{level} options choose among {formula} = {values} = "
                f"{expected} actions (primitive actions and the options of levels 1..{level - 1})."
            )
        k_opt = getattr(options, "num_options", None)
        k_meta = getattr(meta_control, "num_options", None)
        if k_opt is not None and k_meta is not None and k_opt != k_meta:
            raise ValueError(f"options has num_options={k_opt} but meta_control has num_options={k_meta}: they must match.")
        self.options = options
        self.meta_control = meta_control
        # not registered as submodules: the lower levels are fixed and their parameters are not the loss's
        self.__dict__["lower_levels"] = hierarchy
        self.num_actions = hierarchy.num_actions
        self.terminal_at_end = terminal_at_end
        self.reduction = reduction
        self.diagnostics = diagnostics
        self.backend = backend
        self._in_keys = None

    @property
    def level(self) -> int:
        """The level this loss trains (``d + 1``)."""
        return self.lower_levels.num_levels + 1

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def set_keys(self, **kwargs) -> None:
        super().set_keys(**kwargs)
        self._in_keys = None

    def _modules_in_keys(self) -> list[NestedKey]:
        keys = []
        for m in [*self.lower_levels.levels, self.options]:
            for k in m.in_keys:
                if k not in keys:
                    keys.append(k)
        return keys

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            obs = self._modules_in_keys()
            keys = list(obs)
            if self.meta_control is not None:
                keys += [k for k in self.meta_control.in_keys if k not in keys]
            keys += [_next_key(k) for k in obs]
            for k in (self.tensor_keys.action, self.tensor_keys.mask, self.tensor_keys.terminal):
                if k not in keys:
                    keys.append(k)
            self._in_keys = keys
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    def log_probabilities(self, tensordict: TensorDictBase) -> dict:
        """The inputs of :func:`hierarchical_forward_backward` for a ``[B, T]`` batch: ``action``, ``log_pi``,
        ``log_term``, ``log_cont`` (lists, level 1 first, the trained level last), ``log_eta``, ``mask``,
        ``terminal`` and ``psi_next`` (the trained level's termination probabilities at ``s_{t+1}``)."""
        keys = self.tensor_keys
        tensordict, mask, current, following = prepare_trajectories(
            tensordict, self._modules_in_keys(), keys.mask, owner="HierarchicalDDOLoss"
        )
        B, T = tensordict.batch_size
        both = torch.cat([current, following], 0)

        action = tensordict.get(keys.action, None)
        if action is None:
            raise KeyError(f"HierarchicalDDOLoss needs the primitive action taken at {keys.action!r}.")
        if action.shape == (B, T, 1):
            action = action.squeeze(-1)
        if action.shape != (B, T) or action.is_floating_point():
            raise ValueError(
                f"{keys.action!r} must hold integer primitive actions of shape {(B, T)}, got {action.dtype} "
                f"{tuple(action.shape)}."
            )
        A = self.num_actions
        bad = ((action < 0) | (action >= A)) & mask
        if bad.any():
            raise ValueError(f"{keys.action!r} holds {int(action[bad][0])}, outside the primitive actions [0, {A}).")

        modules = [*self.lower_levels.levels, self.options]
        sizes = self.lower_levels.action_space_sizes
        log_pi, log_term, log_cont = [], [], []
        psi_next = None
        for j, module in enumerate(modules):
            top = j == len(modules) - 1
            with torch.set_grad_enabled(top and torch.is_grad_enabled()):
                out = module(both.select(*module.in_keys).clone(False))
            logits = out.get(keys.option_logits)
            term_logits = out.get(keys.termination_logits)
            name = "options" if top else f"lower_levels level {j + 1}"
            if logits.ndim != 4 or logits.shape[:2] != (2 * B, T) or logits.shape[-1] != sizes[j]:
                raise ValueError(
                    f"{name} wrote {keys.option_logits!r} of shape {tuple(logits.shape)}; expected "
                    f"[B, T, K_{j + 1}, {sizes[j]}] (level {j + 1} chooses among {sizes[j]} actions)."
                )
            K = logits.shape[2]
            if term_logits.shape != (2 * B, T, K):
                raise ValueError(
                    f"{name} wrote {keys.termination_logits!r} of shape {tuple(term_logits.shape)}; expected "
                    f"[B, T, {K}]."
                )
            log_pi.append(logits[:B].log_softmax(-1))
            nxt = term_logits[B:]
            log_term.append(nn.functional.logsigmoid(nxt))
            log_cont.append(nn.functional.logsigmoid(-nxt))
            if top:
                psi_next = torch.sigmoid(nxt)
        K = log_pi[-1].shape[2]
        log_eta = meta_control_log_probs(self.meta_control, tensordict, K, keys.meta_logits, like=log_pi[-1])
        terminal = terminal_flags(tensordict, keys.terminal, mask, self.terminal_at_end)
        return dict(
            action=torch.where(mask, action, 0).long(),
            log_pi=log_pi,
            log_term=log_term,
            log_cont=log_cont,
            log_eta=log_eta,
            mask=mask,
            terminal=terminal,
            psi_next=psi_next,
        )

    def posterior(self, tensordict: TensorDictBase, *, marginals: bool = True):
        """The :class:`~torchrl_options.hierarchy.HierarchyPosterior` of a ``[B, T]`` batch under the hierarchy
        (lower levels plus the trained one): per-level marginals ``u``, ``v`` and the most likely option at each
        level by ``posterior.most_likely(level)``."""
        p = self.log_probabilities(tensordict)
        return hierarchical_forward_backward(
            p["action"], p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"],
            marginals=marginals, backend=self.backend,
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        p = self.log_probabilities(tensordict)
        post = hierarchical_forward_backward(
            p["action"], p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"],
            marginals=self.diagnostics, validate=False, backend=self.backend,
        )
        mask = p["mask"]
        n_steps = mask.sum()
        ll = post.log_likelihood
        if self.reduction == "mean":
            loss = -ll.sum() / n_steps
        elif self.reduction == "sum":
            loss = -ll.sum()
        else:
            loss = -ll
        out = TensorDict({"log_likelihood_per_step": ll.detach().sum() / n_steps}, batch_size=[])
        if self.diagnostics:
            with torch.no_grad():
                u, v = post.u[-1], post.v[-1]
                usage = u.sum((0, 1)) / n_steps
                entropy = -(usage * usage.clamp_min(torch.finfo(usage.dtype).tiny).log()).sum()
                out.update(
                    {
                        "option_duration": n_steps / v.sum(),
                        "option_entropy": entropy,
                        "termination_probability": (u * p["psi_next"]).sum() / n_steps,
                        "lower_option_usage": 1.0 - post.emitter[..., -1].sum() / n_steps,
                    }
                )
        out.set("loss_ddo", loss)
        return out
