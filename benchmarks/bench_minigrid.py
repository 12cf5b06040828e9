"""Throughput on MiniGrid: TorchRL's plain PPO collection, the same with the OptionExecutor, and OptionsPPO's whole
loop with and without options, on the same batched envs (issue 50, part 4).

Envs: ``--envs`` copies of a MiniGrid level (``torchrl_options.envs.minigrid.make_minigrid_env``: gymnasium's
MiniGrid through TorchRL's GymWrapper, the one-hot view as a 984-float observation) in a ``SerialEnv`` and in a
``ParallelEnv``. Per layout, four rows:

- ``collect A``: TorchRL's own PPO collection: a ``Collector`` running a ``ProbabilisticActor`` (categorical MLP
  policy over the 7 actions, ``--hidden`` units) on the batched env: the baseline of the ratios;
- ``collect A+K``: the same with the ``OptionExecutor`` appended (K options, an ``OptionsMLP`` with 8 hidden
  units, the size DDO discovers) and the policy over the ``7 + K`` augmented actions;
- ``TorchRL PPO A``: TorchRL's plain PPO loop written from its parts, collection and updates: the collector
  above, a ``ValueOperator`` critic, ``GAE`` (gamma 0.99, lambda 0.95) and ``ClipPPOLoss`` (entropy 0.01) with Adam,
  4 epochs of minibatches of 64 per batch of ``--frames`` frames;
- ``OptionsPPO A``: the package's PPO over actions only, collection and updates (the same sizes);
- ``OptionsPPO A+K``: the same over actions and options.

The options are untrained (throughput depends on how long options run, not on what they do; untrained ones stop
after about 2 steps, so the executor runs often). The three collector rows take turns, ``--frames`` frames each per
round, so load on a shared machine affects them alike; ``OptionsPPO.train`` builds a collector per call, so each
OptionsPPO row runs its ``--rounds`` batches in one call, timed batch by batch from its callback (after a first
batch that starts the envs). The table gives the median frames/s over the rounds (batches) in wall time and in
process CPU time (the ParallelEnv's workers are other processes: its CPU column counts the driver only), and the
ratio to ``collect A`` of the same layout.

Run::

    python benchmarks/bench_minigrid.py                       # 4 envs, 3 rounds of 2048 frames, serial and parallel
    python benchmarks/bench_minigrid.py --level BabyAI-UnlockPickup-v0 --envs 8 --rounds 5
"""
from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import ExplorationType, ParallelEnv, SerialEnv
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from torchrl_options import OptionExecutor, OptionsMLP, OptionsPPO, OptionsPPOConfig
from torchrl_options.envs.minigrid import make_minigrid_env, observation_size


def _actor(env, hidden: int) -> ProbabilisticActor:
    spec = env.full_action_spec_unbatched["action"]
    net = MLP(in_features=observation_size(), out_features=spec.n, num_cells=[hidden, hidden], activation_class=nn.Tanh)
    return ProbabilisticActor(TensorDictModule(net, ["observation"], ["logits"]), in_keys=["logits"], spec=spec,
                              distribution_class=torch.distributions.Categorical, return_log_prob=True,
                              default_interaction_type=ExplorationType.RANDOM)  # fmt: skip


class _Collect:
    """A persistent collector over ``env`` yielding ``frames`` per call."""

    def __init__(self, env, frames: int, hidden: int):
        self.env = env
        self.collector = Collector(env, _actor(env, hidden), frames_per_batch=frames, total_frames=-1,
                                   auto_register_policy_transforms=False)
        self.iterator = iter(self.collector)
        self.frames = frames

    def run(self) -> int:
        next(self.iterator)
        return self.frames

    def close(self) -> None:
        self.collector.shutdown()


class _PlainPPO(_Collect):
    """TorchRL's PPO from its parts on ``env``: each call collects ``frames`` frames and runs 4 epochs of ClipPPOLoss
    over minibatches of 64 (the sizes of OptionsPPO's rows)."""

    def __init__(self, env, frames: int, hidden: int):
        super().__init__(env, frames, hidden)
        actor = self.collector.policy
        critic = ValueOperator(MLP(in_features=observation_size(), out_features=1, num_cells=[hidden, hidden],
                                   activation_class=nn.Tanh), in_keys=["observation"])  # fmt: skip
        self.gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic)
        self.loss = ClipPPOLoss(actor, critic, entropy_coeff=0.01)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=3e-4)

    def run(self) -> int:
        batch = next(self.iterator)
        with torch.no_grad():
            self.gae(batch)
        flat = batch.reshape(-1)
        for _ in range(4):
            for idx in torch.randperm(flat.numel()).split(64):
                losses = self.loss(flat[idx])
                total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                self.optim.zero_grad()
                total.backward()
                self.optim.step()
        self.collector.update_policy_weights_()
        return self.frames


class _Train:
    """OptionsPPO's whole loop; its ``train`` builds a new collector per call, so a row runs all its batches in one
    call and each batch is timed from the callback (the first batch, which starts the envs, is not counted)."""

    def __init__(self, factory, num_envs: int, parallel: bool, frames: int, hidden: int, options, k: int):
        config = OptionsPPOConfig(mode="both" if options is not None else "actions", num_envs=num_envs,
                                  parallel=parallel, frames_per_batch=frames, hidden_sizes=(hidden, hidden))
        self.agent = OptionsPPO(factory, config, options=options, num_options=k if options is not None else None)
        self.frames = frames

    def run_all(self, batches: int) -> tuple[list[float], list[float]]:
        wall, cpu, marks = [], [], [(time.perf_counter(), time.process_time())]

        def tick(agent, batch):
            marks.append((time.perf_counter(), time.process_time()))
            return False

        self.agent.train(total_frames=self.frames * (batches + 1), callback=tick)
        for (w0, c0), (w1, c1) in zip(marks[1:-1], marks[2:]):
            wall.append(self.frames / (w1 - w0))
            cpu.append(self.frames / max(c1 - c0, 1e-9))
        return wall, cpu

    def close(self) -> None:
        if not self.agent.env.is_closed:
            self.agent.env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--envs", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=2048, help="frames per row per round")
    parser.add_argument("--options", type=int, default=5, help="K")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--layouts", nargs="+", default=["serial", "parallel"], choices=["serial", "parallel"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    factory = partial(make_minigrid_env, args.level)
    k = args.options
    options = OptionsMLP(observation_size(), 7, k, num_cells=8)
    print(f"MiniGrid throughput: {args.level}, {args.envs} envs, K = {k} untrained options, "
          f"{args.rounds} rounds x {args.frames} frames per row; median frames/s")
    print("| layout | row | frames/s (wall) | frames/s (CPU, driver) | ratio to collect A (wall) | ratio (CPU) |")
    print("|---|---|---|---|---|---|")
    for layout in args.layouts:
        parallel = layout == "parallel"
        batched = partial(ParallelEnv if parallel else SerialEnv, args.envs, factory)
        with_executor = batched().append_transform(OptionExecutor(options, num_options=k))
        collect = {
            "collect A": _Collect(batched(), args.frames, args.hidden),
            f"collect A+{k}": _Collect(with_executor, args.frames, args.hidden),
            "TorchRL PPO A": _PlainPPO(batched(), args.frames, args.hidden),
        }
        wall = {n: [] for n in collect}
        cpu = {n: [] for n in collect}
        try:
            for _ in range(args.rounds + 1):  # the first round warms up (workers start, first batches), not counted
                for name, row in collect.items():
                    w, c = time.perf_counter(), time.process_time()
                    frames = row.run()
                    wall[name].append(frames / (time.perf_counter() - w))
                    cpu[name].append(frames / max(time.process_time() - c, 1e-9))
        finally:
            for row in collect.values():
                row.close()
        for name in collect:
            wall[name], cpu[name] = wall[name][1:], cpu[name][1:]
        for name, opts in (("OptionsPPO A", None), (f"OptionsPPO A+{k}", options)):
            row = _Train(factory, args.envs, parallel, args.frames, args.hidden, opts, k)
            try:
                wall[name], cpu[name] = row.run_all(args.rounds)
            finally:
                row.close()
        base_w, base_c = statistics.median(wall["collect A"]), statistics.median(cpu["collect A"])
        for name in wall:
            w, c = statistics.median(wall[name]), statistics.median(cpu[name])
            print(f"| {layout} | {name} | {w:,.0f} | {c:,.0f} | {w / base_w:.2f} | {c / base_c:.2f} |", flush=True)


if __name__ == "__main__":
    main()
