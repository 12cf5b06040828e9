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

from torchrl_options.discovery.usage_floor import UsageFloor
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
    if isinstance(columns, torch.Tensor) or not isinstance(columns, Sequence) or not columns:
        raise ValueError("unique_rows: columns must be a non-empty sequence of tensors.")
    for i, c in enumerate(columns):
        if not isinstance(c, torch.Tensor) or c.ndim == 0:
            raise TypeError(f"unique_rows: columns[{i}] must be a tensor with a leading dimension N, got {type(c).__name__}.")
    n = columns[0].shape[0]
    if any(c.shape[0] != n for c in columns):
        raise ValueError(f"unique_rows: the columns must share their leading size N, got {[c.shape[0] for c in columns]}.")
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
    inverse = _lexicographic_ranks(mat)
    num = int(inverse.max()) + 1 if n else 0
    first = torch.full((num,), n, dtype=torch.long, device=mat.device)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=mat.device), "amin")
    return inverse, first


def _lexicographic_ranks(mat: torch.Tensor) -> torch.Tensor:
    """The rank of each row of an int64 ``[N, D]`` matrix among its distinct rows in lexicographic order: the
    ``inverse`` of ``torch.unique(mat, dim=0, return_inverse=True)``, computed with one-dimensional ``unique`` calls
    (columns ranked one at a time and folded into the running rank, which stays below ``N``), many times faster than
    ``unique(dim=0)`` on CPU.

    Examples:
        >>> import torch
        >>> mat = torch.tensor([[2, 1], [0, 5], [2, 1], [0, -3]])
        >>> _lexicographic_ranks(mat).tolist() == torch.unique(mat, dim=0, return_inverse=True)[1].tolist()
        True
    """
    _, rank = torch.unique(mat[:, 0], return_inverse=True)
    for d in range(1, mat.shape[1]):
        _, column = torch.unique(mat[:, d], return_inverse=True)
        # both ranks are below N <= 2**31, so the pair's key fits an int64 and orders as (rank, column) does
        key = rank * (int(column.max()) + 1 if column.numel() else 1) + column
        _, rank = torch.unique(key, return_inverse=True)
    return rank


def _changed(params: Sequence[torch.Tensor], snapshot: Sequence[torch.Tensor]) -> bool:
    """Whether any parameter differs from its snapshot (as ``not torch.equal`` would say), in one host
    synchronisation rather than one per parameter."""
    if not params:
        return False
    return bool(torch.stack([torch.ne(p.detach(), s).any() for p, s in zip(params, snapshot)]).any())


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
        if not hasattr(loss_module, "tensor_keys") or not hasattr(loss_module, "options"):
            raise TypeError(f"TabulatedDDO: loss_module must be a DDOLoss, got {type(loss_module).__name__}.")
        if not isinstance(batch, TensorDictBase):
            raise TypeError(f"TabulatedDDO: batch must be a [B, T] TensorDict of trajectories, got {type(batch).__name__}.")
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
        self._categorical, self._pair_action_index = False, None  # set by the first forward pass (_forward)
        self._flat = self._next_used = None  # per-batch indices, computed when first needed
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
        if self._pair_action_index is not None:
            new._pair_action_index = self._pair_action_index[pairs]
        new._flat = new._next_used = None
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

    def _flat_indices(self, K: int) -> dict:
        """Per-batch indices, computed once (per K): ``steps``, the flat positions of the valid steps (``None`` when
        all are valid); ``pair``, ``next``, ``meta``, the flat positions ``row * K + h`` in the ``[rows, K]`` tables
        of the pairs, states and meta-control states of the valid steps' ``K`` entries; ``term_steps``, the flat
        positions of the steps whose ``log_term`` enters the likelihood (all valid steps but each row's last, unless
        the row is terminal), and ``next_term``, their entries in the state table."""
        if self._flat is None or self._flat["K"] != K:
            valid = self.mask.reshape(-1)
            steps = None if bool(valid.all()) else valid.nonzero().squeeze(1)
            options = torch.arange(K, device=valid.device)

            def entries(index):
                index = index.reshape(-1)
                index = index if steps is None else index[steps]
                return (index.unsqueeze(1) * K + options).reshape(-1)

            lengths = self.mask.sum(1, keepdim=True)
            t = torch.arange(self.mask.shape[1], device=valid.device)
            term_steps = ((t < lengths - 1) | ((t == lengths - 1) & self.terminal.unsqueeze(1))).reshape(-1)
            term_steps = term_steps.nonzero().squeeze(1)
            next_term = (self.next_index.reshape(-1)[term_steps].unsqueeze(1) * K + options).reshape(-1)
            self._flat = dict(
                K=K, steps=steps, pair=entries(self.pair_index), next=entries(self.next_index),
                meta=None if self.meta_index is None else entries(self.meta_index), term_steps=term_steps,
                next_term=next_term,
            )  # fmt: skip
        return self._flat

    def _forward(self) -> tuple[tuple[torch.Tensor, torch.Tensor] | torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The networks on the distinct states: ``(pi, term_logits [U, K], meta_logits [M, K] or None)``.

        ``pi`` is ``(logits [U, K, A], logsumexp(logits) [U, K])`` for discrete options (the log-probability of a
        pair is ``logits[s, :, a] - logsumexp[s]``), the ``[P, K]`` log-probabilities of the pairs for Gaussian ones.
        """
        keys = self.keys
        out = self.options(self.table.clone(False))
        if not self._actions_checked:
            # the actions (and the outputs' layout) are checked once per batch, by the loss's own reading of them
            log_pi = option_log_probs(
                out[self.pair_state], self.pair_action, action_space=self.action_space,
                option_logits_key=keys.option_logits, option_loc_key=keys.option_loc,
                option_scale_key=keys.option_scale, action_key=keys.action,
            )  # fmt: skip
            self._actions_checked = True
            self._categorical = keys.option_logits in out.keys(include_nested=True) and (
                self.action_space in ("auto", "categorical")
            )
            if self._categorical:
                A, action = out.get(keys.option_logits).shape[-1], self.pair_action
                # option_log_probs's reading: one-hot [P, A] (A > 1), or integers [P] or [P, 1]
                onehot = action.shape == (self.num_pairs, A) and A > 1
                self._pair_action_index = action.long().argmax(-1) if onehot else action.reshape(-1).long()
        else:
            log_pi = None
        if self._categorical:
            logits = out.get(keys.option_logits)
            pi = (logits, torch.logsumexp(logits, -1))
        else:
            pi = log_pi if log_pi is not None else option_log_probs(
                out[self.pair_state], self.pair_action, action_space=self.action_space,
                option_logits_key=keys.option_logits, option_loc_key=keys.option_loc,
                option_scale_key=keys.option_scale, action_key=keys.action, checks=BatchChecks(),
            )  # fmt: skip
        K = pi[1].shape[-1] if isinstance(pi, tuple) else pi.shape[-1]
        term_logits = out.get(keys.termination_logits)
        if term_logits is None or term_logits.shape != (self.num_states, K):
            got = "nothing" if term_logits is None else tuple(term_logits.shape)
            raise ValueError(
                f"{keys.termination_logits!r} must have shape [..., K] with K = {K} (from the control policies), got "
                f"{got} for a batch of {self.num_states} states."
            )
        meta = None
        if self.meta_control is not None:
            meta = self.meta_control(self.meta_table.clone(False)).get(keys.meta_logits)
            if meta.shape != (self.meta_table.batch_size[0], K):
                raise ValueError(
                    f"{keys.meta_logits!r} must have shape [..., K] with K = {K}: the meta-control must choose among "
                    f"the {K} options, got {tuple(meta.shape)}."
                )
        return pi, term_logits, meta

    def _pair_log_pi(self, pi) -> torch.Tensor:
        """``log pi_h(a | s)`` per pair ``[P, K]`` from :meth:`_forward`'s ``pi``."""
        if not isinstance(pi, tuple):
            return pi
        logits, lse = pi
        return logits[self.pair_state, :, self._pair_action_index] - lse[self.pair_state]

    def _parameters(self) -> list[torch.Tensor]:
        params = list(self.options.parameters())
        return params + ([] if self.meta_control is None else list(self.meta_control.parameters()))

    def e_step(self, usage_floor: UsageFloor | None = None) -> tuple[dict[str, torch.Tensor], Callable[[], torch.Tensor]]:
        """Posterior of the batch under the current parameters.

        Args:
            usage_floor (UsageFloor, optional): project the posterior onto a floor on every option's usage
                (:mod:`~torchrl_options.discovery.usage_floor`): the E-step runs with the floor's dual variables
                added to the options' action log-probabilities, the record's ``log_likelihood_per_step`` (and
                ``loss_ddo``) is the penalised objective ``log p(x) - KL(q* || p(z|x))`` per step (the likelihood
                when no floor binds, a lower bound of it otherwise), and the dual takes one step from this
                posterior's usage. ``None`` (default): the exact posterior.

        Returns:
            ``(record, objective)``: ``record`` holds :class:`~torchrl_options.DDOLoss`'s outputs (detached) for the
            current parameters; ``objective()`` evaluates ``-Q / n_steps`` under the parameters at call time
            (differentiable), ``Q`` with this E-step's expected counts. The E-step's forward pass of the networks
            serves the first call of ``objective()`` if the parameters are unchanged by then (bit for bit).

        Raises:
            ValueError: when the networks' outputs hold NaN (or log-probabilities +inf) at a valid step, naming it.
        """
        B, T = self.mask.shape
        params = self._parameters()
        snapshot = [p.detach().clone() for p in params]
        with torch.enable_grad():
            forward = self._forward()
        with torch.no_grad():
            pi, term_logits, meta_logits = forward
            # contiguous tables: the gathers below read whole rows
            log_pi_pairs = self._pair_log_pi(pi).detach().contiguous()
            term_logits = term_logits.detach().contiguous()
            K = log_pi_pairs.shape[-1]
            log_meta = None if meta_logits is None else meta_logits.detach().log_softmax(-1).contiguous()
            self._check_outputs(log_pi_pairs, term_logits, log_meta)

            def per_step(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
                return table.index_select(0, index.reshape(-1)).view(B, T, *table.shape[1:])

            log_pi = per_step(log_pi_pairs, self.pair_index)
            log_term = per_step(torch.nn.functional.logsigmoid(term_logits), self.next_index)
            log_cont = per_step(torch.nn.functional.logsigmoid(-term_logits), self.next_index)
            if log_meta is None:
                log_eta = torch.full((B, T, K), -math.log(K), dtype=log_pi.dtype, device=log_pi.device)
            else:
                log_eta = per_step(log_meta, self.meta_index)
            # the values were checked above (on the tables) and the mask when the batch was tabulated
            if usage_floor is not None:
                log_pi = usage_floor.biased(log_pi)
            fb = forward_backward(log_pi, log_term, log_cont, log_eta, self.mask, self.terminal, validate=False)
            n = self.num_steps
            ll = fb.log_likelihood.sum()
            if usage_floor is not None:
                ll = ll - usage_floor.penalty(fb.u)
                usage_floor.update(fb.u.sum((0, 1)) / n)
            psi_next = per_step(torch.sigmoid(term_logits), self.next_index)
            diagnostics = ddo_diagnostics(fb.u, fb.v, psi_next, n)
            record = {"loss_ddo": -ll / n, "log_likelihood_per_step": ll / n, **diagnostics}

            # the expected counts: the Expectation-Gradient of forward_backward (d log P / d log_pi = u,
            # d / d log_term = u - w where log_term enters the likelihood, else 0, d / d log_cont = w,
            # d / d log_eta = v) summed per table row
            flat = self._flat_indices(K)

            def counts(values: torch.Tensor, entries: torch.Tensor, size: int, steps: torch.Tensor | None):
                values = values.reshape(B * T, K)
                values = values if steps is None else values.index_select(0, steps)
                out = torch.zeros(size * K, dtype=values.dtype, device=values.device)
                return out.scatter_add_(0, entries, values.reshape(-1)).view(size, K)

            steps, U = flat["steps"], self.num_states
            n_pi = counts(fb.u, flat["pair"], self.num_pairs, steps)
            n_term = counts(fb.u - fb.w, flat["next_term"], U, flat["term_steps"])
            n_cont = counts(fb.w, flat["next"], U, steps)
            n_eta = None if log_meta is None else counts(fb.v, flat["meta"], self.meta_table.batch_size[0], steps)
            n_stop = n_term + n_cont
            if isinstance(pi, tuple):
                # Q's policy term per state: sum_a N[s, h, a] logits[s, h, a] - (sum_a N[s, h, a]) logsumexp[s, h]
                n_pi_dense = torch.zeros(pi[0].shape, dtype=n_pi.dtype, device=n_pi.device)
                n_pi_dense[self.pair_state, :, self._pair_action_index] = n_pi
                n_pi_state = n_pi_dense.sum(-1)
                pi_used, state_used = n_pi_dense != 0, n_pi_state != 0
            else:
                pi_used = n_pi != 0
            if n_eta is not None:
                n_eta_sum = n_eta.sum(-1)
                eta_used, eta_sum_used = n_eta != 0, n_eta_sum != 0
        cached = [forward]

        def objective() -> torch.Tensor:
            forward = cached.pop() if cached else None
            if forward is None or _changed(params, snapshot):
                forward = self._forward()
            pi, term_logits, meta_logits = forward
            # zero counts times a -inf log-probability (an option that cannot take the action) contribute nothing
            if isinstance(pi, tuple):
                logits, lse = pi
                q = torch.where(pi_used, n_pi_dense * logits, 0.0).sum()
                q = q - torch.where(state_used, n_pi_state * lse, 0.0).sum()
            else:
                q = torch.where(pi_used, n_pi * pi, 0.0).sum()
            # n_term log psi + n_cont log(1 - psi), with log(1 - sigmoid(x)) = logsigmoid(x) - x
            q = q + (n_stop * torch.nn.functional.logsigmoid(term_logits) - n_cont * term_logits).sum()
            if n_eta is not None:
                q = q + torch.where(eta_used, n_eta * meta_logits, 0.0).sum()
                q = q - torch.where(eta_sum_used, n_eta_sum * torch.logsumexp(meta_logits, -1), 0.0).sum()
            return -q / n

        return record, objective

    def _check_outputs(self, log_pi: torch.Tensor, term_logits: torch.Tensor, log_eta: torch.Tensor | None) -> None:
        """NaN (or +inf log-probabilities) in the tables, at the rows the valid steps read, in one synchronisation;
        the error names the first valid step reading a bad row."""
        checks = BatchChecks()
        tables = [("log pi (from the options' outputs)", log_pi, self.pair_index, False)]
        tables.append((f"options' {self.keys.termination_logits!r}", term_logits, self.next_index, True))
        if log_eta is not None:
            tables.append((f"log eta (meta_control's {self.keys.meta_logits!r})", log_eta, self.meta_index, False))
        for name, x, index, logits in tables:
            bad = torch.isnan(x) if logits else torch.isnan(x) | (x == float("inf"))
            bad = bad.any(-1)
            if index is self.next_index:  # the states seen only at s_t (e.g. s_0) are not read here
                bad = bad & self._next_states(x.shape[-1])
            checks.add(bad.any(), lambda name=name, bad=bad, index=index, logits=logits: (
                f"{name} holds NaN{'' if logits else ' or +inf'} at valid step "
                f"(b, t) = {tuple((bad[index] & self.mask).nonzero()[0].tolist())}: the networks' outputs must be "
                "finite."
            ))  # fmt: skip
        checks.raise_if_any()

    def _next_states(self, K: int) -> torch.Tensor:
        """``[U]`` bool: the states some valid step reaches (``s_{t+1}``)."""
        if self._next_used is None:
            used = torch.zeros(self.num_states * K, dtype=torch.bool, device=self.mask.device)
            self._next_used = used.index_fill_(0, self._flat_indices(K)["next"], True).view(-1, K).any(-1)
        return self._next_used
