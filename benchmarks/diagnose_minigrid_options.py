"""What the options of kept MiniGrid segmentation records track, when they are not the skills (issue 50).

For each record of --records (the JSON lines of benchmarks/diagnose_minigrid_segmentation.py, which keep the
options' Viterbi labels per step), the same demonstrations are made again (100 bot demonstrations, seed s: layouts
1000 s ...; the step count is checked against the record's) and
torchrl_options.experiments.minigrid.option_information measures how much of each target's entropy the option
explains: the skill, the subgoal, the bot's action, the turn's side, the heading and the carried object, and the
share of the turning steps held by one-sided options. One JSON line per record is appended to --out (records already
there are skipped: resumable); the table of means with 95% Student-t intervals over the seeds is printed at the end.

    OMP_NUM_THREADS=1 python benchmarks/diagnose_minigrid_options.py \
        --records results/minigrid/segmentation/round8_conv_learned_meta.jsonl \
        --records results/minigrid/segmentation/round10_new_levels.jsonl \
        --records results/minigrid/segmentation/round11_seeds_5_to_9.jsonl \
        --out results/minigrid/segmentation/option_information.jsonl
"""
from __future__ import annotations

import argparse
import logging
import sys

import torch

from torchrl_options.experiments.minigrid import bot_demonstrations, option_information
from torchrl_options.experiments.minigrid.segmentation import LAYOUTS_PER_SEED
from torchrl_options.experiments.minigrid.summary import append_record, information_markdown, method_label, read_records


def _padded(labels: list[list[int]], shape: tuple[int, int]) -> torch.Tensor:
    out = torch.zeros(shape, dtype=torch.long)
    for i, row in enumerate(labels):
        out[i, : len(row)] = torch.tensor(row, dtype=torch.long)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", action="append", required=True, help="a kept .jsonl of segmentation records")
    parser.add_argument("--level", action="append", default=None, help="only these levels (repeatable)")
    parser.add_argument("--demonstrations", type=int, default=100, help="the records' demonstrations per seed")
    parser.add_argument("--out", required=True, help="a .jsonl file; its records are skipped")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    records = [r for path in args.records for r in read_records(path)]
    records = [r for r in records if args.level is None or r["level"] in args.level]
    done = {(r["level"], method_label(r["method"]), r["seed"]) for r in read_records(args.out)}
    for r in records:
        key = (r["level"], method_label(r["method"]), r["seed"])
        if key in done:
            continue
        demos = bot_demonstrations(r["level"], args.demonstrations, first_seed=LAYOUTS_PER_SEED * r["seed"])
        data = demos.data
        if demos.num_steps != r["num_steps"] or len(r["labels"]) != data.shape[0]:
            print(f"error: {key}: the demonstrations made again have {demos.num_steps} steps in {data.shape[0]} "
                  f"trajectories, the record {r['num_steps']} in {len(r['labels'])}: not the record's data "
                  f"(--demonstrations?)", file=sys.stderr)
            return 2
        info = option_information(_padded(r["labels"], tuple(data.shape)), data)
        append_record(args.out, {"level": r["level"], "method": r["method"], "seed": r["seed"],
                                 "num_steps": r["num_steps"], "information": info})
        done.add(key)
        print(f"{key}: " + ", ".join(f"{k} {v:.3f}" for k, v in info.items()), flush=True)
    rows = [r for r in read_records(args.out) if args.level is None or r["level"] in args.level]
    print("\n## the share of each target's entropy that the option explains (mean [95% Student-t interval])\n")
    print(information_markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
