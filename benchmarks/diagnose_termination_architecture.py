"""How fast can a Gaussian option's termination network fit the planted step-shaped termination of gaussian-3?

The planted Gaussian options (``torchrl_options.testing.planted_gaussian_demonstrations``) terminate with
probability 0.95 within radius 0.12 of their goal and 0.02 elsewhere: a step in a continuous state. With the true
option of every step known, this script fits :class:`~torchrl_options.GaussianOptionsMLP` options by Adam (learning
rate 0.03 unless a variant sets ``lr``) on the complete-data log-likelihood along the true labels (each option's
actions on its steps, its termination at ``s_{t+1}`` on the true switches, both read from
:meth:`~torchrl_options.DDOLoss.log_probabilities`), and prints, per variant, the termination term minus the
truth's (nats per valid step) after 500, 1500 and 5000 steps, and the policy term minus the truth's at the end.
No E-step is involved: this isolates what the network can reach from what discovery finds.

A variant is a JSON object: ``cells`` (the hidden sizes of the networks), optional ``tcells`` (the termination
networks' own hidden sizes; drawn after the module, replacing its termination networks), ``act`` (activation,
default ``"tanh"``), ``lr``, ``xs`` (a factor on the observations) and ``steps``.

Usage (the runs kept in ``results/planted_suite/gaussian_termination_architectures.jsonl``)::

    OMP_NUM_THREADS=1 python benchmarks/diagnose_termination_architecture.py --seed 0 \
        --variants '[{"cells": 8, "steps": 5000}, {"cells": 8, "tcells": [16, 16], "steps": 5000}]'
"""
from __future__ import annotations

import argparse
import json
import time

import torch

from torchrl_options import DDOLoss, GaussianOptionsMLP
from torchrl_options.modules.options import _ensemble  # the ensemble GaussianOptionsMLP builds its networks with
from torchrl_options.testing.planted_suite import PLANTED_SUITE


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variants", required=True, help="a JSON list of variants (see the module docstring)")
    parser.add_argument("--out", default=None, help="also append the JSON lines to this file")
    args = parser.parse_args()
    torch.set_num_threads(1)
    problem = next(p for p in PLANTED_SUITE if p.name == "gaussian-3")
    seed = args.seed
    base, truth = problem.make(seed)
    mask = base["collector", "mask"]
    true_option = base["true_option"].clamp_min(0)[..., None]
    switch_next = torch.zeros_like(mask)
    switch_next[:, :-1] = base["true_switch"][:, 1:]
    has_next = mask.clone()
    has_next[:, :-1] &= mask[:, 1:]
    has_next[:, -1] = False

    def along(p: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(policy term, termination term) along the true labels, each per valid step."""
        policy = (p["log_pi"].gather(-1, true_option).squeeze(-1) * mask).sum() / mask.sum()
        term = torch.where(switch_next, p["log_term"].gather(-1, true_option).squeeze(-1),
                           p["log_cont"].gather(-1, true_option).squeeze(-1))  # fmt: skip
        return policy, (term * has_next).sum() / mask.sum()

    truth_policy, truth_term = along(truth)
    for v in json.loads(args.variants):
        data = base.clone()
        data["observation"] = base["observation"] * v.get("xs", 1.0)
        data["next", "observation"] = base["next", "observation"] * v.get("xs", 1.0)
        torch.manual_seed(seed)
        spread = min(max(float(data["action"][mask].std(0).mean()), 1e-2), 1.0)
        options = GaussianOptionsMLP(2, 2, 3, num_cells=v["cells"], activation=v.get("act", "tanh"), init_scale=spread,
                                     min_scale=min(1e-3, spread / 10))  # fmt: skip
        if "tcells" in v:
            options.termination = _ensemble(2, 1, 3, v["tcells"], v.get("act", "tanh"))
        loss = DDOLoss(options, action_space="continuous")
        optimizer = torch.optim.Adam(options.parameters(), lr=v.get("lr", 0.03))
        start, gaps = time.process_time(), {}
        for i in range(1, v["steps"] + 1):
            policy, term = along(loss.log_probabilities(data))
            objective = -(policy + term)
            optimizer.zero_grad()
            objective.backward()
            optimizer.step()
            if i in (500, 1500, 5000, 15000):
                gaps[i] = round(float(term.detach() - truth_term), 4)
        row = dict(seed=seed, **v, policy_gap=round(float(policy.detach() - truth_policy), 4), term_gap=gaps,
                   cpu=round(time.process_time() - start, 1))  # fmt: skip
        line = json.dumps(row)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    main()
