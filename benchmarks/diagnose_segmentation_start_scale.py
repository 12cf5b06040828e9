"""Does the Gaussian options' starting scale explain the continuous segmentation benchmark's drop?

Until 2026-12-05 fresh Gaussian options started at a standard deviation of 1.0; since then
:func:`~torchrl_options.discovery.default_options` starts them at the demonstrations' action spread. This script runs
``bench_segmentation.py``'s ``continuous`` benchmark (its settings: one random start, 300 iterations, learning rate
0.01) on seeds 1-5, either as it is (``spread``) or with the fresh options' scale put back to 1.0 (``scale1``: the
same weights, only the scale parameter replaced), and prints each seed's boundary accuracy and log-likelihood per step.

Usage (the runs kept in ``results/segmentation/start_scale.txt``)::

    OMP_NUM_THREADS=1 python benchmarks/diagnose_segmentation_start_scale.py spread
    OMP_NUM_THREADS=1 python benchmarks/diagnose_segmentation_start_scale.py scale1

``--defaults`` runs ``discover_options`` with its defaults (only ``action_space="continuous"`` set) instead of the
benchmark's settings.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_segmentation  # noqa: E402

import torchrl_options.discovery.discover as discover  # noqa: E402
from torchrl_options import GaussianOptionsMLP  # noqa: E402


def main() -> None:
    mode = sys.argv[1] if len(sys.argv) > 1 else "spread"
    if mode not in ("spread", "scale1"):
        raise SystemExit(f"mode must be 'spread' or 'scale1', got {mode!r}")
    if "--defaults" in sys.argv[2:]:  # discover_options' defaults instead of the benchmark's settings
        bench_segmentation.SETTINGS["continuous"]["discovery"] = dict(action_space="continuous")
    built = discover.default_options

    def default_options(data, num_options, **kwargs):
        options = built(data, num_options, **kwargs)
        if mode == "scale1" and isinstance(options, GaussianOptionsMLP):
            config = {k: v for k, v in options.config.items() if k not in ("in_keys", "out_keys")}
            config.update(init_scale=1.0, min_scale=1e-3)
            at_one = GaussianOptionsMLP(**config)
            at_one.load_state_dict({k: v for k, v in options.state_dict().items() if k != "raw_scale"}, strict=False)
            return at_one
        return options

    discover.default_options = default_options  # discover_options looks it up at call time
    for seed in range(1, 6):
        r = bench_segmentation.run_one("continuous", seed, 32, None)
        print(mode, seed, round(r["accuracy"], 3), round(r["log_likelihood"], 4), round(r["seconds"], 1), flush=True)


if __name__ == "__main__":
    main()
