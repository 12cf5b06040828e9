"""Segmentation of the BabyAI bot's demonstrations by DDO, scored against the bot's subgoals (issue 50, stage 2).

One measurement per (level, method, seed): 100 bot demonstrations (seed s: layouts 1000 s ...), discover_options
with the method's settings, segment, the scores and the trivial baselines on the same data
(torchrl_options.experiments.minigrid.segmentation_cell). Each record is appended to --out as one JSON line, and
cells already there are skipped (resumable); the table of means with 95% Student-t intervals over the seeds is
printed at the end.

    OMP_NUM_THREADS=1 python benchmarks/diagnose_minigrid_segmentation.py --level BabyAI-UnlockPickup-v0 \
        --seeds 5 --method '{}' --out results/minigrid/segmentation/probe.jsonl     # issue 50's probe, 5 seeds
    ... --method '{"network": "conv", "num_options": 5}'                          # a conv net on the view
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time

import torch

from torchrl_options.experiments.minigrid.segmentation import segmentation_cell
from torchrl_options.experiments.minigrid.summary import (
    append_record,
    composition_markdown,
    method_label,
    read_records,
    segmentation_markdown,
)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", action="append", required=True, help="BabyAI level (repeatable)")
    parser.add_argument("--seeds", type=int, default=5, help="seeds 0 .. N-1")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--method", action="append", default=None, help="JSON dict of settings (repeatable)")
    parser.add_argument("--demonstrations", type=int, default=100)
    parser.add_argument("--out", required=True, help="a .jsonl file; its cells are skipped")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    try:
        methods = [json.loads(m) for m in (args.method or ["{}"])]
    except json.JSONDecodeError as err:
        print(f"error: --method must be a JSON dict: {err}", file=sys.stderr)
        return 2
    done = {(r["level"], method_label(r["method"]), r["seed"]) for r in read_records(args.out)}
    for level in args.level:
        for method in methods:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                full = {"network": "mlp", "num_options": 5, **method}
                if full["network"] != "mlp":  # the record names the default starts of option_factory's modules
                    full.setdefault("starts", "factory")
                label = method_label(full)
                if (level, label, seed) in done:
                    continue
                t0 = time.time()
                record = segmentation_cell(level, seed, method=method, num_demonstrations=args.demonstrations)
                record["wall_seconds"] = time.time() - t0
                append_record(args.out, record)
                d = record["subgoal"]["ddo"]
                print(f"{level} {label} seed {seed}: label acc {d['label_accuracy']:.3f}, F1+-2 {d['f1_w2']:.3f}, "
                      f"rate {d['boundary_rate']:.3f}, max usage {record['subgoal']['composition']['max_usage']:.2f}, "
                      f"{record['fit']['cpu_seconds']:.0f} CPU-s", flush=True)
    records = [r for r in read_records(args.out) if r["level"] in args.level]
    for granularity in ("subgoal", "skill"):
        print(f"\n## against the bot's {granularity}s (mean [95% Student-t interval] over seeds)\n")
        print(segmentation_markdown(records, granularity))
    print(composition_markdown(records, "subgoal"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
