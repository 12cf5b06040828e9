"""The gradient loop of discovery (:func:`fit_ddo`) and its stopping rule (:func:`converged_at`).

DDO (Fox, Krishnan, Stoica, Goldberg, 2017, section 4) maximises the likelihood of the demonstrations by
Expectation-Gradient: each iteration computes the exact posterior (the E-step) and takes a gradient step of the
expected complete-data log-likelihood, whose gradient at the E-step's parameters is the likelihood's; several such
steps per E-step make a generalised EM.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase

from torchrl_options.checks import check_int
from torchrl_options.discovery.settings import check_stopping_rule

__all__ = ["EStep", "converged_at", "fit_ddo"]

logger = logging.getLogger(__name__)


def converged_at(values: Sequence[float], tol: float, patience: int) -> int | None:
    """The first iteration at which a maximised quantity stopped improving: ``tol`` over ``patience`` iterations.

    Iteration ``i >= patience`` is the convergence point when the best value up to ``i`` exceeds the best value up
    to ``i - patience`` by less than ``tol``. This is the stopping rule of :func:`fit_ddo` (on the log-likelihood per
    step, in nats): with full-batch training the log-likelihood rises monotonically (up to optimiser noise), so it
    reads "less than ``tol`` nats per step gained over the last ``patience`` iterations".

    Args:
        values (sequence of float): the quantity at each iteration (NaN counts as no improvement).
        tol (float): the smallest gain that counts as progress, ``>= 0``.
        patience (int): the window, ``>= 1``.

    Returns:
        The iteration index, or ``None`` if the values never stopped improving.

    Examples:
        >>> converged_at([-3.0, -2.0, -1.5, -1.4995, -1.4993, -1.4992], tol=1e-3, patience=2)
        4
        >>> converged_at([-3.0, -2.0, -1.0], tol=1e-3, patience=2) is None
        True
    """
    check_stopping_rule(tol, patience)
    best: list[float] = []
    for i, x in enumerate(values):
        if stopping_gain(best, x, tol, patience) is not None:
            return i
    return None


def stopping_gain(best: list[float], value: float, tol: float, patience: int) -> float | None:
    """One iteration of the stopping rule of :func:`converged_at`: appends the best value so far to ``best`` (NaN
    counts as no improvement) and returns the gain over the last ``patience`` iterations when it is below ``tol``
    (the rule says stop), ``None`` otherwise.

    Examples:
        >>> best = []
        >>> [stopping_gain(best, x, 1e-3, 1) for x in (-2.0, -1.0, float("nan"))]
        [None, None, 0.0]
    """
    previous = best[-1] if best else float("-inf")
    best.append(float(value) if value == value and value > previous else previous)
    i = len(best) - 1
    if i >= patience and not best[i] - best[i - patience] >= tol:
        return best[i] - best[i - patience]
    return None


EStep = Callable[[TensorDictBase], "tuple[dict, Callable[[], torch.Tensor]]"]


def record_floats(out: dict) -> dict[str, float]:
    """A record's values as Python floats, read from the device in one synchronisation (the values are stacked in
    float64, which holds every float32 exactly: the floats are those of ``float(value)``).

    Examples:
        >>> record_floats({"a": torch.tensor(0.1), "b": torch.tensor(2, dtype=torch.int64), "c": 3.5})
        {'a': 0.10000000149011612, 'b': 2.0, 'c': 3.5}
    """
    items = list(out.items())  # a dict or a TensorDict (of 0-d tensors)
    tensors = [(k, v) for k, v in items if isinstance(v, torch.Tensor)]
    values = {k: float(v) for k, v in items if not isinstance(v, torch.Tensor)}
    if tensors:
        stacked = torch.stack([v.detach().reshape(()).to(torch.float64) for _, v in tensors]).tolist()
        values.update(zip([k for k, _ in tensors], stacked))
    return {k: values[k] for k, _ in items}


def fit_ddo(
    loss_module: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    next_batch: Callable[[int], TensorDictBase],
    num_iterations: int,
    *,
    e_step: EStep | None = None,
    m_steps: int = 1,
    tol: float | None = None,
    patience: int = 20,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
    desc: str = "DDO",
    progress: bool = True,
    log_every: int = 50,
    set_diagnostics: Callable[[bool], None] | None = None,
    keep_best: bool = False,
) -> list[dict]:
    """The gradient loop of discovery, one- or multi-level: ``num_iterations`` E-steps on ``next_batch(it)``.

    Without ``e_step``, an iteration is one Expectation-Gradient step: ``loss_module(batch)["loss_ddo"]`` is
    back-propagated and ``optimizer`` steps once. With ``e_step``, ``e_step(batch)`` returns ``(record,
    objective)``: the loss module's outputs at the current parameters and a closure whose value has the same
    gradient there (the negative expected complete-data log-likelihood, see
    :class:`~torchrl_options.discovery.TabulatedDDO`); ``optimizer`` then steps ``m_steps`` times on
    ``objective()`` (``m_steps > 1``: a generalised EM, several G-steps per E-step).

    Args:
        loss_module (nn.Module): writes ``loss_ddo`` and ``log_likelihood_per_step`` (used without ``e_step``).
        optimizer (torch.optim.Optimizer): over the trained parameters; stepped as given (its learning rate, and
            any scheduler the caller attached, are the caller's).
        next_batch (callable): ``next_batch(it)``, the ``[B, T]`` batch of iteration ``it``.
        num_iterations (int): the most iterations (E-steps).

    Keyword Args:
        e_step (callable, optional): see above.
        m_steps (int): optimizer steps per E-step; more than 1 needs ``e_step``. Defaults to 1.
        tol (float, optional): stop early once the log-likelihood per step has gained less than ``tol`` nats over
            the last ``patience`` iterations (:func:`converged_at`). ``None`` (default): run all iterations.
        patience (int): the window of the stopping rule, in iterations. Defaults to 20.
        scheduler (LRScheduler, optional): a learning-rate scheduler of ``optimizer``, stepped once per iteration
            (after its ``m_steps`` optimizer steps).
        desc (str): progress-bar and log label.
        progress (bool): show a tqdm progress bar.
        log_every (int): log the diagnostics every this many iterations (0: never).
        set_diagnostics (callable, optional): told before each step whether this one is logged (a loss whose full
            diagnostics cost extra can skip them otherwise).
        keep_best (bool): leave ``loss_module`` at the parameters of the iteration with the highest recorded
            log-likelihood per step (early stopping's "restore the best weights"; the last steps are not evaluated,
            and a generalised EM with several Adam steps per E-step is not monotone). Meant for full-batch training,
            where every record is the likelihood of the same data. Defaults to ``False``: the parameters after the
            last step.

    Returns:
        Per iteration, the loss module's outputs as floats (at the parameters before that iteration's steps).

    Raises:
        ValueError: naming the argument, for ``m_steps`` < 1 (or > 1 without ``e_step``), ``tol`` < 0 or
            ``patience`` < 1.

    Examples:
        >>> import torch
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(8, 50)
        >>> loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
        >>> opt = torch.optim.Adam(loss.parameters(), lr=0.05)
        >>> records = fit_ddo(loss, opt, lambda it: data, 500, tol=1e-3, patience=10, progress=False)
        >>> len(records) < 500, records[-1]["log_likelihood_per_step"] > records[0]["log_likelihood_per_step"]
        (True, True)
    """
    check_int(m_steps, "m_steps", minimum=1)
    check_stopping_rule(tol, patience)
    if m_steps > 1 and e_step is None:
        raise ValueError(f"m_steps={m_steps} needs an e_step (several G-steps reuse one E-step's posterior).")
    records: list[dict] = []
    best: list[float] = []
    best_state, best_value = None, float("-inf")
    iterator = range(num_iterations)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(iterator, desc=desc, unit="it")
        iterator = bar
    for it in iterator:
        batch = next_batch(it)
        full = bool(log_every) and (it % log_every == 0 or it == num_iterations - 1)
        if set_diagnostics is not None:
            set_diagnostics(full)
        if e_step is None:
            out = loss_module(batch)
        else:
            out, objective = e_step(batch)
        snapshot = None
        if keep_best:  # the parameters this record is computed at, before this iteration's steps (a device copy)
            snapshot = {k: v.detach().clone() for k, v in loss_module.state_dict().items()}
        if e_step is None:
            optimizer.zero_grad()
            out["loss_ddo"].backward()
            optimizer.step()
        else:
            for _ in range(m_steps):
                optimizer.zero_grad()
                objective().backward()
                optimizer.step()
        if scheduler is not None:
            scheduler.step()
        record = record_floats(out)  # the iteration's one host synchronisation, after its steps are queued
        if snapshot is not None and record["log_likelihood_per_step"] > best_value:
            best_value, best_state = record["log_likelihood_per_step"], snapshot
        records.append(record)
        if bar is not None:
            postfix = {"ll_step": f"{record['log_likelihood_per_step']:.4f}"}
            if "option_duration" in record:
                postfix["dur"] = f"{record['option_duration']:.1f}"
            bar.set_postfix(postfix)
        if full:
            logger.info("%s iteration %d: %s", desc, it, {k: round(v, 4) for k, v in record.items()})
        if tol is not None:
            x = record["log_likelihood_per_step"]
            gain = stopping_gain(best, x, tol, patience)
            if gain is not None:
                logger.info(
                    "%s converged at iteration %d: log-likelihood per step %.4f, gained %.2e < tol=%g over the last %d",
                    desc, it, x, gain, tol, patience,
                )
                break
    if bar is not None:
        bar.close()
    if best_state is not None:
        loss_module.load_state_dict(best_state)
    return records
