"""Collector throughput with and without :class:`~torchrl_options.transforms.OptionExecutor`.

Same 16 batched envs, same policy (``QValueActor`` MLP + ``EGreedyModule``), the only difference being the
executor with K=4 MLP options (and the policy's K extra outputs). Rounds alternate between the two setups
so that load on a shared machine affects both alike; the table reports the median frames/s of each and
their ratio. Envs:

- ``randomwalk``: a natively batched env whose step costs almost nothing, the worst case for the executor
  (its cost, and that of the ``TransformedEnv`` wrapper it brings, is not hidden behind a simulator);
- ``randomwalk+stepcounter``: the same env already wrapped in a ``TransformedEnv`` (as most envs are);
- ``serial-randomwalk``: a ``SerialEnv`` of 16 single random walks, the executor outside it.

Episode ends are random and independent of the actions, so both setups reset equally often.

Run::

    python benchmarks/bench_option_executor.py               # defaults: 16 envs, K=4, 5 rounds
    python benchmarks/bench_option_executor.py --rounds 9 --frames 32768
"""
from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, SerialEnv, StepCounter
from torchrl.modules import MLP, EGreedyModule, QValueActor

from torchrl_options.transforms import OptionExecutor


class BatchedRandomWalk(EnvBase):
    """A cheap natively batched env: a point in R^d moved by one of ``num_actions`` fixed directions.

    Episodes end at random, ``episode_length`` steps on average, so that sub-envs reset at different times.
    """

    def __init__(self, num_envs: int = 16, obs_dim: int = 8, num_actions: int = 4, episode_length: int = 100):
        super().__init__(batch_size=torch.Size([num_envs]))
        self.end_prob = 1.0 / episode_length
        self.observation_spec = Composite(observation=Unbounded((num_envs, obs_dim)), shape=(num_envs,))
        self.action_spec = Categorical(num_actions, shape=(num_envs,))
        self.reward_spec = Unbounded((num_envs, 1))
        self.directions = torch.randn(num_actions, obs_dim, generator=torch.Generator().manual_seed(0)) * 0.1
        self.state = torch.zeros(num_envs, obs_dim)
        self.rng = torch.Generator().manual_seed(0)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones(self.batch_size, dtype=torch.bool) if reset is None else reset.reshape(self.batch_size)
        self.state = torch.where(mask.unsqueeze(-1), 0.0, self.state)
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {"observation": self.state.clone(), "done": done, "terminated": done.clone()}, self.batch_size
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.state = self.state + self.directions[tensordict.get("action")]
        terminated = torch.rand(*self.batch_size, 1, generator=self.rng) < self.end_prob
        return TensorDict(
            {
                "observation": self.state.clone(),
                "reward": -self.state.norm(dim=-1, keepdim=True),
                "done": terminated,
                "terminated": terminated.clone(),
            },
            self.batch_size,
        )

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(seed)


class MLPOptions(nn.Module):
    """K options from one MLP: ``option_logits`` [..., K, A] and ``termination_logits`` [..., K]."""

    def __init__(self, obs_dim: int, num_options: int, num_actions: int, hidden: int = 64):
        super().__init__()
        self.K, self.A = num_options, num_actions
        self.net = nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, num_options * (num_actions + 1)))

    def forward(self, observation: torch.Tensor):
        out = self.net(observation)
        return out[..., : self.K * self.A].unflatten(-1, (self.K, self.A)), out[..., self.K * self.A :]


ENV_KINDS = ("randomwalk", "randomwalk+stepcounter", "serial-randomwalk")


def make_base_env(args, kind: str):
    """16 batched envs: natively batched (cheapest step: worst case for the executor) or a SerialEnv."""
    if kind == "serial-randomwalk":
        return SerialEnv(args.num_envs, partial(BatchedRandomWalk, 1, args.obs_dim, args.num_actions))
    env = BatchedRandomWalk(args.num_envs, args.obs_dim, args.num_actions)
    if kind == "randomwalk+stepcounter":
        env = env.append_transform(StepCounter(max_steps=1000))
    return env


def make_env(args, with_executor: bool, kind: str):
    env = make_base_env(args, kind)
    if with_executor:
        obs_dim = env.observation_spec["observation"].shape[-1]
        num_actions = env.full_action_spec_unbatched["action"].n
        options = TensorDictModule(
            MLPOptions(obs_dim, args.num_options, num_actions),
            in_keys=["observation"],
            out_keys=["option_logits", "termination_logits"],
        )
        env = env.append_transform(OptionExecutor(options, num_options=args.num_options))
    return env


def make_policy(env, args):
    spec = env.full_action_spec_unbatched["action"]
    actor = QValueActor(MLP(out_features=spec.n, num_cells=[64, 64]), in_keys=["observation"], spec=spec)
    return TensorDictSequential(actor, EGreedyModule(spec, eps_init=0.1, eps_end=0.1))


def frames_per_second(env, policy, args) -> float:
    # closing a batched env resets torch's thread count (torchrl 0.14): set it for every run
    torch.set_num_threads(args.threads)
    collector = Collector(
        env,
        policy,
        frames_per_batch=args.frames_per_batch,
        total_frames=args.frames,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(0)
    start, frames = None, 0
    for i, batch in enumerate(collector):
        if i == 0:  # warm-up batch
            start = time.perf_counter()
            continue
        frames += batch.numel()
    elapsed = time.perf_counter() - start
    collector.shutdown(close_env=False)
    return frames / elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-options", type=int, default=4)
    parser.add_argument("--num-actions", type=int, default=4)
    parser.add_argument("--obs-dim", type=int, default=8)
    parser.add_argument("--frames-per-batch", type=int, default=1024)
    parser.add_argument("--frames", type=int, default=16384)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--envs", nargs="+", default=list(ENV_KINDS), choices=ENV_KINDS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    rows = []
    for kind in args.envs:
        setups = {}
        for with_executor in (False, True):
            env = make_env(args, with_executor, kind)
            setups[with_executor] = (env, make_policy(env, args))
        fps = {False: [], True: []}
        for _ in range(args.rounds):
            for with_executor, (env, policy) in setups.items():
                fps[with_executor].append(frames_per_second(env, policy, args))
        base, opt = statistics.median(fps[False]), statistics.median(fps[True])
        rows.append((kind, base, opt, opt / base))

    print(
        f"Collector frames/s, {args.num_envs} batched envs, K={args.num_options} MLP options, "
        f"A={args.num_actions}, {args.frames} frames x {args.rounds} rounds (median), "
        f"torch threads={args.threads}"
    )
    header = f"| {'env (16 batched)':<32} | {'without executor':>16} | {'with executor':>13} | {'ratio':>5} |"
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for name, base, opt, ratio in rows:
        print(f"| {name:<32} | {base:>16.0f} | {opt:>13.0f} | {ratio:>5.2f} |")


if __name__ == "__main__":
    main()
