"""Quickstart: discover two options from planted demonstrations, inspect them, save them.

The demonstrations walk a 10-cell corridor under two planted options (one walks right, one walks left, each
with 20% action noise); DDO recovers them from the actions alone. Prints the discovery's figures, what each
option does and how well the posterior labels every step with its true option; writes ``options.pt`` to
``out_dir`` (default ``outputs/quickstart``) and nothing elsewhere.

Run: python recipes/quickstart.py [out_dir=PATH]
"""
import logging
import sys
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_options import DDOLoss, discover_options, forward_backward, load_options, most_likely_options, save_options
from torchrl_options.testing import label_accuracy, planted_corridor_demonstrations

DEFAULT_OUT_DIR = "outputs/quickstart"


def parse_args(argv: list[str]) -> dict[str, str]:
    """``key=value`` arguments, like the Hydra recipes; the only key is ``out_dir``."""
    settings = {"out_dir": DEFAULT_OUT_DIR}
    for arg in argv:
        key, sep, value = arg.partition("=")
        if not sep or key not in settings or not value:
            raise ValueError(f"quickstart takes out_dir=PATH (default {DEFAULT_OUT_DIR}), got {arg!r}.")
        settings[key] = value
    return settings


def main(argv: list[str] | None = None) -> dict:
    settings = parse_args(sys.argv[1:] if argv is None else list(argv))
    out_dir = Path(settings["out_dir"])
    logging.basicConfig(level=logging.WARNING)
    data = planted_corridor_demonstrations(num_trajectories=32, length=100, seed=0)
    result = discover_options(data, num_options=2, seed=0, return_info=True, progress=False)  # the defaults
    with torch.no_grad():
        p = DDOLoss(result.options).log_probabilities(data)
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
        labels = most_likely_options(fb.u)
        # what each option does: its action and termination probabilities at every corridor cell
        cells = torch.unique(data["observation"].reshape(-1, 2), dim=0)
        out = result.options(TensorDict(observation=cells, batch_size=[len(cells)]))
        p_right = torch.softmax(out["option_logits"], -1)[..., 1].mean(0)  # [K]
        p_stop = torch.sigmoid(out["termination_logits"])  # [cells, K], cells left to right
    accuracy = label_accuracy(labels, data["true_option"])
    with torch.no_grad():  # the returned options' own figures (the fit ends at its best iteration, not its last)
        last = {k: float(v) for k, v in DDOLoss(result.options)(data).items() if v.numel() == 1}
    print(f"Discovered {len(result.option_usage)} options from {data.batch_size[0]} demonstrations of "
          f"{data.batch_size[1]} steps in a 10-cell corridor:")  # fmt: skip
    for k, usage in enumerate(result.option_usage):
        direction = "right" if p_right[k] > 0.5 else "left"
        print(f"  option {k}: walks {direction} (P(right) = {float(p_right[k]):.2f}); terminates with probability "
              f"{float(p_stop[0, k]):.2f} at the left end, {float(p_stop[-1, k]):.2f} at the right end; "
              f"used at {usage:.0%} of the steps")  # fmt: skip
    print(f"Segmentation: {accuracy:.1%} of the steps labelled with their planted option (chance: about 50%).\n")
    print("| quantity | value |\n|---|---|")
    print(f"| log-likelihood per step | {last['log_likelihood_per_step']:.4f} |")
    print(f"| mean option duration (steps) | {last['option_duration']:.2f} |")
    print(f"| option usage entropy (nats) | {last['option_entropy']:.3f} |")
    print(f"| steps labelled with the planted option | {accuracy:.1%} |")
    print(f"| starts (log-likelihood per step) | {', '.join(f'{x:.4f}' for x in result.restart_log_likelihoods)} |")
    print(f"| option usage | {', '.join(f'{u:.2f}' for u in result.option_usage)} |")
    for warning in result.warnings:
        print(f"warning: {warning}")
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "options.pt"
    save_options(result.options, path)
    load_options(path)
    print(f"\nsaved the options to {path} (load them with torchrl_options.load_options)")
    return {"accuracy": accuracy, "usage": list(result.option_usage), "p_right": p_right.tolist(), "path": path}


if __name__ == "__main__":
    try:
        main()
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
