"""Collector throughput with and without :class:`~torchrl_options.transforms.OptionExecutor`.

Same 16 batched envs, same policy (``QValueActor`` MLP + ``EGreedyModule``, over the augmented action spec
``A + K`` with the executor and over the plain spec ``A`` without it), one run; the only difference is the
executor with K=4 MLP options. The two collectors take turns batch by batch so that load on a shared
machine affects both alike; the table reports the median over rounds of the frames/s of each, their ratio,
the range of the per-round ratios, and the same ratio measured in process CPU time
(``time.process_time``), which time slicing on a loaded machine does not distort (on an idle machine the
two agree: everything runs in this process, single-threaded). Envs:

- ``randomwalk``: a natively batched env whose step costs almost nothing, the worst case for the executor
  (its cost, and that of the ``TransformedEnv`` wrapper it brings, is not hidden behind a simulator);
- ``randomwalk+stepcounter``: the same env already wrapped in a ``TransformedEnv`` (as most envs are);
- ``gridworld``: our natively batched :class:`~torchrl_options.envs.GridWorldEnv` (four rooms, apple task);
- ``serial-randomwalk``: a ``SerialEnv`` of 16 single random walks, the executor outside it.

Episode ends are random and independent of the actions in the random walks, so both setups reset equally
often.

A third setup, the env with TorchRL's :class:`~torchrl.envs.transforms.StepCounter` appended instead of the
executor, runs in the same rounds: the second table gives the overhead per batched env step (process CPU time,
microseconds, over the env alone) of StepCounter and of the executor, and their ratio (issue 51 aims at most 2).
``--options optionsmlp`` uses the package's :class:`~torchrl_options.modules.OptionsMLP` (the same network: one
hidden layer of 64 ReLU units, shared heads), a TensorDict module that writes its outputs itself, in place of the
plain ``TensorDictModule``, whose call (tensordict 0.14) converts every output with ``TensorDict.from_any``, which
looks pandas up with ``importlib.util.find_spec`` each time (tens of microseconds where pandas is not imported).
With ``--compile BACKEND`` a fourth setup runs the executor with ``compile_options={"backend": BACKEND}``
(compiled before the rounds, in the warm-up batch).

Run::

    python benchmarks/bench_option_executor.py --rounds 5 --frames 8192   # the issue's setting
    python benchmarks/bench_option_executor.py --rounds 9 --frames 32768 --envs randomwalk gridworld
    python benchmarks/bench_option_executor.py --rounds 3 --frames 8192 --breakdown   # where the time goes
    python benchmarks/bench_option_executor.py --rounds 5 --frames 8192 --compile eager  # + compile_options
    python benchmarks/bench_option_executor.py --rounds 5 --frames 8192 --options optionsmlp
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

from torchrl_options.envs import GridWorldEnv
from torchrl_options.modules import OptionsMLP
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


ENV_KINDS = ("randomwalk", "randomwalk+stepcounter", "gridworld", "serial-randomwalk")


def make_base_env(args, kind: str):
    """16 batched envs: natively batched (cheapest step: worst case for the executor) or a SerialEnv."""
    if kind == "serial-randomwalk":
        return SerialEnv(args.num_envs, partial(BatchedRandomWalk, 1, args.obs_dim, args.num_actions))
    if kind == "gridworld":
        return GridWorldEnv("four-rooms", batch_size=[args.num_envs], seed=0)
    env = BatchedRandomWalk(args.num_envs, args.obs_dim, args.num_actions)
    if kind == "randomwalk+stepcounter":
        env = env.append_transform(StepCounter(max_steps=1000))
    return env




def make_env(args, with_executor: bool | str, kind: str):
    env = make_base_env(args, kind)
    if with_executor == "stepcounter":
        return env.append_transform(StepCounter(max_steps=10**9))
    if with_executor:
        obs_dim = env.observation_spec["observation"].shape[-1]
        num_actions = env.full_action_spec_unbatched["action"].n
        if args.options == "optionsmlp":  # the package's options module (what discovery returns), the same network
            options = OptionsMLP(
                obs_dim, num_actions, args.num_options, num_cells=64, activation="relu", architecture="shared"
            )
        else:
            options = TensorDictModule(
                MLPOptions(obs_dim, args.num_options, num_actions),
                in_keys=["observation"],
                out_keys=["option_logits", "termination_logits"],
            )
        compile_options = {"backend": args.compile} if with_executor == "compiled" else False
        executor = OptionExecutor(options, num_options=args.num_options, compile_options=compile_options)
        env = env.append_transform(executor)
    return env


def make_policy(env, args):
    spec = env.full_action_spec_unbatched["action"]
    actor = QValueActor(MLP(out_features=spec.n, num_cells=[64, 64]), in_keys=["observation"], spec=spec)
    return TensorDictSequential(actor, EGreedyModule(spec, eps_init=0.1, eps_end=0.1))


def measure(setups: dict, args) -> dict:
    """Per-round frames/s (wall clock and process CPU time) of each setup, batches interleaved.

    One collector per setup; after a warm-up batch each, the collectors take turns batch by batch, so that
    a change of load on a shared machine hits both setups alike. A round is ``args.frames`` frames.
    """
    # closing a batched env resets torch's thread count (torchrl 0.14): set it before collecting
    torch.set_num_threads(args.threads)
    collectors, iterators = {}, {}
    for key, (env, policy) in setups.items():
        collectors[key] = Collector(
            env, policy, frames_per_batch=args.frames_per_batch, total_frames=-1, auto_register_policy_transforms=False
        )
        collectors[key].set_seed(0)
        iterators[key] = iter(collectors[key])
        next(iterators[key])  # warm-up batch
    batches = max(1, args.frames // args.frames_per_batch)
    fps = {key: [] for key in setups}
    for _ in range(args.rounds):
        wall, cpu, frames = dict.fromkeys(setups, 0.0), dict.fromkeys(setups, 0.0), dict.fromkeys(setups, 0)
        for _ in range(batches):
            if torch.get_num_threads() != args.threads:
                # closing a batched env (e.g. one garbage-collected from a previous row) resets it
                torch.set_num_threads(args.threads)
            for key, iterator in iterators.items():
                start, start_cpu = time.perf_counter(), time.process_time()
                batch = next(iterator)
                wall[key] += time.perf_counter() - start
                cpu[key] += time.process_time() - start_cpu
                frames[key] += batch.numel()
        for key in setups:
            fps[key].append((frames[key] / wall[key], frames[key] / cpu[key]))
    for collector in collectors.values():
        collector.shutdown(close_env=False)
    return fps


class _CpuTimer:
    """Accumulates the process CPU time spent in some methods of some objects (instance-level wrappers)."""

    def __init__(self):
        self.totals: dict[str, float] = {}

    def wrap(self, obj, method: str, label: str) -> None:
        inner = getattr(obj, method)
        self.totals.setdefault(label, 0.0)

        def timed(*args, **kwargs):
            start = time.process_time()
            try:
                return inner(*args, **kwargs)
            finally:
                self.totals[label] += time.process_time() - start

        setattr(obj, method, timed)


def breakdown(setups: dict, args) -> dict[str, float]:
    """Process CPU time per env step (microseconds) of the policy, of the executor and of its options.

    ``executor`` is the executor's own per-step code (``_inv_call``, ``_step``, ``_reset``) including the
    options' forward (``options``); ``bookkeeping`` is the difference. The rest of a step is the env, the
    ``TransformedEnv`` machinery and the collector.
    """
    timer = _CpuTimer()
    for with_executor, (env, policy) in setups.items():
        tag = "with" if with_executor else "without"
        timer.wrap(policy, "forward", f"policy ({tag})")
        if with_executor:
            executor = next(t for t in env.transform.modules() if isinstance(t, OptionExecutor))
            for method in ("_inv_call", "_step", "_reset"):
                timer.wrap(executor, method, "executor")
            timer.wrap(getattr(executor.options, "module", executor.options), "forward", "options")
    fps = measure(setups, args)
    steps = (args.rounds * max(1, args.frames // args.frames_per_batch) + 1) * args.frames_per_batch / args.num_envs
    out = {key: 1e6 * total / steps for key, total in timer.totals.items()}
    out["bookkeeping"] = out["executor"] - out["options"]
    for with_executor, rounds in fps.items():
        tag = "with" if with_executor else "without"
        out[f"env step, all ({tag})"] = 1e6 * args.num_envs / statistics.median(c for _, c in rounds)
    return out


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
    parser.add_argument(
        "--options",
        default="tensordictmodule",
        choices=("tensordictmodule", "optionsmlp"),
        help="the options module: a plain TensorDictModule around an MLP (default), or the package's OptionsMLP",
    )
    parser.add_argument(
        "--compile",
        default=None,
        metavar="BACKEND",
        help="also run the executor with compile_options={'backend': BACKEND}",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also time (process CPU time per env step, instrumented run) the policy, the executor and its options",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    rows, overheads = [], []
    for kind in args.envs:
        setups = {}
        for with_executor in (False, True, "stepcounter", *(("compiled",) if args.compile else ())):
            env = make_env(args, with_executor, kind)
            setups[with_executor] = (env, make_policy(env, args))
        fps = measure(setups, args)
        wall = {k: [w for w, _ in v] for k, v in fps.items()}
        cpu = {k: [c for _, c in v] for k, v in fps.items()}
        base, opt = statistics.median(wall[False]), statistics.median(wall[True])
        per_round = [o / b for o, b in zip(wall[True], wall[False])]
        cpu_ratio = statistics.median(cpu[True]) / statistics.median(cpu[False])
        rows.append((kind, base, opt, opt / base, min(per_round), max(per_round), cpu_ratio))
        # overhead per batched step over the env alone, CPU time: medians over rounds of the per-round differences
        step_us = {k: [1e6 * args.num_envs / c for c in v] for k, v in cpu.items()}
        counter = statistics.median(s - b for s, b in zip(step_us["stepcounter"], step_us[False]))
        ours = statistics.median(o - b for o, b in zip(step_us[True], step_us[False]))
        compiled = (
            statistics.median(o - b for o, b in zip(step_us["compiled"], step_us[False])) if args.compile else None
        )
        overheads.append((kind, statistics.median(step_us[False]), counter, ours, ours / counter, compiled))

    print(
        f"Collector frames/s, {args.num_envs} batched envs, K={args.num_options} MLP options, "
        f"{args.frames} frames x {args.rounds} rounds (median), torch threads={args.threads}"
    )
    header = (
        f"| {'env (16 batched)':<24} | {'without executor':>16} | {'with executor':>13} | {'ratio':>5} "
        f"| {'per-round ratios':>16} | {'ratio (CPU time)':>16} |"
    )
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for name, base, opt, ratio, lo, hi, cpu_ratio in rows:
        spread = f"{lo:.2f}-{hi:.2f}"
        print(
            f"| {name:<24} | {base:>16.0f} | {opt:>13.0f} | {ratio:>5.2f} | {spread:>16} | {cpu_ratio:>16.2f} |"
        )

    print(
        "\nOverhead per batched env step over the env alone (process CPU time, microseconds, median over rounds): "
        "TorchRL's StepCounter and the OptionExecutor, same rounds"
    )
    header = (
        f"| {'env (16 batched)':<24} | {'env alone':>9} | {'StepCounter':>11} | {'OptionExecutor':>14} "
        f"| {'executor / StepCounter':>22} |"
    )
    if args.compile:
        header += f" {'compiled executor':>17} | {'compiled / StepCounter':>22} |"
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for name, alone, counter, ours, ratio, compiled in overheads:
        line = f"| {name:<24} | {alone:>9.0f} | {counter:>11.0f} | {ours:>14.0f} | {ratio:>22.2f} |"
        if compiled is not None:
            line += f" {compiled:>17.0f} | {compiled / counter:>22.2f} |"
        print(line)


    if args.breakdown:
        print(f"\nCPU time per env step ({args.num_envs} envs), microseconds, instrumented run:")
        for kind in args.envs:
            setups = {}
            for with_executor in (False, True):
                env = make_env(args, with_executor, kind)
                setups[with_executor] = (env, make_policy(env, args))
            times = breakdown(setups, args)
            print(f"  {kind}: " + ", ".join(f"{key} {value:.0f}" for key, value in times.items()))

if __name__ == "__main__":
    main()
