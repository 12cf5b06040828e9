"""Quickstart: discover two options from planted demonstrations, inspect them, save them.

Run: python recipes/quickstart.py
"""
import logging
import os

import torch

from torchrl_options import DDOLoss, discover_options, forward_backward, load_options, most_likely_options, save_options
from torchrl_options.testing import label_accuracy, planted_corridor_demonstrations


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    data = planted_corridor_demonstrations(num_trajectories=32, length=100, seed=0)
    result = discover_options(data, num_options=2, seed=0, return_info=True)  # the defaults
    with torch.no_grad():
        p = DDOLoss(result.options).log_probabilities(data)
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
    accuracy = label_accuracy(most_likely_options(fb.u), data["true_option"])
    last = result.history[-1]
    print("| quantity | value |\n|---|---|")
    print(f"| log-likelihood per step | {last['log_likelihood_per_step']:.4f} |")
    print(f"| mean option duration (steps) | {last['option_duration']:.2f} |")
    print(f"| option usage entropy (nats) | {last['option_entropy']:.3f} |")
    print(f"| steps labelled with the planted option | {accuracy:.1%} |")
    print(f"| starts (log-likelihood per step) | {', '.join(f'{x:.4f}' for x in result.restart_log_likelihoods)} |")
    print(f"| option usage | {', '.join(f'{u:.2f}' for u in result.option_usage)} |")
    for warning in result.warnings:
        print(f"warning: {warning}")
    os.makedirs("outputs/quickstart", exist_ok=True)
    save_options(result.options, "outputs/quickstart/options.pt")
    load_options("outputs/quickstart/options.pt")
    print("saved to outputs/quickstart/options.pt")


if __name__ == "__main__":
    main()
