"""Discovery on the planted suite: does ``discover_options`` with its defaults reach the Bayes ceiling?

For every problem of :data:`torchrl_options.testing.planted_suite.PLANTED_SUITE` (and the planted two-level
hierarchy, with ``discover_hierarchy``) and every seed, demonstrations are drawn, the truth's own posterior gives the
Bayes ceiling (accuracy of its most likely option per step, and its log-likelihood per step), and options are
discovered with nothing but ``num_options`` and ``seed`` set (``defaults``) and, side by side, with the paper's
four-rooms settings (``paper``: :data:`torchrl_options.discovery.PAPER_SETTINGS`). Per problem and setting it prints
the ceiling, the mean and worst discovered accuracy (best relabelling), the worst gap to the ceiling in points,
the mean log-likelihood gap to the truth (nats per step; negative: below the truth), how many seeds are ``near``
the ceiling (within 2 points and at or above the truth's likelihood minus 1e-3 nats per step), how many reach a
likelihood at or above the truth's (``ll>=``: a labelling far from the ceiling with such a likelihood means the
problem is not identifiable at this data size, not a local optimum), and the CPU time per 10,000 steps.

    python benchmarks/bench_planted_suite.py                      # every problem, seeds 0-9, both settings
    python benchmarks/bench_planted_suite.py --problems landmarks-3 --seeds 0 1 --settings defaults
    python benchmarks/bench_planted_suite.py --csv results.csv    # also one row per run
    python benchmarks/bench_planted_suite.py --problems walls-4 --data-factor 4   # 4x the trajectories

``--set key=value`` overrides a ``discover_options`` argument for a setting named ``custom`` (values parsed as
Python literals), to try candidates against the same suite.
"""
from __future__ import annotations

import argparse
import ast
import csv
import logging
import time

import torch

from torchrl_options import DDOLoss
from torchrl_options.discovery import discover_options, PAPER_SETTINGS
from torchrl_options.hierarchy import discover_hierarchy, hierarchical_forward_backward, HierarchicalDDOLoss
from torchrl_options.testing import planted_two_level_demonstrations, planted_two_level_log_probabilities
from torchrl_options.testing.planted_suite import best_matching_accuracy, PLANTED_SUITE, posterior_accuracy

TWO_LEVEL = "two-level-4x4"


def run_flat(problem, seed: int, settings: dict, data_factor: int = 1) -> dict:
    data, truth = problem.make(seed)
    if data_factor != 1:  # the same problem, more trajectories
        data, truth = problem.make(seed, data_factor * data.shape[0])
    ceiling, truth_ll = problem.ceiling(data, truth)
    start = time.process_time()
    result = discover_options(
        data, problem.num_options, action_space=problem.action_space, seed=seed, progress=False, return_info=True,
        **settings,
    )  # fmt: skip
    cpu = time.process_time() - start
    loss = DDOLoss(result.options, result.meta_control, action_space=problem.action_space)
    with torch.no_grad():
        acc, ll = posterior_accuracy(loss.log_probabilities(data), data["true_option"])
    steps = int(data["collector", "mask"].sum())
    return dict(ceiling=ceiling, accuracy=acc, ll=ll, truth_ll=truth_ll, cpu_per_10k=cpu * 1e4 / steps,
                warnings=len(result.warnings) if hasattr(result, "warnings") else 0)  # fmt: skip


def run_two_level(seed: int, settings: dict, data_factor: int = 1) -> dict:
    data = planted_two_level_demonstrations(64 * data_factor, 60, seed=seed)
    post = hierarchical_forward_backward(**planted_two_level_log_probabilities(data), marginals=True)
    ceiling = best_matching_accuracy(post.most_likely(2), data["true_option_2"])
    truth_ll = post.log_likelihood.sum().item() / data.numel()
    hier_settings = {k: v for k, v in settings.items() if k not in ("tol", "patience") or v is not None}
    start = time.process_time()
    hierarchy = discover_hierarchy(data, [4, 4], seed=seed, progress=False, **hier_settings)
    cpu = time.process_time() - start
    loss = HierarchicalDDOLoss(hierarchy.options(2), hierarchy.levels[:1], num_actions=4)
    with torch.no_grad():
        p = loss.posterior(data)
        ll = loss(data)["log_likelihood_per_step"].item()
    acc = best_matching_accuracy(p.most_likely(2), data["true_option_2"])
    return dict(ceiling=ceiling, accuracy=acc, ll=ll, truth_ll=truth_ll, cpu_per_10k=cpu * 1e4 / data.numel(),
                warnings=0)  # fmt: skip


def near(row: dict) -> bool:
    """Within 2 points of the ceiling and at or above the truth's likelihood minus 1e-3 nats per step."""
    return row["ceiling"] - row["accuracy"] <= 0.02 and row["ll"] >= row["truth_ll"] - 1e-3


def above(row: dict) -> bool:
    """At or above the truth's likelihood: no better optimum left to find, whatever the labels (where the
    labelling is far from the ceiling, the problem is not identifiable at this data size)."""
    return row["ll"] >= row["truth_ll"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [p.name for p in PLANTED_SUITE] + [TWO_LEVEL]
    parser.add_argument("--problems", nargs="+", default=names, choices=names)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--settings", nargs="+", default=["defaults", "paper"], choices=["defaults", "paper", "custom"])
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="for --settings custom")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--csv", help="also write one row per run to this file")
    parser.add_argument("--data-factor", type=int, default=1,
                        help="draw this many times each problem's trajectories (is a missed labelling found with more "
                             "data? then the problem is not identifiable at the suite's data size)")
    parser.add_argument("--verbose", action="store_true", help="one line per run")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.ERROR)
    custom = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    presets = {"defaults": {}, "paper": dict(PAPER_SETTINGS), "custom": custom}
    rows = []
    if args.data_factor < 1:
        parser.error(f"--data-factor must be a positive integer, got {args.data_factor}")
    factor = f", {args.data_factor}x the trajectories" if args.data_factor != 1 else ""
    print(f"torch {torch.__version__}, {args.threads} thread(s), seeds {args.seeds}{factor}")
    header = (f"{'problem':<14} {'setting':<9} {'ceiling':>7} {'found':>6} {'worst':>6} {'gap pts':>7} "
              f"{'dll/step':>9} {'near':>6} {'ll>=':>6} {'cpu s/10k':>9}")  # fmt: skip
    print(header)
    print("-" * len(header))
    for name in args.problems:
        problem = next((p for p in PLANTED_SUITE if p.name == name), None)
        for setting in args.settings:
            runs = []
            for seed in args.seeds:
                if problem is None:
                    row = run_two_level(seed, presets[setting], args.data_factor)
                else:
                    row = run_flat(problem, seed, presets[setting], args.data_factor)
                row.update(problem=name, setting=setting, seed=seed)
                runs.append(row)
                if args.verbose:
                    print(f"  {name} {setting} seed {seed}: ceiling {row['ceiling']:.3f} found {row['accuracy']:.3f} "
                          f"dll {row['ll'] - row['truth_ll']:+.4f} cpu/10k {row['cpu_per_10k']:.1f}s", flush=True)
            rows += runs
            n = len(runs)
            mean = lambda k: sum(r[k] for r in runs) / n  # noqa: E731
            worst_gap = max(r["ceiling"] - r["accuracy"] for r in runs)
            print(f"{name:<14} {setting:<9} {mean('ceiling'):>7.3f} {mean('accuracy'):>6.3f} "
                  f"{min(r['accuracy'] for r in runs):>6.3f} {100 * worst_gap:>7.1f} "
                  f"{mean('ll') - mean('truth_ll'):>+9.4f} {sum(map(near, runs)):>3}/{n:<2} {sum(map(above, runs)):>3}/{n:<2} "
                  f"{mean('cpu_per_10k'):>9.1f}",
                  flush=True)  # fmt: skip
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
