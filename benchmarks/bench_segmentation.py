"""Segmentation of demonstrations with planted skills: DDO boundaries against the ground truth.

The paper's third use of DDO (Fox et al., 2017, section 5.3) scores boundaries by the fraction of predicted
boundaries with exactly one reference boundary within a window (72% for DDO on surgical data, 14% for random
boundaries). This script does the same on two generators with known boundaries:

- ``continuous``: :func:`~torchrl_options.segmentation.reach_grasp_demonstrations`, pick-and-place with four
  skills and Gaussian action noise (about 31 steps per segment); Gaussian options.
- ``gridworld``: :func:`~torchrl_options.segmentation.gridworld_subgoal_demonstrations`, tours of the four-rooms
  centres by a value-iteration supervisor with env noise 0.3 (about 19 steps per segment); discrete options.

The windows (+-2 steps for continuous, +-1 for the GridWorld) are about a sixth of a segment, like the paper's
300 ms window against surgical gestures lasting seconds. Each row is the mean (and min) over seeds of discovery
(different data and initialisation), next to random boundaries at the rate of the method's boundaries.

Run::

    python benchmarks/bench_segmentation.py                  # both benchmarks, 3 seeds
    python benchmarks/bench_segmentation.py --benchmarks continuous --seeds 1
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchrl_options import discover_options
from torchrl_options.segmentation import (
    boundary_metrics,
    gridworld_subgoal_demonstrations,
    random_baseline,
    reach_grasp_demonstrations,
    segment,
)

SETTINGS = {
    "continuous": dict(
        make=lambda n, seed: reach_grasp_demonstrations(n, seed=seed),
        window=2,
        discovery=dict(action_space="continuous", meta_control="learned", num_cells=16, num_iterations=300, lr=0.01),
    ),
    "gridworld": dict(
        make=lambda n, seed: gridworld_subgoal_demonstrations(n, 200, seed=seed),
        window=1,
        discovery=dict(action_space="categorical", meta_control="uniform", num_cells=16, num_iterations=300, lr=0.01),
    ),
}


def run_one(name: str, seed: int, num_trajectories: int, num_iterations: int | None) -> dict:
    s = SETTINGS[name]
    data = s["make"](num_trajectories, seed)
    kwargs = dict(s["discovery"])
    if num_iterations is not None:
        kwargs["num_iterations"] = num_iterations
    start = time.perf_counter()
    result = discover_options(data, 4, seed=seed, progress=False, return_info=True, **kwargs)
    seconds = time.perf_counter() - start
    seg = segment(data, result)
    lengths = data["collector", "mask"].sum(1)
    ref = data["true_switch"]
    m = boundary_metrics(seg.boundary_mask, ref, s["window"], lengths=lengths)
    base = random_baseline(ref, lengths, s["window"], m["rate"], num_samples=200, generator=seed)
    return dict(m, random=base, seconds=seconds, segment_length=float(lengths.sum() / ref.sum()),
                kwargs=kwargs, steps=int(lengths.sum()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--benchmarks", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--trajectories", type=int, default=32)
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    for name in args.benchmarks:
        runs = [run_one(name, seed, args.trajectories, args.iterations) for seed in range(args.seeds)]
        for seed, r in enumerate(runs):
            print(f"# {name} seed {seed}: accuracy {r['accuracy']:.3f} precision {r['precision']:.3f} "
                  f"recall {r['recall']:.3f} f1 {r['f1']:.3f} random {r['random']['accuracy']:.3f} "
                  f"({r['seconds']:.0f} s)", flush=True)
        rows.append((name, runs))

    print()
    print("| benchmark | data | window | boundary accuracy | precision | recall | F1 | random accuracy | random F1 |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, runs in rows:
        r0 = runs[0]
        data = (f"{args.trajectories} traj., {r0['steps']} steps, "
                f"{np.mean([r['segment_length'] for r in runs]):.0f} steps/segment")

        def cell(key, sub=None):
            vals = np.array([r[sub][key] if sub else r[key] for r in runs], dtype=float)
            return f"{np.nanmean(vals):.3f} (min {np.nanmin(vals):.3f})" if len(vals) > 1 else f"{vals[0]:.3f}"

        print(f"| {name} | {data} | +-{SETTINGS[name]['window']} | {cell('accuracy')} | {cell('precision')} | "
              f"{cell('recall')} | {cell('f1')} | {cell('accuracy', 'random')} | {cell('f1', 'random')} |")
    print()
    for name, runs in rows:
        k = runs[0]["kwargs"]
        print(f"- {name}: K=4, {k}, mean discovery time {np.mean([r['seconds'] for r in runs]):.0f} s "
              f"({args.threads} thread(s)), seeds 0..{args.seeds - 1}")


if __name__ == "__main__":
    main()
