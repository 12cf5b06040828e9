"""HierarchicalDDOLoss: DDO for level d+1 of a hierarchy, over the fixed options of levels 1..d."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from torchrl_options.hierarchy.hierarchy import OptionHierarchy
from torchrl_options.hierarchy.inference import BACKENDS, hierarchical_forward_backward
from torchrl_options.objectives.common import (
    _call_checked,
    BatchChecks,
    check_network_output,
    DDOLossBase,
    terminal_flags,
)

__all__ = ["HierarchicalDDOLoss"]


class HierarchicalDDOLoss(DDOLossBase):
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
        action_space (str): ``"auto"`` (default) or ``"categorical"``: hierarchies are over discrete actions.
        terminal_at_end (bool): read the ``terminal`` key at each row's last valid step; where set, every option on
            the call stack terminates at ``s_T``. Defaults to ``True``.
        reduction (str): ``"mean"`` (per valid step, default), ``"sum"`` or ``"none"`` (``[B]``).
        diagnostics (bool): compute the posterior diagnostics (one more backward pass through the recursion).
            Defaults to ``True``; without them only ``loss_ddo`` and ``log_likelihood_per_step`` are written.
        backend (str): see :func:`~torchrl_options.hierarchy.hierarchical_forward_backward`.

    The loss keeps TorchRL's ``LossModule`` contract (see :class:`~torchrl_options.objectives.DDOLossBase`). The
    lower levels are a registered submodule, ``lower_levels`` (a snapshot :class:`OptionHierarchy` of the levels
    given, sharing their modules): ``.to(device)``, dtype casts and ``state_dict()`` include them, while
    ``parameters()`` and ``reset_parameters_recursive()`` leave them out (they are fixed, not trained).

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
    class _AcceptedKeys(DDOLossBase._AcceptedKeys):
        """Configurable tensordict keys (change them with :meth:`set_keys`).

        Attributes:
            action (NestedKey): the primitive action taken at each step. Defaults to ``"action"``.
            option_logits (NestedKey): written by every level's options, ``[..., K_j, N_j]``. Defaults to
                ``"option_logits"``.
            termination_logits (NestedKey): ``[..., K_j]``, ``psi = sigmoid``. Defaults to ``"termination_logits"``.
            meta_logits (NestedKey): ``[..., K]``, ``eta = softmax``. Defaults to ``"meta_logits"``.
            mask (NestedKey): ``[B, T]`` bool, the valid steps (a prefix of each row); missing means all valid.
                Read with the entries of :attr:`loss_mask_key`. Defaults to ``("collector", "mask")``.
            terminal (NestedKey): ``[B, T]`` bool read at each row's last valid step. Defaults to
                ``("next", "terminated")``.
        """

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

    BACKENDS = BACKENDS
    ACTION_SPACES = ("categorical",)

    lower_levels: OptionHierarchy

    def __init__(
        self,
        options: TensorDictModuleBase,
        lower_levels: OptionHierarchy | Sequence[TensorDictModuleBase],
        meta_control: TensorDictModuleBase | None = None,
        *,
        num_actions: int | None = None,
        action_space: str = "auto",
        terminal_at_end: bool = True,
        reduction: str = "mean",
        diagnostics: bool = True,
        backend: str = "auto",
    ) -> None:
        super().__init__(
            options, meta_control, action_space=action_space, terminal_at_end=terminal_at_end, reduction=reduction,
            diagnostics=diagnostics, backend=backend,
        )  # fmt: skip
        if isinstance(lower_levels, OptionHierarchy):
            if num_actions is not None and num_actions != lower_levels.num_actions:
                raise ValueError(
                    f"num_actions={num_actions} but lower_levels (an OptionHierarchy) has {lower_levels.num_actions}."
                )
            d = lower_levels.num_levels
            # a snapshot: levels appended to the given hierarchy later are not this loss's lower levels
            hierarchy = OptionHierarchy(
                lower_levels.num_actions, list(lower_levels.levels),
                meta_controls=[lower_levels.meta_control(j) for j in range(1, d + 1)],
                num_options=lower_levels.num_options,
            )  # fmt: skip
        else:
            if isinstance(lower_levels, nn.Module) and not isinstance(lower_levels, nn.ModuleList):
                raise TypeError(
                    "lower_levels must be an OptionHierarchy or a sequence of options modules (level 1 first), got "
                    f"{type(lower_levels).__name__}."
                )
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
        # registered: .to(device), casts and state_dict() carry the fixed levels; named_parameters() skips them
        self.lower_levels = hierarchy
        self.num_actions = hierarchy.num_actions

    @property
    def level(self) -> int:
        """The level this loss trains (``d + 1``)."""
        return self.lower_levels.num_levels + 1

    def named_parameters(self, prefix: str = "", recurse: bool = True):
        """The trained parameters (the new level's options and meta-control): the fixed lower levels are left out,
        so that an optimizer over ``loss.parameters()`` does not train them."""
        skip = f"{prefix}.lower_levels." if prefix else "lower_levels."
        for name, param in super().named_parameters(prefix=prefix, recurse=recurse):
            if not name.startswith(skip):
                yield name, param

    def _option_modules(self) -> list[TensorDictModuleBase]:
        return [*self.lower_levels.levels, self.options]

    def _module_name(self, j: int) -> str:
        return "options" if j == self.lower_levels.num_levels else f"lower_levels level {j + 1}"

    def _modules_in_keys(self) -> list[NestedKey]:
        return self._obs_keys()

    def log_probabilities(self, tensordict: TensorDictBase) -> dict:
        """The inputs of :func:`hierarchical_forward_backward` for a ``[B, T]`` batch: ``action``, ``log_pi``,
        ``log_term``, ``log_cont`` (lists, level 1 first, the trained level last), ``log_eta``, ``mask``,
        ``terminal`` and ``psi_next`` (the trained level's termination probabilities at ``s_{t+1}``).

        The batch is checked on the way (one host-device synchronisation for all value checks).

        Raises:
            ValueError: naming the key, for a missing entry, an entry of the wrong shape or dtype, inputs that do
                not fit the networks, NaN/inf at a valid step, an action outside the primitive actions, or network
                outputs of the wrong shape. TypeError for an input that is not a tensordict.
        """
        keys = self.tensor_keys
        checks = BatchChecks()
        tensordict, mask, current, following, action = self._prepare(tensordict, checks)
        B, T = tensordict.batch_size
        if action.shape == (B, T, 1):
            action = action.squeeze(-1)
        if action.shape != (B, T) or action.is_floating_point() or action.is_complex():
            raise ValueError(
                f"{keys.action!r} must hold integer primitive actions of shape {(B, T)}, got {action.dtype} "
                f"{tuple(action.shape)}."
            )
        A = self.num_actions
        bad = ((action < 0) | (action >= A)) & mask
        checks.add(
            bad.any(), lambda: f"{keys.action!r} holds {int(action[bad][0])}, outside the primitive actions [0, {A})."
        )

        modules = self._option_modules()
        sizes = self.lower_levels.action_space_sizes
        both = torch.cat([current.select(*self._obs_keys()), following], 0)
        log_pi, log_term, log_cont = [], [], []
        psi_next = None
        for j, module in enumerate(modules):
            top = j == len(modules) - 1
            name = self._module_name(j)
            inputs = both.select(*module.in_keys).clone(False)
            if top:
                out = self._run("options", inputs)
            else:
                with torch.no_grad():
                    out = _call_checked(name, module, inputs)
            logits = out.get(keys.option_logits, None)
            term_logits = out.get(keys.termination_logits, None)
            if logits is None or logits.ndim != 4 or logits.shape[:2] != (2 * B, T) or logits.shape[-1] != sizes[j]:
                got = "nothing" if logits is None else f"shape {tuple(logits.shape)}"
                raise ValueError(
                    f"{name} wrote {keys.option_logits!r} of {got}; expected "
                    f"[B, T, K_{j + 1}, {sizes[j]}] (level {j + 1} chooses among {sizes[j]} actions)."
                )
            K = logits.shape[2]
            if term_logits is None or term_logits.shape != (2 * B, T, K):
                got = "nothing" if term_logits is None else f"shape {tuple(term_logits.shape)}"
                raise ValueError(f"{name} wrote {keys.termination_logits!r} of {got}; expected [B, T, {K}].")
            lp = logits[:B].log_softmax(-1)
            nxt = term_logits[B:]
            check_network_output(checks, f"{name}' {keys.option_logits!r}", lp, mask)
            check_network_output(checks, f"{name}' {keys.termination_logits!r}", nxt, mask, logits=True)
            log_pi.append(lp)
            log_term.append(nn.functional.logsigmoid(nxt))
            log_cont.append(nn.functional.logsigmoid(-nxt))
            if top:
                psi_next = torch.sigmoid(nxt)
        K = log_pi[-1].shape[2]
        log_eta = self._meta_log_probs(current, K, like=log_pi[-1])
        check_network_output(checks, f"log eta (meta_control's {keys.meta_logits!r})", log_eta, mask)
        terminal = terminal_flags(tensordict, keys.terminal, mask, self.terminal_at_end)
        checks.raise_if_any()
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

    def _posterior(self, p: dict, *, marginals: bool, log_pi=None, log_term=None, log_cont=None, log_eta=None):
        return hierarchical_forward_backward(
            p["action"], p["log_pi"] if log_pi is None else log_pi, p["log_term"] if log_term is None else log_term,
            p["log_cont"] if log_cont is None else log_cont, p["log_eta"] if log_eta is None else log_eta, p["mask"],
            p["terminal"], marginals=marginals, validate=False, backend=self.backend,
        )  # fmt: skip

    def _top_marginals(self, posterior) -> tuple[torch.Tensor, torch.Tensor]:
        return posterior.u[-1], posterior.v[-1]

    def _extra_diagnostics(self, p: dict, posterior, n_steps: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"lower_option_usage": 1.0 - posterior.emitter[..., -1].sum() / n_steps}

    def posterior(self, tensordict: TensorDictBase, *, marginals: bool = True):
        """The :class:`~torchrl_options.hierarchy.HierarchyPosterior` of a ``[B, T]`` batch under the hierarchy
        (lower levels plus the trained one): per-level marginals ``u``, ``v`` and the most likely option at each
        level by ``posterior.most_likely(level)``."""
        return self._posterior(self.log_probabilities(tensordict), marginals=marginals)
