"""The gradient loop of streamed discovery (:func:`fit_stream`): DDO's Expectation-Gradient (Fox, Krishnan, Stoica,
Goldberg, 2017, section 4) on trajectories read from a replay buffer a chunk at a time, the gradients summed over
chunks and processes (:mod:`~torchrl_options.discovery.distributed`).

An iteration: (with minibatches) the evaluation set's log-likelihood at the current parameters; then for each
E-step chunk of the iteration's trajectories, the exact posterior (:class:`~torchrl_options.discovery.TabulatedDDO`)
and the gradient of its ``-Q`` (the negative expected complete-data log-likelihood, summed over the chunk's valid
steps) added up; one all-reduce of the gradients and the statistics; the gradient divided by the iteration's valid
steps, and the optimizer's step. ``m_steps > 1`` G-steps (a generalised EM) re-use the one chunk's posterior, each
with its own all-reduce. Records, the stopping rule and ``keep_best`` are those of
:func:`~torchrl_options.discovery.fit.fit_ddo`, on the likelihood :mod:`~torchrl_options.discovery.streaming` defines.
"""
from __future__ import annotations

import logging
from typing import Any

import torch

from torchrl_options.discovery.fit import record_floats, stopping_gain
from torchrl_options.discovery.streaming import TrajectoryStream
from torchrl_options.discovery.tabulated import TabulatedDDO

__all__ = ["fit_stream"]

logger = logging.getLogger(__name__)

# the statistics summed over chunks and processes with the gradients: valid steps, log-likelihood, expected option
# starts, expected termination probability, entropy (weighted by steps), evaluation steps and log-likelihood
_N, _LL, _STARTS, _TERM, _ENTROPY, _EVAL_N, _EVAL_LL = range(7)


def _table(stream: TrajectoryStream, name: str, rows: torch.Tensor, loss_module: torch.nn.Module,
           data: Any = None) -> TabulatedDDO | None:  # fmt: skip
    """The tabulation of trajectories that stay in memory (the evaluation set, a fixed shard), made once and re-used
    by every start's modules."""
    if rows.numel() == 0:
        return None
    table = stream.tables.get(name)
    if table is None:
        table = TabulatedDDO(loss_module, stream.read(rows) if data is None else data)
        stream.tables[name] = table
        return table
    return table.for_loss(loss_module)


def _chunk_stats(record: dict, n: torch.Tensor) -> list[torch.Tensor]:
    n = n.to(torch.float64)
    return [n, record["log_likelihood_per_step"].double() * n, n / record["option_duration"].double(),
            record["termination_probability"].double() * n, record["option_entropy"].double() * n]  # fmt: skip


def fit_stream(
    loss_module: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    stream: TrajectoryStream,
    generator: torch.Generator,
    num_iterations: int,
    *,
    m_steps: int = 1,
    tol: float | None = None,
    patience: int = 20,
    scheduler: Any = None,
    desc: str = "DDO",
    progress: bool = True,
    log_every: int = 50,
    keep_best: bool = False,
    probe: Any = None,
) -> list[dict]:
    """Trains ``loss_module`` for at most ``num_iterations`` iterations on ``stream`` (see the module).

    Args:
        loss_module (DDOLoss): the loss whose options (and meta-control) are trained.
        optimizer (torch.optim.Optimizer): over its parameters; the same on every process.
        stream (TrajectoryStream): the trajectories (:func:`~torchrl_options.discovery.streaming.trajectory_stream`).
        generator (torch.Generator): the run's generator (minibatch draws with one process).
        num_iterations (int): the most iterations.

    Keyword Args:
        m_steps, tol, patience, scheduler, desc, progress, log_every, keep_best: as in
            :func:`~torchrl_options.discovery.fit.fit_ddo`; only process 0 shows the progress bar and logs.
        probe (TensorDictBase, optional): the evaluation set already read (the door's sample).

    Returns:
        Per iteration, the records of :class:`~torchrl_options.DDOLoss` (at the parameters before that iteration's
        steps) summed over the iteration's chunks and processes; with minibatches ``log_likelihood_per_step`` is the
        evaluation set's and ``minibatch_log_likelihood_per_step`` the minibatch's.

    Examples:
        >>> import torch
        >>> from torchrl_options import DDOLoss, OptionsMLP
        >>> from torchrl_options.data import demonstration_buffer, write_demonstrations
        >>> from torchrl_options.discovery.settings import DiscoverySettings
        >>> from torchrl_options.discovery.streaming import trajectory_stream
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> buffer = demonstration_buffer(10_000)
        >>> _ = write_demonstrations(buffer, planted_corridor_demonstrations(16, 100))
        >>> stream, probe = trajectory_stream(buffer, DiscoverySettings(2, batch_size=4, eval_trajectories=8))
        >>> loss = DDOLoss(OptionsMLP(2, 2, 2))
        >>> records = fit_stream(loss, torch.optim.Adam(loss.parameters(), lr=0.05), stream, torch.Generator(), 30,
        ...                      progress=False, probe=probe)
        >>> len(records), records[-1]["log_likelihood_per_step"] > records[0]["log_likelihood_per_step"]
        (30, True)
    """
    group = stream.group
    params = [p for p in loss_module.parameters() if p.requires_grad]
    group.broadcast_(params + list(loss_module.buffers()))  # every process starts from process 0's modules
    lead = group.rank == 0
    full = stream.full_batch
    probe_is_eval = probe is not None and torch.equal(stream.eval_rows, stream.probe_rows)
    eval_table = None if full else _table(stream, "eval", stream.eval_rows, loss_module,
                                          probe if probe_is_eval else None)  # fmt: skip
    fixed_table = None
    if stream.fixed:
        same = probe is not None and torch.equal(stream.rows, stream.probe_rows)
        fixed_table = _table(stream, "train", stream.rows, loss_module, probe if same else None)
    device = next(iter(params)).device if params else stream.device
    records: list[dict] = []
    best: list[float] = []
    best_state, best_value = None, float("-inf")
    iterator = range(num_iterations)
    bar = None
    if progress and lead:
        from tqdm.auto import tqdm

        bar = tqdm(iterator, desc=desc, unit="it")
        iterator = bar
    for it in iterator:
        stats = torch.zeros(7, dtype=torch.float64, device=device)
        if eval_table is not None:
            eval_record, _ = eval_table.e_step()
            stats[_EVAL_N] = eval_table.num_steps.double()
            stats[_EVAL_LL] = eval_record["log_likelihood_per_step"].double() * eval_table.num_steps.double()
        rows = stream.iteration_rows(generator)
        tables = [fixed_table] if fixed_table is not None else None
        chunks = stream.chunks(rows) if tables is None else [rows]
        single = group.world_size == 1 and len(chunks) == 1
        optimizer.zero_grad()
        objective = None
        snapshot = None
        for index, chunk in enumerate(chunks):
            table = tables[0] if tables is not None else TabulatedDDO(loss_module, stream.read(chunk))
            record, objective = table.e_step()
            n = table.num_steps
            for i, value in enumerate(_chunk_stats(record, n)):
                stats[i] += value
            if single:
                objective().backward()  # the in-memory path's step, bit for bit
            else:
                (objective() * n).backward()
            del table
        if keep_best:
            snapshot = {k: v.detach().clone() for k, v in loss_module.state_dict().items()}
        if single:
            stats_sum = stats
        else:
            stats_sum = group.reduce_gradients(params, stats, scale_by=_N)
        optimizer.step()
        for _ in range(m_steps - 1):  # one chunk per process (refused otherwise at the door)
            optimizer.zero_grad()
            if single:
                objective().backward()
            else:
                (objective() * stats[_N].to(params[0].dtype)).backward()
                group.reduce_gradients(params, stats[:1].clone(), scale_by=0)
            optimizer.step()
        if scheduler is not None:
            scheduler.step()
        if single and eval_table is None:  # the in-memory path's record, bit for bit (one host synchronisation)
            record = record_floats(record)
        else:
            record = _record(stats_sum, full)
        records.append(record)
        value = record["log_likelihood_per_step"]
        if keep_best and value > best_value:
            best_value, best_state = value, snapshot
        if bar is not None:
            bar.set_postfix({"ll_step": f"{value:.4f}"})
        if lead and log_every and (it % log_every == 0 or it == num_iterations - 1):
            logger.info("%s iteration %d: %s", desc, it, {k: round(v, 4) for k, v in record.items()})
        if tol is not None:
            gain = stopping_gain(best, value, tol, patience)
            if gain is not None:
                if lead:
                    logger.info("%s converged at iteration %d: log-likelihood per step %.4f, gained %.2e < tol=%g over "
                                "the last %d", desc, it, value, gain, tol, patience)  # fmt: skip
                break
    if bar is not None:
        bar.close()
    if best_state is not None:
        loss_module.load_state_dict(best_state)
    return records


def _record(stats: torch.Tensor, full: bool) -> dict[str, float]:
    """The iteration's record from the summed statistics, read from the device in one synchronisation."""
    values = stats.tolist()
    n = values[_N]
    ll = values[_LL] / n
    record = {
        "loss_ddo": -ll,
        "log_likelihood_per_step": ll,
        "option_duration": n / values[_STARTS],
        "option_entropy": values[_ENTROPY] / n,
        "termination_probability": values[_TERM] / n,
    }
    if not full:
        record["minibatch_log_likelihood_per_step"] = ll
        record["log_likelihood_per_step"] = values[_EVAL_LL] / values[_EVAL_N]
    return record
