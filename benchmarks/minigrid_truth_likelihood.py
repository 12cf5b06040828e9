"""Does DDO's objective prefer the BabyAI bot's own subgoals? The likelihood of the truth's structure against what
DDO finds (issue 50's measured reason).

For each level and seed: 100 bot demonstrations (the layouts of ``segmentation_cell``'s seed), then

- ``ddo``: ``discover_options(data, 5)`` with its defaults (what rounds 1 and 6 of docs/experiments/minigrid.md
  score);
- ``truth-<granularity>``: options of the same family (:class:`~torchrl_options.OptionsMLP`, ``num_cells`` units,
  uniform meta-control) fitted with the bot's labels given: option ``h`` is the ``h``-th subgoal type (or skill),
  and an option terminates exactly where the bot's label switches, and at the end of an episode that terminates
  (maximum complete-data likelihood, full-batch Adam);
- ``one-option``: a single option fitted by behaviour cloning (K = 1: the likelihood of a reactive policy alone);
- the same with a learned meta-control (``-learned``: ``discover_options(meta_control="learned")``, and a
  :class:`~torchrl_options.MetaControlMLP` fitted to the bot's choices at each segment start).

Every model is then scored by the same marginal likelihood, ``held_out_log_likelihood`` (:class:`~torchrl_options.DDOLoss`'s
exact forward pass) on the same demonstrations (the quantity DDO maximises). If the truth's structure scores
below what DDO finds, no maximum-likelihood fit of these options can be expected to recover it.

    OMP_NUM_THREADS=1 python benchmarks/minigrid_truth_likelihood.py --level BabyAI-UnlockPickup-v0 --seeds 3 \
        --out results/minigrid/segmentation/truth_likelihood.jsonl

One JSON line per (level, seed), appended (finished cells are skipped).
"""
from __future__ import annotations

import argparse
import json
import os
import time

import torch
from tensordict import TensorDict


def _fit_with_labels(data, labels: torch.Tensor, switches: torch.Tensor, num_options: int, num_cells: int,
                     iterations: int, seed: int, learned_meta: bool = False):
    """An OptionsMLP (and, with ``learned_meta``, a MetaControlMLP) fitted to the complete-data likelihood with
    the option of every step and the switches given; returns ``(options, meta_control or None, complete-data
    log-likelihood per step)`` (with the uniform meta-control, its constant terms left out)."""
    from torchrl_options import MetaControlMLP, OptionsMLP

    torch.manual_seed(seed)
    mask = data["collector", "mask"].bool()
    n = int(mask.sum())
    obs, next_obs = data["observation"], data["next", "observation"]
    actions = data["action"].reshape(mask.shape).long().clamp_min(0)
    z = labels.clamp_min(0)
    # termination of the option of step t is read at s_{t+1}: the switch of step t + 1, where step t + 1 is valid
    term_valid = torch.zeros_like(mask)
    term_valid[:, :-1] = mask[:, 1:]
    term_target = torch.zeros(mask.shape)
    term_target[:, :-1] = switches[:, 1:].float()
    # an episode that ends by terminating ends its last option too (DDOLoss's terminal_at_end, the paper's model)
    last = mask & ~term_valid
    ended = last & data["next", "terminated"].reshape(mask.shape).bool()
    term_valid, term_target = term_valid | ended, torch.where(ended, 1.0, term_target)
    options = OptionsMLP(obs.shape[-1], 7, num_options, num_cells=num_cells)
    meta = MetaControlMLP(obs.shape[-1], num_options, num_cells=num_cells) if learned_meta else None
    params = list(options.parameters()) + ([] if meta is None else list(meta.parameters()))
    opt = torch.optim.Adam(params, lr=0.01)
    # the meta-control chooses at step 0 and after every termination: where a new label segment starts
    chosen = switches.clone()
    chosen[:, 0] = True
    chosen &= mask

    def complete_ll() -> torch.Tensor:
        out = options(TensorDict(observation=obs, batch_size=mask.shape))
        log_pi = out["option_logits"].log_softmax(-1)  # [B, T, K, A]
        log_pi = log_pi.gather(-2, z[..., None, None].expand(*z.shape, 1, log_pi.shape[-1])).squeeze(-2)
        log_pi = log_pi.gather(-1, actions[..., None]).squeeze(-1)
        term = options(TensorDict(observation=next_obs, batch_size=mask.shape))["termination_logits"]
        term = term.gather(-1, z[..., None]).squeeze(-1)
        bce = -torch.nn.functional.binary_cross_entropy_with_logits(term, term_target, reduction="none")
        total = torch.where(mask, log_pi, 0.0).sum() + torch.where(term_valid, bce, 0.0).sum()
        if meta is not None:
            log_eta = meta(TensorDict(observation=obs, batch_size=mask.shape))["meta_logits"].log_softmax(-1)
            total = total + torch.where(chosen, log_eta.gather(-1, z[..., None]).squeeze(-1), 0.0).sum()
        return total / n

    for _ in range(iterations):
        opt.zero_grad()
        loss = -complete_ll()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return options, meta, float(complete_ll())


def _marginal(options, data, meta_control=None) -> float:
    from torchrl_options.discovery.width import held_out_log_likelihood

    return held_out_log_likelihood(options, meta_control, data)


def truth_likelihood_cell(level: str, seed: int, *, num_demonstrations: int = 100, num_cells: int = 8,
                          iterations: int = 1500) -> dict:
    from torchrl_options import discover_options
    from torchrl_options.experiments.minigrid.demonstrations import bot_demonstrations
    from torchrl_options.experiments.minigrid.scoring import GRANULARITIES
    from torchrl_options.experiments.minigrid.segmentation import LAYOUTS_PER_SEED

    data = bot_demonstrations(level, num_demonstrations, first_seed=LAYOUTS_PER_SEED * seed).data
    mask = data["collector", "mask"].bool()
    record = {"level": level, "seed": seed, "num_steps": int(mask.sum()), "num_cells": num_cells, "models": {}}
    for meta_control, suffix in (("uniform", ""), ("learned", "-learned")):
        t0 = time.process_time()
        result = discover_options(data, 5, seed=seed, progress=False, return_info=True, meta_control=meta_control)
        record["models"]["ddo" + suffix] = {
            "num_options": 5, "marginal": _marginal(result.options, data, result.meta_control),
            "last_record": result.final_log_likelihood_per_step, "cpu_seconds": time.process_time() - t0,
            "option_usage": [float(u) for u in result.option_usage],
        }  # fmt: skip
        for name, (label_key, switch_key) in GRANULARITIES.items():
            raw = data[label_key].long()
            values = torch.unique(raw[mask])
            labels = torch.where(mask, torch.searchsorted(values, raw.clamp_min(int(values.min()))), -1)
            options, meta, complete = _fit_with_labels(data, labels, data[switch_key].bool() & mask, len(values),
                                                       num_cells, iterations, seed, learned_meta=bool(suffix))  # fmt: skip
            record["models"][f"truth-{name}{suffix}"] = {"num_options": len(values), "complete": complete,
                                                         "marginal": _marginal(options, data, meta)}  # fmt: skip
    zeros = torch.where(mask, 0, -1)
    options, _, complete = _fit_with_labels(data, zeros, torch.zeros_like(mask), 1, num_cells, iterations, seed)
    record["models"]["one-option"] = {"num_options": 1, "complete": complete, "marginal": _marginal(options, data)}
    return record


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--level", action="append", required=True)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--num-cells", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    done = set()
    if os.path.exists(args.out):
        with open(args.out) as f:
            done = {(r["level"], r["seed"], r["num_cells"]) for r in map(json.loads, f)}
    for level in args.level:
        for seed in range(args.seeds):
            if (level, seed, args.num_cells) in done:
                continue
            record = truth_likelihood_cell(level, seed, num_cells=args.num_cells, iterations=args.iterations)
            with open(args.out, "a") as f:
                f.write(json.dumps(record) + "\n")
            print(level, seed, {k: round(v["marginal"], 4) for k, v in record["models"].items()}, flush=True)


if __name__ == "__main__":
    main()
