"""What discovery costs as the demonstrations grow: seconds per iteration, the fixed cost and peak memory at 64k, 1M
and 10M steps, for today's in-memory path and the two streamed ones; the likelihood reached per wall-clock second
at 1M steps; and data-parallel iterations per second with 1 and 2 processes.

Data: planted corridor demonstrations (``torchrl_options.testing``), 1000 steps per trajectory, written once per
size into a demonstration buffer on disk (``--workdir``) by ``write_planted_corridor``, 1024 trajectories at a
time, so that the generator never holds 10M steps. Discovery: K = 8 options, the default 8-unit MLPs, one start
(``restarts=1, init="random"``), no stopping rule, ``--threads`` torch threads. The paths:

* ``memory``: today's path, ``discover_options`` on the whole ``[B, T]`` tensordict in memory (read from the same
  files), full batch, 5 G-steps per E-step;
* ``full``: streamed, every trajectory each iteration in E-step chunks of ``--chunk`` trajectories, the chunks'
  gradients summed (exactly the full-batch gradient), ``m_steps=1``;
* ``minibatch``: streamed, ``--batch`` trajectories per iteration, 5 G-steps per E-step, the stopping rule's
  likelihood on an evaluation set of ``--batch`` trajectories.

Every (path, size) cell runs in a fresh process, so its peak memory is its own: ``peak RSS`` is the process's
high-water mark of resident memory (``ru_maxrss``: it counts the memory-mapped files' pages it touched, which the
kernel can drop), ``peak anon`` the largest anonymous (heap) resident memory sampled every 20 ms, ``after import``
the resident memory once torch and the package are imported. Seconds per iteration: the median interval between the
ends of consecutive iterations (from the log records of ``log_every=1``); fixed cost: the time to the end of the
first iteration minus one iteration (checking, indexing, the door's sample, tabulation, compilation caches).

    python benchmarks/bench_discovery_scale.py                              # the cost table (64k, 1M, 10M)
    python benchmarks/bench_discovery_scale.py --sizes 64000,1024000 --paths memory,minibatch --iterations 10
    python benchmarks/bench_discovery_scale.py --curve --seconds 60        # likelihood per wall-clock second, 1M
    python benchmarks/bench_discovery_scale.py --processes 1,2             # data-parallel iterations per second
    python benchmarks/bench_discovery_scale.py --plan                       # communication vs compute, 8-64 GPUs
    python benchmarks/bench_discovery_scale.py --sizes 1024000 --device cuda  # the GPU path (benchmarks/gpu_check.sh)
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

LENGTH = 1000
K = 8
PATHS = ("memory", "full", "minibatch")
FIT_LOGGERS = ("torchrl_options.discovery.fit", "torchrl_options.discovery.stream_fit")


def _load() -> str:
    try:
        return "load average %.1f %.1f %.1f" % os.getloadavg()
    except OSError:  # pragma: no cover
        return "load average unavailable"


def _rss_kib(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


OVER_LIMIT = 3  # a cell's exit status when it was stopped at --max-gb


class _AnonPeak(threading.Thread):
    """Samples the process's anonymous resident memory (``RssAnon``) every 20 ms and keeps the largest; past
    ``limit_gb`` it ends the process (exit status :data:`OVER_LIMIT`), so that a cell never takes a shared machine's
    memory."""

    def __init__(self, limit_gb: float | None = None) -> None:
        super().__init__(daemon=True)
        self.peak, self.running = 0, True
        self.limit = None if limit_gb is None else int(limit_gb * 2**20)

    def run(self) -> None:
        while self.running:
            self.peak = max(self.peak, _rss_kib("RssAnon"))
            if self.limit is not None and self.peak > self.limit:
                print(f"stopped: anonymous resident memory {self.peak / 2**20:.2f} GB > --max-gb", file=sys.stderr,
                      flush=True)  # fmt: skip
                os._exit(OVER_LIMIT)
            time.sleep(0.02)


class _Iterations(logging.Handler):
    """The time at the end of each iteration (``fit_ddo`` / ``fit_stream`` log every iteration with
    ``log_every=1``), a snapshot of the watched modules there, and a time budget: past it, the run is stopped by
    raising :class:`_Budget` (a ``BaseException``, which logging does not swallow)."""

    def __init__(self, watched: list | None = None, budget: float | None = None, every: int = 1) -> None:
        super().__init__(logging.INFO)
        self.times: list[float] = []
        self.snapshots: list[tuple[float, dict]] = []
        self.watched, self.budget, self.every, self.start = watched, budget, every, time.perf_counter()

    def emit(self, record: logging.LogRecord) -> None:
        if " iteration " not in record.getMessage() or "converged" in record.getMessage():
            return
        now = time.perf_counter() - self.start
        self.times.append(now)
        if self.watched and (len(self.times) - 1) % self.every == 0:
            self.snapshots.append((now, {k: v.detach().clone() for k, v in self.watched[-1].state_dict().items()}))
        if self.budget is not None and now > self.budget:
            raise _Budget


class _Budget(BaseException):
    pass


def _listen(handler: logging.Handler) -> None:
    for name in FIT_LOGGERS:
        log = logging.getLogger(name)
        log.setLevel(logging.INFO)
        log.addHandler(handler)
        log.propagate = False


def _data_path(workdir: Path, steps: int) -> Path:
    return workdir / f"corridor-{steps}"


def _ensure_data(workdir: Path, steps: int) -> Path:
    """Writes ``steps // 1000`` planted corridor trajectories once (in a child process, 1024 at a time)."""
    path = _data_path(workdir, steps)
    if not (path / "demonstrations.json").exists():
        code = (
            "import shutil, sys; from torchrl_options.data import demonstration_buffer;"
            "from torchrl_options.testing import write_planted_corridor;"
            f"shutil.rmtree({str(path)!r}, ignore_errors=True);"
            f"write_planted_corridor(demonstration_buffer({steps}, path={str(path)!r}), {steps // LENGTH}, {LENGTH})"
        )
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True)
        print(f"wrote {steps} steps to {path} in {time.perf_counter() - t0:.1f} s", flush=True)
    return path


def _settings(path: str, args) -> dict:
    common = dict(num_iterations=args.iterations, restarts=1, init="random", tol=None, seed=0, progress=False,
                  return_info=True, log_every=1, device=args.device)  # fmt: skip
    if path == "memory":
        return common
    if path == "full":
        return dict(common, m_steps=1, chunk_trajectories=args.chunk)
    return dict(common, batch_size=args.batch, eval_trajectories=args.batch)


def _cell(args) -> None:
    """One (path, size) cell in this process: prints one JSON line."""
    import torch

    torch.set_num_threads(args.threads)
    from torchrl_options import discover_options
    from torchrl_options.data import open_demonstrations, TrajectoryReader

    path, steps = args.cell.split(",")
    steps = int(steps)
    after_import = _rss_kib("VmRSS")
    anon = _AnonPeak(args.max_gb)
    anon.start()
    buffer = open_demonstrations(_data_path(Path(args.workdir), steps))
    handler = _Iterations()
    _listen(handler)
    if path == "memory":
        reader = TrajectoryReader(buffer)
        data = reader.read(torch.arange(reader.num_trajectories))  # today's path: the whole data set in memory
        start = handler.start = time.perf_counter()
        result = discover_options(data, K, **_settings(path, args))
    else:
        start = handler.start = time.perf_counter()
        result = discover_options(buffer, K, **_settings(path, args))
    total = time.perf_counter() - start
    anon.running = False
    cuda = torch.device(args.device).type == "cuda"
    times = handler.times
    per = statistics.median(b - a for a, b in zip(times[:-1], times[1:])) if len(times) > 1 else times[0]
    print(json.dumps(dict(
        path=path, steps=steps, iterations=len(result.history), seconds=total, per_iteration=per,
        fixed=times[0] - per, peak_rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        peak_anon=max(anon.peak, _rss_kib("RssAnon")) / 2**20, after_import=after_import / 2**20,
        ll=result.final_log_likelihood_per_step, load=_load(), device=args.device,
        gpu_peak=torch.cuda.max_memory_allocated() / 2**30 if cuda else None,
        card=torch.cuda.get_device_name() if cuda else None,
    )), flush=True)  # fmt: skip


def _table(args) -> None:
    sizes = [int(s) for s in args.sizes.split(",")]
    workdir = Path(args.workdir)
    rows = []
    print(f"{os.cpu_count()} CPUs, {args.threads} thread(s), device {args.device}, {_load()} at start", flush=True)
    for steps in sizes:
        _ensure_data(workdir, steps)
        for path in args.paths.split(","):
            if path == "memory" and steps > args.memory_limit:
                rows.append(dict(path=path, steps=steps, skipped=True,
                                 why="not run: needs ~3 GB per 1M steps (--memory-limit)"))  # fmt: skip
                print(f"{path} {steps}: not run (the in-memory path needs ~3 GB per 1M steps; --memory-limit)", flush=True)
                continue
            iterations = args.big_iterations if steps >= 5_000_000 and path == "full" else args.iterations
            command = [sys.executable, __file__, "--cell", f"{path},{steps}", "--workdir", str(workdir),
                       "--iterations", str(iterations), "--threads", str(args.threads), "--batch", str(args.batch),
                       "--chunk", str(args.chunk), "--device", args.device]  # fmt: skip
            command += ["--max-gb", str(args.max_gb)]
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode == OVER_LIMIT:
                rows.append(dict(path=path, steps=steps, skipped=True, why=f"stopped above {args.max_gb} GB"))
                print(f"{path} {steps}: stopped above {args.max_gb} GB of anonymous resident memory", flush=True)
                continue
            if done.returncode != 0:
                raise RuntimeError(f"cell {path},{steps} failed:\n{done.stderr[-4000:]}")
            row = json.loads(done.stdout.strip().splitlines()[-1])
            rows.append(row)
            gpu = "" if row.get("gpu_peak") is None else f", {row['card']} peak {row['gpu_peak']:.2f} GiB allocated"
            print(f"{path} {steps}: {row['per_iteration']:.3f} s/iteration, fixed {row['fixed']:.1f} s, peak RSS "
                  f"{row['peak_rss']:.2f} GB{gpu} ({row['load']})", flush=True)  # fmt: skip
    print()
    gpu = args.device != "cpu"
    print(f"| path | steps | iterations | s per iteration | us per step and iteration | fixed cost [s] | peak RSS [GB] | "
          f"peak anon [GB] | after import [GB] |" + (" peak GPU allocated [GiB] |" if gpu else ""))  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|" if gpu else ""))
    for r in rows:
        if r.get("skipped"):
            print(f"| {r['path']} | {r['steps']:,} | {r.get('why', 'not run (memory)')} | | | | | | |")
            continue
        work = r["steps"] if r["path"] != "minibatch" else 2 * args.batch * LENGTH  # minibatch + evaluation set
        print(f"| {r['path']} | {r['steps']:,} | {r['iterations']} | {r['per_iteration']:.3f} | "
              f"{r['per_iteration'] / work * 1e6:.3f} | {r['fixed']:.1f} | {r['peak_rss']:.2f} | {r['peak_anon']:.2f} | "
              f"{r['after_import']:.2f} |" + (f" {r['gpu_peak']:.2f} |" if gpu else ""))  # fmt: skip
    print("\nus per step and iteration: seconds per iteration over the steps an iteration reads (minibatch: the "
          f"{args.batch}-trajectory minibatch and the evaluation set of as many)")


def _curve(args) -> None:
    """The full-data log-likelihood per step reached after each wall-clock budget, in-memory full batch against
    streamed minibatches (and streamed full batch), on the same 1M steps."""
    import torch

    torch.set_num_threads(args.threads)
    from torchrl_options import DDOLoss, discover_options
    from torchrl_options.data import open_demonstrations, TrajectoryReader
    from torchrl_options.discovery import TabulatedDDO
    from torchrl_options.modules import OptionsMLP

    steps = args.size
    path = _ensure_data(Path(args.workdir), steps)
    anon = _AnonPeak(args.max_gb)
    anon.start()
    buffer = open_demonstrations(path)
    reader = TrajectoryReader(buffer)
    data = reader.read(torch.arange(reader.num_trajectories))
    print(f"{steps} steps, {args.threads} thread(s), budget {args.seconds} s per path, {_load()} at start", flush=True)
    curves = {}
    for name in args.paths.split(","):
        watched: list = []

        def factory(**kwargs):
            options = OptionsMLP(2, 2, K, num_cells=8)
            watched.append(options)
            return options

        handler = _Iterations(watched, budget=args.seconds, every=args.snapshot_every)
        _listen(handler)
        settings = dict(_settings(name, args), num_iterations=100_000)
        handler.start = time.perf_counter()
        try:
            discover_options(data if name == "memory" else buffer, K, options_factory=factory, **settings)
        except _Budget:
            pass
        for log in FIT_LOGGERS:
            logging.getLogger(log).removeHandler(handler)
        curves[name] = (handler.times, handler.snapshots)
        print(f"{name}: {len(handler.times)} iterations in {handler.times[-1]:.1f} s ({_load()})", flush=True)
    marks = [m for m in (5, 10, 20, 30, 45, 60, 90, 120, 180, 240, 300) if m <= args.seconds]
    loss = DDOLoss(OptionsMLP(2, 2, K, num_cells=8))
    table = TabulatedDDO(loss, data)

    def full_ll(state: dict) -> float:
        loss.options.load_state_dict(state)
        return float(table.for_loss(loss).e_step()[0]["log_likelihood_per_step"])

    print()
    print("| seconds | " + " | ".join(f"{n}: iterations, log-likelihood per step (all {steps:,} steps)"
                                        for n in curves) + " |")  # fmt: skip
    print("|---:|" + "---:|" * len(curves))
    for mark in marks:
        cells = []
        for name, (times, snaps) in curves.items():
            done = [s for s in snaps if s[0] <= mark]
            if not done:
                cells.append("(fixed cost)")
                continue
            at = done[-1][0]
            cells.append(f"{sum(t <= at for t in times)}, {full_ll(done[-1][1]):.4f}")
        print(f"| {mark} | " + " | ".join(cells) + " |")
    print(f"\npeak anonymous resident memory of this process (all paths, the data and the evaluation table): "
          f"{anon.peak / 2**20:.2f} GB")


def _ddp_worker(rank: int, world: int, init_file: str, path: str, settings: dict, out: str) -> None:
    import torch
    import torch.distributed as dist

    torch.set_num_threads(1)
    from torchrl_options import discover_options
    from torchrl_options.data import open_demonstrations

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    handler = _Iterations()
    _listen(handler)
    try:
        buffer = open_demonstrations(path)
        handler.start = time.perf_counter()
        discover_options(buffer, K, distributed=world > 1, **settings)
    finally:
        dist.destroy_process_group()
    if rank == 0:
        times = handler.times
        Path(out).write_text(json.dumps(dict(times=times)))


def _processes(args) -> None:
    import tempfile

    import torch.multiprocessing as mp

    steps = args.size
    path = _ensure_data(Path(args.workdir), steps)
    print(f"{steps} steps, 1 thread per process, {os.cpu_count()} CPUs, {_load()} at start", flush=True)
    print("| path | processes | iterations | s per iteration | iterations per second | speed-up |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in ("minibatch", "full"):
        base = None
        for world in [int(w) for w in args.processes.split(",")]:
            settings = dict(_settings(name, args), num_iterations=args.iterations)
            with tempfile.TemporaryDirectory() as tmp:
                out = f"{tmp}/times.json"
                mp.spawn(_ddp_worker, args=(world, f"{tmp}/init", str(path), settings, out), nprocs=world, join=True)
                times = json.loads(Path(out).read_text())["times"]
            per = statistics.median(b - a for a, b in zip(times[:-1], times[1:]))
            base = base or per
            print(f"| {name} | {world} | {len(times)} | {per:.3f} | {1 / per:.2f} | {base / per:.2f}x |  ({_load()})",
                  flush=True)  # fmt: skip


def _conv_flops(layers, size: int) -> int:
    """Multiply-adds x 2 of a stack of (in, out, kernel, stride) convolutions on ``size`` x ``size`` frames."""
    flops = 0
    for c_in, c_out, k, stride in layers:
        size = (size - k) // stride + 1
        flops += 2 * size * size * c_out * c_in * k * k
    return flops


def _plan(args) -> None:
    """Communication against compute per iteration of data-parallel DDO on W GPUs: each rank holds N / W steps;
    per iteration it runs the E-step on them (the forward-backward messages and the networks' forward pass) and
    ``m_steps`` G-steps (forward + backward), each G-step ending in one all-reduce of the parameters' gradients."""
    import math

    import torch.nn as nn

    from torchrl_options import OptionsMLP

    def count(module):
        return sum(p.numel() for p in module.parameters())

    m = args.m_steps_plan
    nature = [(4, 32, 8, 4), (32, 64, 4, 2), (64, 64, 3, 1)]
    cnn = nn.Sequential(nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(), nn.Conv2d(64, 64, 3, 1),
                        nn.Flatten(), nn.Linear(3136, 512), nn.ReLU(), nn.Linear(512, 18 * K + K))  # fmt: skip
    cnn_forward = _conv_flops(nature, 84) + 2 * (3136 * 512 + 512 * (18 * K + K))
    mlp_small, mlp_ram = OptionsMLP(2, 2, K, num_cells=8), OptionsMLP(128, 18, K, num_cells=[64, 64])
    # (name, parameters, forward FLOPs per step): an MLP's forward is ~2 FLOPs per weight and sample
    models = [
        ("corridor MLP (K=8, 8 units)", count(mlp_small), 2 * count(mlp_small)),
        ("Atari-RAM MLP (K=8, [64, 64])", count(mlp_ram), 2 * count(mlp_ram)),
        ("Nature-CNN trunk + K=8 heads, 84x84x4", count(cnn), cnn_forward),
        ("8 separate Nature-CNN options", 8 * count(cnn), 8 * cnn_forward),
    ]
    flops_per_s, e_bytes_per_s = args.gpu_tflops * 1e12, args.gpu_bandwidth * 1e12 / args.e_step_floor_ratio
    e_step = 7 * K * 4 / e_bytes_per_s  # s per step: 4 inputs read, u, v, w written (float32), at the measured ratio
    links = {"intra": (5e-6, 200e9), "inter": (20e-6, 40e9)}  # (latency per hop [s], bus bandwidth [B/s])
    print(f"Assumed, not measured here: an all-reduce of S bytes over W GPUs takes min(ring, tree), ring = 2 (W - 1) a "
          f"+ 2 (W - 1) / W * S / B, tree = 2 log2(W) a + 2 S / B; W = 8 in one node (a = 5 us, B = 200 GB/s, "
          f"NVLink), W >= 16 across nodes (a = 20 us, B = 40 GB/s, 400 Gb/s InfiniBand per GPU); {m} all-reduces per "
          f"iteration (one per G-step, float32 gradients). Compute per step and iteration: the networks' forward in "
          f"the E-step and forward + backward (3x forward) in each of the {m} G-steps, (1 + 3 x {m}) x forward FLOPs, "
          f"at {args.gpu_tflops:g} TFLOP/s; the E-step's messages at {args.e_step_floor_ratio:g}x their memory floor "
          f"(7 x K x 4 B per step at {args.gpu_bandwidth:g} TB/s): {e_step * 1e9:.2f} ns per step at K = {K}. The "
          f"MLP rows count the forward per step, an upper bound: the tabulated E-step evaluates distinct states "
          f"only.")  # fmt: skip
    print()
    print("| options | parameters | all-reduced per iteration | compute per step [ns] | W | communication per "
          "iteration [ms] | steps per GPU for communication = 10% of compute | communication share at 10M steps "
          "| at 50M steps |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, n, forward in models:
        size = 4 * n
        per_step = (1 + 3 * m) * forward / flops_per_s + e_step
        for w in (8, 16, 32, 64):
            a, b = links["intra" if w <= 8 else "inter"]
            ring = 2 * (w - 1) * a + 2 * (w - 1) / w * size / b
            tree = 2 * math.log2(w) * a + 2 * size / b
            t = m * min(ring, tree)
            shares = [t / (t + total / w * per_step) for total in (10_000_000, 50_000_000)]
            print(f"| {name} | {n:,} | {m * size / 1e6:.3f} MB | {per_step * 1e9:.1f} | {w} | {t * 1e3:.2f} | "
                  f"{10 * t / per_step:,.0f} | {shares[0]:.1%} | {shares[1]:.1%} |")  # fmt: skip


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="64000,1024000,10240000", help="steps, comma-separated (1000 per trajectory)")
    p.add_argument("--size", type=int, default=1_024_000, help="--curve and --processes: steps")
    p.add_argument("--paths", default=",".join(PATHS), help="memory, full, minibatch (comma-separated)")
    p.add_argument("--iterations", type=int, default=10, help="iterations per cell")
    p.add_argument("--big-iterations", type=int, default=3, help="iterations of the streamed full batch from 5M steps")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch", type=int, default=64, help="minibatch: trajectories per iteration")
    p.add_argument("--chunk", type=int, default=64, help="full: trajectories per E-step chunk")
    p.add_argument("--memory-limit", type=int, default=2_000_000, help="skip the in-memory path above this many steps")
    p.add_argument("--workdir", default="/tmp/bench_discovery_scale", help="where the demonstration buffers go")
    p.add_argument("--curve", action="store_true", help="likelihood per wall-clock second at 1M steps")
    p.add_argument("--seconds", type=float, default=60.0, help="--curve: the wall-clock budget of each path")
    p.add_argument("--snapshot-every", type=int, default=1, help="--curve: snapshot the modules every n iterations")
    p.add_argument("--processes", default=None, help="data-parallel iterations per second, e.g. 1,2")
    p.add_argument("--plan", action="store_true", help="communication against compute per iteration on 8-64 GPUs")
    p.add_argument("--gpu-tflops", type=float, default=100.0, help="--plan: the networks' effective TFLOP/s per GPU")
    p.add_argument("--gpu-bandwidth", type=float, default=3.0, help="--plan: device memory TB/s (H100: ~3)")
    p.add_argument("--e-step-floor-ratio", type=float, default=8.5,
                   help="--plan: the E-step's time over its memory floor (8.5 on an H100, benchmarks/gpu_notes.md)")
    p.add_argument("--m-steps-plan", type=int, default=5, help="--plan: all-reduces per iteration")
    p.add_argument("--device", default="cpu", help="the training device of the table's cells (cpu, cuda)")
    p.add_argument("--max-gb", type=float, default=5.5, help="stop a cell above this anonymous resident memory")
    p.add_argument("--cell", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    Path(args.workdir).mkdir(parents=True, exist_ok=True)
    if args.cell:
        _cell(args)
    elif args.curve:
        _curve(args)
    elif args.processes:
        _processes(args)
    elif args.plan:
        _plan(args)
    else:
        _table(args)


if __name__ == "__main__":
    main()
