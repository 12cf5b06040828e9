"""Per-step cost of several versions of :class:`~torchrl_options.transforms.OptionExecutor`, side by side.

Each version is an ``option_executor.py`` file (e.g. extracted from a git revision); all are loaded in one process
and appended, each to its own copy of the same env (the benchmark's natively batched random walk, 16 envs, K = 4
MLP options). The envs are stepped in turn (``env.step_and_maybe_reset`` in blocks of ``--steps`` steps, fixed
random actions, no policy, no collector), so that load from other processes hits every version alike; the table
gives a low quantile of the per-step time of the blocks (the least disturbed ones) and its excess over the bare env,
i.e. the executor's own cost with that of the ``TransformedEnv`` around it.

Run::

    git show c2f2ba7^:torchrl_options/transforms/option_executor.py > /tmp/before.py
    python benchmarks/bench_option_executor_versions.py before=/tmp/before.py \\
        now=torchrl_options/transforms/option_executor.py
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule

sys.path.insert(0, str(Path(__file__).parent))
import bench_option_executor as bench  # noqa: E402


def load_executor(path: str, name: str) -> type:
    """The ``OptionExecutor`` class of the module file at ``path``, imported under the module name ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"cannot import {path!r} (expected an option_executor.py file)")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.OptionExecutor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("versions", nargs="+", help="name=path/to/option_executor.py")
    parser.add_argument("--env", default="randomwalk", choices=bench.ENV_KINDS)
    parser.add_argument("--blocks", type=int, default=400)
    parser.add_argument("--steps", type=int, default=16, help="steps per timed block")
    parser.add_argument("--quantile", type=float, default=0.02)
    a = parser.parse_args()
    args = argparse.Namespace(num_envs=16, num_options=4, num_actions=4, obs_dim=8)
    torch.set_num_threads(1)
    envs = {"none": bench.make_base_env(args, a.env)}
    for i, version in enumerate(a.versions):
        name, sep, path = version.partition("=")
        if not sep:
            raise ValueError(f"expected name=path, got {version!r}")
        executor = load_executor(path, f"_option_executor_{i}")
        torch.manual_seed(1)  # the same options for every version
        obs_dim = envs["none"].observation_spec["observation"].shape[-1]
        options = TensorDictModule(
            bench.MLPOptions(obs_dim, args.num_options, args.num_actions),
            in_keys=["observation"],
            out_keys=["option_logits", "termination_logits"],
        )
        envs[name] = bench.make_base_env(args, a.env).append_transform(executor(options, num_options=args.num_options))
    actions = {key: [env.action_spec.rand() for _ in range(64)] for key, env in envs.items()}
    tds = {key: env.reset() for key, env in envs.items()}
    times = {key: [] for key in envs}
    with torch.no_grad():
        for block in range(a.blocks):
            for key, env in envs.items():
                td = tds[key]
                start = time.perf_counter()
                for step in range(a.steps):
                    td.set("action", actions[key][(block * a.steps + step) % 64])
                    _, td = env.step_and_maybe_reset(td)
                times[key].append((time.perf_counter() - start) / a.steps * 1e6)
                tds[key] = td

    def low(values: list[float]) -> float:
        return sorted(values)[int(len(values) * a.quantile)]

    base = low(times["none"])
    print(f"{a.env}, 16 envs, K=4: per env step (us), {a.quantile:.0%} quantile of {a.blocks} blocks of {a.steps}")
    for key, values in times.items():
        extra = "" if key == "none" else f"  (+{low(values) - base:.0f} over the bare env)"
        print(f"  {key:<12} {low(values):7.1f}{extra}")


if __name__ == "__main__":
    main()
