"""Is a planted problem's miss a local optimum, over-fitting, or a labelling the data cannot tell apart?

For each seed, the problem's demonstrations are split 80 / 20 by trajectory; options are fitted on the 80% and
scored, on both parts, by their labels (best matching accuracy of the posterior's most likely option) and their
log-likelihood per step, next to the truth's own (its posterior: the Bayes ceiling). Three ways to fit:

* ``fit``: ``discover_options`` with the defaults (and any ``--set`` overrides);
* ``oracle``: the options first cloned from the *true* labels (policies on the true option's steps, terminations on
  the true switches), then ``discover_options`` from there (one start): where the likelihood has an optimum next to
  the truth, and how high it is;
* ``anneal``: a tempered E-step (posterior proportional to the joint to the power ``beta``, ``beta`` rising
  linearly from ``--beta0`` to 1 over ``--anneal`` iterations, then 1), patched into the tabulated E-step for this
  experiment only (the package has no such option).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/diagnose_planted_optimum.py --problem landmarks-8 --seeds 0 1 2 --mode fit
    OMP_NUM_THREADS=1 python benchmarks/diagnose_planted_optimum.py --problem landmarks-8 --seeds 0 1 2 --mode oracle
    OMP_NUM_THREADS=1 python benchmarks/diagnose_planted_optimum.py --problem landmarks-8 --seeds 0 1 2 --mode anneal \
        --set '{"restarts": 1, "tol": null, "num_iterations": 600}'

One JSON line per seed (``--out`` appends them to a file as well).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

import torchrl_options.discovery.tabulated as tabulated
from torchrl_options import DDOLoss, discover_options
from torchrl_options.discovery import clone_from_labels, default_options
from torchrl_options.testing.planted_suite import PLANTED_SUITE, posterior_accuracy


def split(num_rows: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(train, held_out)`` row indices: 20% held out, drawn from the seed."""
    perm = torch.randperm(num_rows, generator=torch.Generator().manual_seed(1000 + seed))
    held = num_rows // 5
    return perm[held:], perm[:held]


def oracle_options(train, num_options: int, num_cells: int, action_space: str, steps: int = 1500,
                   termination_cells=None):
    """Options cloned from the true labels: each policy on its option's steps, each termination on the true switches.

    The options are the ones ``discover_options`` builds when none are given (:func:`default_options`), fitted by
    :func:`clone_from_labels` (the pre-training of segment starts) on the true option of every step and the true
    switches (``"true_switch"``: an option starts at the step), for ``steps`` Adam steps.
    """
    options = default_options(train, num_options, action_space=action_space, num_cells=num_cells,
                              termination_cells=termination_cells)
    mask = train["collector", "mask"]
    clone_from_labels(options, train, mask, train["true_option"].clamp_min(0), train["true_switch"],
                      action_space=action_space, num_steps=steps)  # fmt: skip
    return options


def tempered_e_step(beta0: float, anneal: int, counter: list[int]):
    """The tabulated E-step's ``forward_backward`` with marginals at temperature ``beta`` (likelihood untempered)."""
    plain = tabulated.forward_backward

    def forward_backward(log_pi, log_term, log_cont, log_eta, mask, terminal, **kwargs):
        beta = min(1.0, beta0 + (1.0 - beta0) * counter[0] / anneal)
        counter[0] += 1
        out = plain(log_pi, log_term, log_cont, log_eta, mask, terminal, **kwargs)
        if beta >= 1.0:
            return out
        hot = plain(beta * log_pi, beta * log_term, beta * log_cont, beta * log_eta, mask, terminal, **kwargs)
        return dataclasses.replace(hot, log_likelihood=out.log_likelihood)

    return forward_backward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--problem", default="landmarks-8", choices=[p.name for p in PLANTED_SUITE])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--mode", choices=["fit", "oracle", "anneal"], default="fit")
    parser.add_argument("--set", default="{}", help="discover_options overrides, as JSON")
    parser.add_argument("--beta0", type=float, default=0.2)
    parser.add_argument("--anneal", type=int, default=300)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    problem = next(p for p in PLANTED_SUITE if p.name == args.problem)
    overrides = json.loads(args.set)
    counter = [0]
    if args.mode == "anneal":
        tabulated.forward_backward = tempered_e_step(args.beta0, args.anneal, counter)
    for seed in args.seeds:
        counter[0] = 0
        data, truth = problem.make(seed)
        train_rows, held_rows = split(data.batch_size[0], seed)
        kwargs = dict(seed=seed, progress=False, return_info=True, action_space=problem.action_space, **overrides)
        if args.mode == "oracle":
            torch.manual_seed(seed)
            kwargs["options"] = oracle_options(data[train_rows], problem.num_options, kwargs.pop("num_cells", 8),
                                               problem.action_space,
                                               termination_cells=kwargs.pop("termination_cells", None))  # fmt: skip
            kwargs["restarts"] = 1
        start = time.process_time()
        result = discover_options(data[train_rows], problem.num_options, **kwargs)
        cpu = time.process_time() - start
        loss = DDOLoss(result.options, result.meta_control, action_space=problem.action_space)
        row = {"problem": problem.name, "mode": args.mode, "set": overrides, "seed": seed, "cpu_s": round(cpu, 1),
               "iterations": len(result.history)}  # fmt: skip
        if args.mode == "anneal":
            row.update(beta0=args.beta0, anneal=args.anneal)
        if result.split_merge_moves:
            row["split_merge_moves"] = [
                [m["victim"], m["donor"], round(m["log_likelihood_before"], 5), round(m["log_likelihood_after"], 5),
                 m["accepted"]]
                for m in result.split_merge_moves
            ]  # fmt: skip
        for part, rows in (("train", train_rows), ("held_out", held_rows)):
            d = data[rows]
            with torch.no_grad():
                fitted = loss.log_probabilities(d)
            fit_acc, fit_ll = posterior_accuracy(fitted, d["true_option"])
            true_part = {k: v[rows] if torch.is_tensor(v) and v.dim() >= 1 else v for k, v in truth.items()}
            true_acc, true_ll = posterior_accuracy(true_part, d["true_option"])
            row[part] = {"accuracy": round(fit_acc, 4), "ceiling": round(true_acc, 4),
                         "ll_vs_truth": round(fit_ll - true_ll, 4)}  # fmt: skip
        line = json.dumps(row)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    main()
