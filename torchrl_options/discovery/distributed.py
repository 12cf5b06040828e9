"""Data-parallel DDO over ``torch.distributed``: the processes of a group (one per core or GPU, launched with
``torchrun``) each stream their own shard of trajectories, and their gradients are summed by one all-reduce per
G-step (:class:`DataParallel`).

DDO's objective is a sum over trajectories (Fox, Krishnan, Stoica, Goldberg, 2017, section 4: the log-likelihood of
independent demonstrations, and the expected complete-data log-likelihood ``Q`` of each E-step), so the gradient of
the whole batch is the sum of the shards' gradients of ``-Q`` divided by the whole batch's valid steps: after the
all-reduce, every process holds the gradient one process would compute on all the trajectories (to float rounding),
takes the same optimizer step and keeps the same parameters. The all-reduce carries the parameters' gradients and a
few statistics (the valid steps, the log-likelihood, the diagnostics), so every process also takes the same
decisions (the stopping rule, the choice among starts, the best iteration). The backend is the process group's:
``gloo`` on CPU, ``nccl`` on GPU (the tensors are on the training device).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["DataParallel", "SingleProcess"]


class SingleProcess:
    """One process: every reduction is the identity (the default of streamed discovery).

    Examples:
        >>> group = SingleProcess()
        >>> group.rank, group.world_size, group.sum_(torch.ones(2)).tolist()
        (0, 1, [1.0, 1.0])
    """

    rank = 0
    world_size = 1

    def sum_(self, tensor: torch.Tensor) -> torch.Tensor:
        """Sums ``tensor`` over the processes in place (here: leaves it) and returns it."""
        return tensor

    def max_(self, tensor: torch.Tensor) -> torch.Tensor:
        """The largest ``tensor`` over the processes, in place."""
        return tensor

    def broadcast_(self, tensors: Sequence[torch.Tensor]) -> None:
        """Sets every process's ``tensors`` to rank 0's, in place."""

    def reduce_gradients(self, params: Sequence[torch.Tensor], stats: torch.Tensor, scale_by: int = 0) -> torch.Tensor:
        """Sums the parameters' gradients and ``stats`` over the processes (one collective), then divides the
        gradients by the summed ``stats[scale_by]`` (the batch's valid steps); returns the summed ``stats``.

        Examples:
            >>> p = torch.nn.Parameter(torch.zeros(2))
            >>> p.grad = torch.tensor([4.0, 8.0])
            >>> SingleProcess().reduce_gradients([p], torch.tensor([4.0, -1.0])).tolist(), p.grad.tolist()
            ([4.0, -1.0], [1.0, 2.0])
        """
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
        if self.world_size > 1:
            flat = torch.cat([g.reshape(-1) for g in grads] + [stats.to(grads[0].dtype if grads else stats.dtype)])
            self.sum_(flat)
            offset = 0
            for p, g in zip(params, grads):
                g.copy_(flat[offset : offset + g.numel()].view_as(g))
                offset += g.numel()
            stats = flat[offset:].to(stats.dtype)
        scale = stats[scale_by]
        for p, g in zip(params, grads):
            g.div_(scale.to(g.dtype))
            p.grad = g
        return stats


class DataParallel(SingleProcess):
    """The processes of a ``torch.distributed`` group, for data-parallel discovery.

    Args:
        group (ProcessGroup, optional): the group; ``None``: the default one (``init_process_group``, as
            ``torchrun`` launches it).

    Raises:
        ValueError: when ``torch.distributed`` is not available or its process group is not initialised.
    """

    def __init__(self, group=None) -> None:
        import torch.distributed as dist

        if not dist.is_available() or not dist.is_initialized():
            raise ValueError(
                "distributed=True needs an initialised torch.distributed process group: launch with torchrun and call "
                "torch.distributed.init_process_group('gloo' on CPU, 'nccl' on GPU) first "
                "(recipes/discover_distributed.py does both)."
            )
        self._dist, self.group = dist, group
        self.rank = dist.get_rank(group)
        self.world_size = dist.get_world_size(group)
        self._src = dist.get_global_rank(group, 0) if group is not None else 0

    def sum_(self, tensor: torch.Tensor) -> torch.Tensor:
        self._dist.all_reduce(tensor, op=self._dist.ReduceOp.SUM, group=self.group)
        return tensor

    def max_(self, tensor: torch.Tensor) -> torch.Tensor:
        self._dist.all_reduce(tensor, op=self._dist.ReduceOp.MAX, group=self.group)
        return tensor

    def broadcast_(self, tensors: Sequence[torch.Tensor]) -> None:
        for t in tensors:
            self._dist.broadcast(t.data, src=self._src, group=self.group)
