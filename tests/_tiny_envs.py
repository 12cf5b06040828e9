"""Tiny environments and hand-written options for the tests of the executor, SMDP transitions and DQN."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

LEFT, RIGHT = 0, 1


class Corridor(EnvBase):
    """A 1-D corridor ``0 .. length-1``, natively batched.

    Every episode starts at cell 0; action 0 moves left, 1 moves right (walls clamp). Reaching the last cell
    gives reward 1 and terminates; ``max_steps`` truncates. A random walk rarely reaches the end, a
    "go right" option always does. The env echoes the action it received in ``"received_action"`` (-1 after
    a reset), so tests can check what the env was really given.
    """

    batch_locked = True

    def __init__(self, length: int = 8, max_steps: int | None = None, batch_size=(), device=None):
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        self.length = length
        self.max_steps = max_steps
        bs = self.batch_size
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, shape=(*bs, length), device=self.device),
            position=Bounded(0, length - 1, shape=(*bs, 1), dtype=torch.int64, device=self.device),
            received_action=Bounded(-1, 1, shape=bs, dtype=torch.int64, device=self.device),
            shape=bs,
        )
        self.action_spec = Categorical(2, shape=bs, device=self.device)
        self.reward_spec = Unbounded(shape=(*bs, 1), device=self.device)
        self.done_spec = Composite(
            {k: Categorical(2, shape=(*bs, 1), dtype=torch.bool) for k in ("done", "terminated", "truncated")},
            shape=bs,
        )
        self.register_buffer("pos", torch.zeros((*bs, 1), dtype=torch.int64, device=self.device))
        self.register_buffer("t", torch.zeros((*bs, 1), dtype=torch.int64, device=self.device))

    def _obs(self, received: torch.Tensor) -> dict:
        return {
            "observation": nn.functional.one_hot(self.pos.squeeze(-1), self.length).float(),
            "position": self.pos.clone(),
            "received_action": received,
        }

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            reset = torch.ones_like(self.pos, dtype=torch.bool)
        reset = reset.reshape(self.pos.shape)
        self.pos.masked_fill_(reset, 0)
        self.t.masked_fill_(reset, 0)
        done = torch.zeros_like(self.pos, dtype=torch.bool)
        received = torch.full(self.batch_size, -1, dtype=torch.int64, device=self.device)
        return TensorDict(
            {**self._obs(received), "done": done, "terminated": done.clone(), "truncated": done.clone()},
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        move = torch.where(action.reshape(self.pos.shape) == RIGHT, 1, -1)
        self.pos.copy_((self.pos + move).clamp(0, self.length - 1))
        self.t.add_(1)
        terminated = self.pos == self.length - 1
        truncated = torch.zeros_like(terminated)
        if self.max_steps is not None:
            truncated = (self.t >= self.max_steps) & ~terminated
        return TensorDict(
            {
                **self._obs(action.clone()),
                "reward": terminated.float(),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        # the corridor is deterministic: all randomness comes from the policy and the options
        pass


BIG = 1e9  # logits this large make softmax/sigmoid exactly one-hot/0/1 in float32


class CheckpointOptions(nn.Module):
    """Two deterministic options over the corridor: 0 goes right, 1 goes left, each until a checkpoint.

    A checkpoint is a cell whose index is a multiple of ``every`` (and the last cell). Termination is a
    function of the state the option lands in, so an executor evaluating it at s_t instead of s_{t+1} (the
    bug of the authors' code) overshoots by one cell, which the tests detect.
    """

    def __init__(self, length: int, every: int = 3):
        super().__init__()
        self.length = length
        self.every = every

    def forward(self, position: torch.Tensor):
        pos = position.squeeze(-1)
        batch = pos.shape
        logits = torch.full((*batch, 2, 2), -BIG)
        logits[..., 0, RIGHT] = BIG
        logits[..., 1, LEFT] = BIG
        checkpoint = (pos % self.every == 0) | (pos == self.length - 1)
        term = torch.where(checkpoint, BIG, -BIG).unsqueeze(-1).expand(*batch, 2).clone()
        return logits, term

    @staticmethod
    def action(option: torch.Tensor) -> torch.Tensor:
        return torch.where(option == 0, RIGHT, LEFT)

    def terminates(self, position: torch.Tensor) -> torch.Tensor:
        pos = position.squeeze(-1)
        return (pos % self.every == 0) | (pos == self.length - 1)


def checkpoint_options(length: int, every: int = 3, in_key="position") -> TensorDictModule:
    """``CheckpointOptions`` as the TensorDict module an ``OptionExecutor`` expects."""
    return TensorDictModule(
        CheckpointOptions(length, every),
        in_keys=[in_key],
        out_keys=["option_logits", "termination_logits"],
    )


class ConstantOptions(nn.Module):
    """K options with fixed action logits and a fixed termination logit each (stochastic options)."""

    def __init__(self, action_logits: torch.Tensor, termination_logits: torch.Tensor):
        super().__init__()
        self.register_buffer("action_logits", action_logits)  # [K, A]
        self.register_buffer("term_logits", termination_logits)  # [K]

    def forward(self, position: torch.Tensor):
        batch = position.shape[:-1]
        return (
            self.action_logits.expand(*batch, *self.action_logits.shape),
            self.term_logits.expand(*batch, *self.term_logits.shape),
        )


def constant_options(action_logits, termination_logits, in_key="position") -> TensorDictModule:
    return TensorDictModule(
        ConstantOptions(torch.as_tensor(action_logits, dtype=torch.float), torch.as_tensor(termination_logits, dtype=torch.float)),
        in_keys=[in_key],
        out_keys=["option_logits", "termination_logits"],
    )


class GoRightOption(nn.Module):
    """A single option: go right until the end of the corridor (the DQN test's helpful option)."""

    def __init__(self, length: int):
        super().__init__()
        self.length = length

    def forward(self, position: torch.Tensor):
        pos = position.squeeze(-1)
        batch = pos.shape
        logits = torch.full((*batch, 2, 2), -BIG)
        logits[..., 0, RIGHT] = BIG  # option 0: right
        logits[..., 1, LEFT] = BIG  # option 1: left
        at_end = pos == self.length - 1
        term = torch.stack([torch.where(at_end, BIG, -BIG), torch.where(pos == 0, BIG, -BIG)], -1)
        return logits, term


def go_right_options(length: int) -> TensorDictModule:
    return TensorDictModule(
        GoRightOption(length), in_keys=["position"], out_keys=["option_logits", "termination_logits"]
    )
