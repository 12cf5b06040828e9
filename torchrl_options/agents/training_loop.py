"""The collector loop shared by the agents (:class:`~torchrl_options.agents.OptionsDQN`,
:class:`~torchrl_options.agents.OptionsPPO`): what they record, and how they seed, collect and stop.

An agent collects with a TorchRL :class:`~torchrl.collectors.Collector` over its env (with the
:class:`~torchrl_options.transforms.OptionExecutor` of Fox et al., 2017, "Multi-Level Discovery of Deep Options",
section 5, when it acts with options), and learns from every batch in its own way.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_options.checks import check_callable, check_int
from torchrl_options.transforms.option_executor import OptionExecutor

__all__ = ["CollectorTraining", "TrainingLog", "check_train_arguments", "seed_executors"]


@dataclass
class TrainingLog:
    """What an agent's ``train`` records, per finished episode and per gradient step."""

    episode_returns: list[float] = field(default_factory=list)
    episode_lengths: list[int] = field(default_factory=list)  # primitive steps
    episode_end_frames: list[int] = field(default_factory=list)  # total frames when the episode ended
    losses: list[float] = field(default_factory=list)
    # one entry per :meth:`OptionsDQN.record_evaluation`: [training episodes so far, frames so far, mean greedy
    # return, episodes evaluated]
    evaluations: list[list[float]] = field(default_factory=list)

    def record_episodes(self, batch: TensorDictBase, frames: int) -> torch.Tensor | None:
        """Appends the episodes that end in a collector ``batch`` ``[*envs, T]`` (needs ``RewardSum`` and
        ``StepCounter``), in the order they ended; ``frames`` is the count before the batch. Returns their returns,
        or ``None`` when none ended."""
        done = batch.get(("next", "done")).squeeze(-1)
        if not done.any():
            return None
        # frame index (1-based) of every step, counting all envs of a time step together
        n_envs = batch.shape[:-1].numel()
        frame = (frames + (torch.arange(batch.shape[-1]) + 1) * n_envs).expand(batch.shape).to(done.device)
        returns = batch.get(("next", "episode_reward")).squeeze(-1)[done]
        lengths = batch.get(("next", "step_count")).squeeze(-1)[done]
        ends = frame[done]
        order = ends.argsort(stable=True)
        self.episode_returns += returns[order].tolist()
        self.episode_lengths += lengths[order].tolist()
        self.episode_end_frames += ends[order].tolist()
        return returns


def check_train_arguments(total_frames: Any, callback: Any) -> None:
    """The door checks of ``train(total_frames, callback)``.

    Examples:
        >>> check_train_arguments(1000, None)
        >>> check_train_arguments(-1, None)
        Traceback (most recent call last):
        ...
        ValueError: total_frames must be an int >= 0, got -1.
    """
    check_int(total_frames, "total_frames", minimum=0, allow_none=True)
    check_callable(callback, "callback", allow_none=True)


def seed_executors(env: EnvBase, seed: int) -> None:
    """Seeds the private generators of the executors of ``env`` (one stream per level), as ``collector.set_seed``
    seeds the env: the options' draws neither depend on nor shift the exploration's."""
    if isinstance(env, TransformedEnv):
        for executor in env.transform.modules():
            if isinstance(executor, OptionExecutor):
                executor.set_seed(seed * 1_000_003 + 7_919 * executor.level)


class CollectorTraining:
    """The training loop of an agent that learns from the batches of a TorchRL ``Collector``.

    A subclass holds ``config`` (with ``total_frames``, ``frames_per_batch`` and ``seed``), ``env``, ``device``,
    ``frames`` (primitive env steps so far) and ``log`` (a :class:`TrainingLog`), and defines
    :meth:`_collector_policy`, :meth:`_start_episodes`, :meth:`_record_episodes` and :meth:`_learn`.

    Examples:
        >>> from types import SimpleNamespace
        >>> from torchrl.envs import RewardSum, TransformedEnv
        >>> from torchrl.modules import MLP, QValueActor
        >>> from torchrl_options.envs import GridWorldEnv
        >>> class Untrained(CollectorTraining):  # collects with a fixed Q-network, learns nothing
        ...     def __init__(self):
        ...         self.config = SimpleNamespace(total_frames=64, frames_per_batch=32, seed=0)
        ...         self.env = TransformedEnv(GridWorldEnv("four-rooms", seed=0), RewardSum())  # it counts steps
        ...         spec = self.env.action_spec
        ...         q_values = MLP(out_features=spec.n, num_cells=[8])
        ...         self.actor = QValueActor(q_values, in_keys=["observation"], spec=spec)
        ...         self.device, self.frames, self.log, self.batches = torch.device("cpu"), 0, TrainingLog(), 0
        ...     def _collector_policy(self):
        ...         return self.actor
        ...     def _start_episodes(self):
        ...         pass
        ...     def _record_episodes(self, batch):
        ...         self.log.record_episodes(batch, self.frames)
        ...     def _learn(self, batch):
        ...         self.batches += 1
        >>> agent = Untrained()
        >>> _ = agent.train()
        >>> agent.frames, agent.batches
        (64, 2)
        >>> _ = agent.train(total_frames=10)  # rounded up to whole batches
        >>> agent.frames, agent.batches
        (96, 3)
    """

    config: Any
    env: EnvBase
    device: torch.device
    frames: int
    log: TrainingLog

    def train(
        self, total_frames: int | None = None, callback: Callable[[Any, TensorDictBase], Any] | None = None
    ) -> TrainingLog:
        """Collects ``total_frames`` more frames (default: what is left of ``config.total_frames``) and learns.

        The budget is counted in whole collector batches: ``total_frames`` is rounded up to a multiple of
        ``config.frames_per_batch`` (which the envs fill exactly). ``callback(agent, batch)`` is called after every
        collector batch (logging, evaluation, checkpoints); when it returns ``True`` training stops there (e.g.
        after a number of episodes). Can be called again to continue training (the collector then restarts the
        episodes), also after ``load_state_dict``. Torch's thread count is as the caller left it afterwards (TorchRL
        raises it when its collector closes a batched env).
        """
        check_train_arguments(total_frames, callback)
        config = self.config
        if total_frames is None:
            total_frames = config.total_frames - self.frames
        total_frames = math.ceil(total_frames / config.frames_per_batch) * config.frames_per_batch
        if total_frames <= 0:
            return self.log
        # The collector resets the env when it is built: seed the env first, so that every call starts from a state
        # set by the frame count alone (a run resumed from a checkpoint then starts as the uninterrupted run did)
        self.env.set_seed(config.seed + self.frames)
        collector = Collector(
            self.env,
            self._collector_policy(),
            frames_per_batch=config.frames_per_batch,
            total_frames=total_frames,
            storing_device=self.device,
            policy_device=self.device,
            # Named explicitly: TorchRL 0.14.1's Collector picks its env-side CUDA sync from this argument only, so
            # without it a CUDA policy's actions reach a CPU env through an unsynchronised non-blocking copy
            # (seen on an H100: garbage actions, ALE's "list index out of range").
            env_device=self.env.device,
            auto_register_policy_transforms=False,
        )
        collector.set_seed(config.seed + self.frames)
        seed_executors(self.env, config.seed + self.frames)
        self._start_episodes()  # the collector starts new episodes
        # TorchRL's Collector closes the env once its frame budget is spent, and closing a SerialEnv / ParallelEnv
        # sets torch's thread count to min(the count when torchrl was imported, the count now + its workers): after
        # train() a process that asked for 1 thread would run on 2 or more (several agents in processes sharing a
        # machine then oversubscribe its cores: 7x slower MiniGrid cells on 2 cores). The caller's count is kept.
        threads = torch.get_num_threads()
        try:
            for batch in collector:
                self._record_episodes(batch)  # counts from the frames before the batch
                self.frames += batch.numel()
                self._learn(batch)
                collector.update_policy_weights_()
                if callback is not None and callback(self, batch):
                    break
        finally:
            collector.shutdown(close_env=False)
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)
        return self.log

    def _collector_policy(self) -> nn.Module:
        """The policy the collector runs."""
        raise NotImplementedError

    def _start_episodes(self) -> None:
        """Forgets the episodes in progress (the collector starts new ones)."""
        raise NotImplementedError

    def _record_episodes(self, batch: TensorDictBase) -> None:
        """Logs the episodes that end in ``batch``, before ``frames`` counts it."""
        raise NotImplementedError

    def _learn(self, batch: TensorDictBase) -> None:
        """Learns from one collector batch (``frames`` already counts it)."""
        raise NotImplementedError
