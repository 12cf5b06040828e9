"""DDO's E-step and G-steps with the networks evaluated once per distinct state (exactly the gradient of DDOLoss).

The likelihood of :class:`~torchrl_options.DDOLoss` reads the networks only through ``log pi_h(a_t | s_t)``,
``log psi_h(s_{t+1})``, ``log(1 - psi_h(s_{t+1}))`` and ``log eta(h | s_t)``. Demonstrations in small or discrete
state spaces visit the same states again and again (the paper's four rooms: 1851 distinct observations in 50 x 1000
steps), so the networks can be evaluated on the distinct states and state-action pairs only.

The E-step computes the posterior marginals with :func:`~torchrl_options.forward_backward` and sums them per
distinct state (action pair): the *expected counts* ``N_pi[s, a, h]`` (the sum of ``u_t(h)`` over the steps with
``(s_t, a_t) = (s, a)``), ``N_psi[s, h]`` and ``N_cont[s, h]`` (``u - w`` and ``w`` over the steps with
``s_{t+1} = s``) and ``N_eta[s, h]`` (``v``). A G-step then maximises the expected complete-data log-likelihood

.. math::
    Q(\\theta) = \\sum_{s,a,h} N_\\pi \\log\\pi_h(a|s) + \\sum_{s,h} N_\\psi \\log\\psi_h(s)
                + N_{cont} \\log(1-\\psi_h(s)) + N_\\eta \\log\\eta(h|s),

whose gradient at the parameters of the E-step *is* the gradient of the log-likelihood (Fox et al., 2017,
section 4.2): one G-step per E-step is the paper's Expectation-Gradient; several are a generalised EM (each
G-step that increases ``Q`` increases the likelihood at least as much).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_options.inference import forward_backward
from torchrl_options.objectives.common import BatchChecks, ddo_diagnostics, prepare_trajectories, terminal_flags
from torchrl_options.objectives.ddo import option_log_probs

__all__ = ["TabulatedDDO", "expected_counts", "tabulate_states", "unique_rows"]


def unique_rows(columns: Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of side-by-side columns, compared bit for bit.

    Args:
        columns (sequence of Tensor): tensors with the same leading size N (trailing dimensions are flattened).

    Returns:
        ``(inverse [N], first [U])``: row ``i`` is the distinct row ``inverse[i]``, and ``first[j]`` is the first row
        equal to the distinct row ``j``.

    Examples:
        >>> import torch
        >>> inverse, first = unique_rows([torch.tensor([[0.5, 1.0], [0.0, 1.0], [0.5, 1.0]]), torch.tensor([2, 2, 2])])
        >>> inverse.tolist(), first.tolist()
        ([1, 0, 1], [1, 0])
    """
    n = columns[0].shape[0]
    parts = []
    for c in columns:
        c = c.reshape(n, -1)
        if c.is_floating_point() or c.is_complex():
            # exact: every float dtype converts to float64 without rounding, and the bits are then compared
            c = torch.view_as_real(c).reshape(n, -1) if c.is_complex() else c
            c = c.to(torch.float64).view(torch.int64)
        else:
            c = c.to(torch.int64)
        parts.append(c)
    mat = torch.cat(parts, 1) if len(parts) > 1 else parts[0]
    if mat.shape[1] == 1:
        _, inverse = torch.unique(mat.squeeze(1), return_inverse=True)
    else:
        _, inverse = torch.unique(mat, dim=0, return_inverse=True)
    num = int(inverse.max()) + 1 if n else 0
    first = torch.full((num,), n, dtype=torch.long, device=mat.device)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=mat.device), "amin")
    return inverse, first


def _valid_rows(td: TensorDictBase, keys: Sequence[NestedKey], valid: torch.Tensor) -> TensorDictBase:
    return TensorDict({k: td.get(k)[valid] for k in keys}, batch_size=[int(valid.sum())], device=td.device)


def _scatter(values: torch.Tensor, valid: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    out = torch.zeros(valid.numel(), dtype=torch.long, device=values.device)
    out[valid] = values
    return out.view(shape)


def tabulate_states(
    keys: Sequence[NestedKey],
    mask: torch.Tensor,
    current: TensorDictBase,
    following: TensorDictBase | None = None,
) -> tuple[TensorDictBase, torch.Tensor, torch.Tensor | None]:
    """The distinct states of the valid steps of a ``[B, T]`` batch, at ``s_t`` (and ``s_{t+1}``).

    Args:
        keys (sequence of NestedKey): the entries that make a state (a module's ``in_keys``).
        mask (Tensor): ``[B, T]`` bool, the valid steps.
        current (TensorDictBase): ``[B, T]``, the entries at ``s_t``.
        following (TensorDictBase, optional): ``[B, T]``, the entries at ``s_{t+1}``.

    Returns:
        ``(table, state_index, next_index)``: ``table`` ``[U]`` holds the distinct states (``keys`` only);
        ``state_index`` and ``next_index`` (``None`` without ``following``) are ``[B, T]`` long, the row of
        ``table`` of each step's ``s_t`` and ``s_{t+1}`` (0 on padding).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.tensor([[0.0, 1.0, 0.0], [1.0, 1.0, 2.0]]).unsqueeze(-1)
        >>> td = TensorDict({"x": obs}, [2, 3])
        >>> mask = torch.tensor([[True, True, True], [True, True, False]])
        >>> table, index, _ = tabulate_states(["x"], mask, td)
        >>> table["x"].flatten().tolist(), index.tolist()
        ([0.0, 1.0], [[0, 1, 0], [1, 1, 0]])
    """
    valid = mask.reshape(-1)
    n = int(valid.sum())
    rows = [_valid_rows(current.reshape(-1), keys, valid)]
    if following is not None:
        rows.append(_valid_rows(following.reshape(-1), keys, valid))
    states = torch.cat(rows) if len(rows) > 1 else rows[0]
    inverse, first = unique_rows([states.get(k) for k in keys])
    shape = tuple(mask.shape)
    state_index = _scatter(inverse[:n], valid, shape)
    next_index = _scatter(inverse[n:], valid, shape) if following is not None else None
    return states[first], state_index, next_index


def expected_counts(index: torch.Tensor, counts: torch.Tensor, mask: torch.Tensor, size: int) -> torch.Tensor:
    """Per-step counts ``[B, T, ...]`` summed per table row (``index`` ``[B, T]``): ``[size, ...]``, over the valid
    steps only.

    Examples:
        >>> import torch
        >>> index, mask = torch.tensor([[0, 1, 0]]), torch.tensor([[True, True, False]])
        >>> expected_counts(index, torch.ones(1, 3, 2), mask, 2)
        tensor([[1., 1.],
                [1., 1.]])
    """
    valid = mask.reshape(-1)
    flat = counts.reshape(valid.numel(), *counts.shape[2:])[valid]
    out = torch.zeros(size, *counts.shape[2:], dtype=counts.dtype, device=counts.device)
    return out.index_add_(0, index.reshape(-1)[valid], flat)


class TabulatedDDO:
    """The E-step and G-step objective of :class:`~torchrl_options.DDOLoss` for one batch of trajectories, with the
    networks evaluated once per distinct state (and state-action pair) of the batch.

    :meth:`e_step` returns the diagnostics of :class:`~torchrl_options.DDOLoss` (same keys, same values) and a
    closure returning ``-Q / n_steps``: its gradient at the current parameters equals the gradient of
    ``DDOLoss(batch)["loss_ddo"]`` (to float rounding), and it can be stepped several times (generalised EM). The
    options (and meta-control) must be per-step functions of their ``in_keys``, as the DDO model assumes: they are
    evaluated on a ``[U]`` tensordict of distinct states instead of the ``[B, T]`` batch.

    Args:
        loss_module (DDOLoss): the loss whose options, meta-control, keys and settings are used.
        batch (TensorDictBase): ``[B, T]`` trajectories (mask at the loss's ``mask`` key; missing: all valid).

    Examples:
        >>> import torch
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(4, 50)
        >>> loss = DDOLoss(OptionsMLP(2, 2, 2))
        >>> table = TabulatedDDO(loss, data)
        >>> table.num_states, table.num_pairs  # 10 corridor cells, 2 actions
        (10, 20)
        >>> record, objective = table.e_step()
        >>> torch.allclose(record["loss_ddo"], loss(data)["loss_ddo"])
        True
        >>> objective().backward()
    """

    def __init__(self, loss_module: TensorDictModuleBase, batch: TensorDictBase) -> None:
        if getattr(loss_module, "reduction", "mean") != "mean":
            raise ValueError(f"loss_module must use reduction='mean', got {loss_module.reduction!r}.")
        keys = loss_module.tensor_keys
        self.loss_module = loss_module
        self.options = loss_module.options
        self.meta_control = loss_module.meta_control
        self.action_space = loss_module.action_space
        self.keys = keys
        option_keys = list(self.options.in_keys)
        meta_keys = [] if self.meta_control is None else list(self.meta_control.in_keys)
        # the loss's masks: tensor_keys.mask and its loss_mask_key entries
        batch, mask, current, following = prepare_trajectories(
            batch, option_keys, loss_module.mask_keys, owner=type(loss_module).__name__, current_keys=meta_keys
        )
        B, T = mask.shape
        self._actions_checked = False
        self.mask = mask
        self.terminal = terminal_flags(batch, keys.terminal, mask, loss_module.terminal_at_end)
        self.table, self.state_index, self.next_index = tabulate_states(
            option_keys, mask, current.select(*option_keys), following
        )

        action = batch.get(keys.action, None)
        if action is None:
            raise ValueError(f"DDOLoss needs the action taken at {keys.action!r}, missing from the trajectories.")
        valid = mask.reshape(-1)
        action = action.reshape(B * T, *action.shape[2:])[valid]
        states = self.state_index.reshape(-1)[valid]
        pair_inverse, pair_first = unique_rows([states, action])
        self.pair_state = states[pair_first]
        self.pair_action = action[pair_first]
        self.pair_index = _scatter(pair_inverse, valid, (B, T))

        self.meta_table = self.meta_index = None
        if self.meta_control is not None:
            self.meta_table, self.meta_index, _ = tabulate_states(meta_keys, mask, current.select(*meta_keys))

    def for_loss(self, loss_module: TensorDictModuleBase) -> TabulatedDDO:
        """This tabulation for another loss module with the same keys, input keys and meta-control presence (a
        fresh start of the same model)."""
        same = (
            list(loss_module.options.in_keys) == list(self.options.in_keys)
            and (loss_module.meta_control is None) == (self.meta_control is None)
            and (self.meta_control is None or list(loss_module.meta_control.in_keys) == list(self.meta_control.in_keys))
            and loss_module.tensor_keys == self.keys
            and loss_module.mask_keys == self.loss_module.mask_keys
            and loss_module.terminal_at_end == self.loss_module.terminal_at_end
        )
        if not same:
            raise ValueError("loss_module reads other entries than the one this table was built for.")
        new = object.__new__(TabulatedDDO)
        new.__dict__.update(self.__dict__)
        new.loss_module, new.options, new.meta_control = loss_module, loss_module.options, loss_module.meta_control
        new.action_space = loss_module.action_space
        new._actions_checked = False
        return new

    def subset(self, rows: torch.Tensor) -> TabulatedDDO:
        """The tabulation of the trajectories ``rows`` of this batch (a minibatch): only the states and pairs they
        visit are kept, so that the networks run on those alone.

        Examples:
            >>> from torchrl_options import DDOLoss, OptionsMLP
            >>> from torchrl_options.testing import planted_corridor_demonstrations
            >>> table = TabulatedDDO(DDOLoss(OptionsMLP(2, 2, 2)), planted_corridor_demonstrations(4, 50))
            >>> table.subset(torch.tensor([2, 0])).mask.shape
            torch.Size([2, 50])
        """
        new = object.__new__(TabulatedDDO)
        new.__dict__.update(self.__dict__)
        mask = self.mask[rows]
        new.mask, new.terminal = mask, self.terminal[rows]

        def compact(index_lists, table_size):
            used = torch.unique(torch.cat([ix[rows][mask] for ix in index_lists]))
            remap = torch.zeros(table_size, dtype=torch.long, device=used.device)
            remap[used] = torch.arange(used.numel(), device=used.device)
            return used, [remap[ix[rows]] for ix in index_lists]

        used, (new.state_index, new.next_index) = compact([self.state_index, self.next_index], self.num_states)
        new.table = self.table[used]
        pairs, (new.pair_index,) = compact([self.pair_index], self.num_pairs)
        remap = torch.zeros(self.num_states, dtype=torch.long, device=used.device)
        remap[used] = torch.arange(used.numel(), device=used.device)
        new.pair_state = remap[self.pair_state[pairs]]
        new.pair_action = self.pair_action[pairs]
        if self.meta_table is not None:
            meta_used, (new.meta_index,) = compact([self.meta_index], self.meta_table.batch_size[0])
            new.meta_table = self.meta_table[meta_used]
        return new

    @property
    def num_steps(self) -> torch.Tensor:
        """The valid steps of the batch (a 0-d tensor)."""
        return self.mask.sum()

    @property
    def num_states(self) -> int:
        """Distinct states (at ``s_t`` or ``s_{t+1}``) the options are evaluated on."""
        return self.table.batch_size[0]

    @property
    def num_pairs(self) -> int:
        """Distinct (state, action) pairs of the valid steps."""
        return self.pair_state.shape[0]

    def _tables(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``log pi`` per pair ``[P, K]``, termination logits per state ``[U, K]``, meta-control logits ``[M, K]``."""
        keys = self.keys
        out = self.options(self.table.clone(False))
        log_pi = option_log_probs(
            out[self.pair_state],
            self.pair_action,
            action_space=self.action_space,
            option_logits_key=keys.option_logits,
            option_loc_key=keys.option_loc,
            option_scale_key=keys.option_scale,
            action_key=keys.action,
            # the actions are checked once per batch: later calls record the checks and drop them
            checks=BatchChecks() if self._actions_checked else None,
        )
        self._actions_checked = True
        K = log_pi.shape[-1]
        term_logits = out.get(keys.termination_logits)
        if term_logits.shape != (self.num_states, K):
            raise ValueError(
                f"{keys.termination_logits!r} must have shape [..., K] with K = {K} (from the control policies), got "
                f"{tuple(term_logits.shape)} for a batch of {self.num_states} states."
            )
        meta = None
        if self.meta_control is not None:
            meta = self.meta_control(self.meta_table.clone(False)).get(keys.meta_logits)
            if meta.shape != (self.meta_table.batch_size[0], K):
                raise ValueError(
                    f"{keys.meta_logits!r} must have shape [..., K] with K = {K}: the meta-control must choose among "
                    f"the {K} options, got {tuple(meta.shape)}."
                )
        return log_pi, term_logits, meta

    def e_step(self) -> tuple[dict[str, torch.Tensor], Callable[[], torch.Tensor]]:
        """Posterior of the batch under the current parameters.

        Returns:
            ``(record, objective)``: ``record`` holds :class:`~torchrl_options.DDOLoss`'s outputs (detached) for the
            current parameters; ``objective()`` evaluates ``-Q / n_steps`` under the parameters at call time
            (differentiable), ``Q`` with this E-step's expected counts.
        """
        B, T = self.mask.shape
        with torch.no_grad():
            log_pi_pairs, term_logits, meta_logits = self._tables()
        K = log_pi_pairs.shape[-1]
        log_pi = log_pi_pairs[self.pair_index].requires_grad_()
        log_term_states = torch.nn.functional.logsigmoid(term_logits)
        log_cont_states = torch.nn.functional.logsigmoid(-term_logits)
        log_term = log_term_states[self.next_index].requires_grad_()
        log_cont = log_cont_states[self.next_index].requires_grad_()
        if meta_logits is None:
            log_eta = torch.full((B, T, K), -math.log(K), dtype=log_pi.dtype, device=log_pi.device)
        else:
            log_eta = meta_logits.log_softmax(-1)[self.meta_index]
        log_eta.requires_grad_()
        with torch.enable_grad():
            fb = forward_backward(log_pi, log_term, log_cont, log_eta, self.mask, self.terminal)
            g_pi, g_term, g_cont, g_eta = torch.autograd.grad(fb.log_likelihood.sum(), [log_pi, log_term, log_cont, log_eta])
        n = self.num_steps
        ll = fb.log_likelihood.detach().sum()
        psi_next = torch.sigmoid(term_logits)[self.next_index]
        record = {"loss_ddo": -ll / n, "log_likelihood_per_step": ll / n, **ddo_diagnostics(fb.u, fb.v, psi_next, n)}

        mask = self.mask
        n_pi = expected_counts(self.pair_index, g_pi, mask, self.num_pairs)
        n_term = expected_counts(self.next_index, g_term, mask, self.num_states)
        n_cont = expected_counts(self.next_index, g_cont, mask, self.num_states)
        n_eta = None
        if meta_logits is not None:
            n_eta = expected_counts(self.meta_index, g_eta, mask, self.meta_table.batch_size[0])

        def objective() -> torch.Tensor:
            log_pi_pairs, term_logits, meta_logits = self._tables()
            # zero counts times a -inf log-probability (an option that cannot take the action) contribute nothing
            q = torch.where(n_pi != 0, n_pi * log_pi_pairs, 0.0).sum()
            q = q + (n_term * torch.nn.functional.logsigmoid(term_logits)).sum()
            q = q + (n_cont * torch.nn.functional.logsigmoid(-term_logits)).sum()
            if n_eta is not None:
                q = q + (n_eta * meta_logits.log_softmax(-1)).sum()
            return -q / n

        return record, objective
