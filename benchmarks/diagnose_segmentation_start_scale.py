"""Does the Gaussian options' starting scale explain the continuous segmentation benchmark's drop?

Until 2026-12-05 fresh Gaussian options started at a standard deviation of 1.0; since then
:func:`~torchrl_options.discovery.default_options` starts them at the demonstrations' action spread, and
``bench_segmentation.py`` pins ``init_scale=1.0``. This script runs that benchmark's ``continuous`` problem (its
settings: one random start, 300 iterations, learning rate 0.01) on seeds 1-5 with ``init_scale=None`` (``spread``)
or ``init_scale=1.0`` (``scale1``, the benchmark as it is), and prints each seed's boundary accuracy, log-likelihood
per step and seconds.

Usage (the runs kept in ``results/segmentation/start_scale.txt``)::

    OMP_NUM_THREADS=1 python benchmarks/diagnose_segmentation_start_scale.py spread
    OMP_NUM_THREADS=1 python benchmarks/diagnose_segmentation_start_scale.py scale1

``--defaults`` runs ``discover_options`` with its defaults (only ``action_space="continuous"`` and the start scale
set) instead of the benchmark's settings. The kept ``scale1`` lines of 2026-12-05 were made before ``init_scale``
existed, by replacing the scale of options drawn at the spread (the same weights, a different draw of what comes
after them), so they differ from this script's ``scale1`` lines.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_segmentation  # noqa: E402


def main() -> None:
    mode = sys.argv[1] if len(sys.argv) > 1 else "spread"
    if mode not in ("spread", "scale1"):
        raise SystemExit(f"mode must be 'spread' or 'scale1', got {mode!r}")
    settings = bench_segmentation.SETTINGS["continuous"]
    if "--defaults" in sys.argv[2:]:  # discover_options' defaults instead of the benchmark's settings
        settings["discovery"] = dict(action_space="continuous")
    settings["discovery"]["init_scale"] = 1.0 if mode == "scale1" else None
    for seed in range(1, 6):
        r = bench_segmentation.run_one("continuous", seed, 32, None)
        print(mode, seed, round(r["accuracy"], 3), round(r["log_likelihood"], 4), round(r["seconds"], 1), flush=True)


if __name__ == "__main__":
    main()
