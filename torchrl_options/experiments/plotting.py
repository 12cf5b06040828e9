"""Learning curves of the recipes: mean return and bootstrap interval per condition (matplotlib, headless)."""
from __future__ import annotations

import os
from collections import defaultdict

import numpy as np

from torchrl_options.experiments.results import ResultsLog, smooth

__all__ = ["plot_curves"]


def plot_curves(
    log: ResultsLog,
    path: str | os.PathLike,
    *,
    smooth_window: int = 50,
    confidence: float = 0.95,
    num_resamples: int = 500,
    title: str | None = None,
) -> None:
    """Writes ``curves.png``: one panel per setting, per condition the mean (over seeds) of the smoothed returns
    with a percentile-bootstrap interval over seeds.

    Needs matplotlib (the ``recipes`` extra).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = log.rows()
    data: dict[str, dict[str, dict[int, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in sorted(rows, key=lambda r: (r["setting"], r["condition"], r["seed"], r["episode"])):
        data[r["setting"]][r["condition"]][r["seed"]].append(r["return"])
    settings = list(data)
    fig, axes = plt.subplots(1, max(len(settings), 1), figsize=(6 * max(len(settings), 1), 4), squeeze=False)
    rng = np.random.default_rng(0)
    alpha = (1 - confidence) / 2
    for ax, setting in zip(axes[0], settings):
        for condition, seeds in data[setting].items():
            n = min(len(v) for v in seeds.values())
            curves = np.stack([smooth(v[:n], smooth_window) for v in seeds.values()])
            mean = curves.mean(0)
            idx = rng.integers(0, curves.shape[0], size=(num_resamples, curves.shape[0]))
            boot = curves[idx].mean(1)
            lo, hi = np.quantile(boot, alpha, axis=0), np.quantile(boot, 1 - alpha, axis=0)
            x = np.arange(1, n + 1)
            ax.plot(x, mean, label=f"{condition} ({curves.shape[0]} seeds)")
            ax.fill_between(x, lo, hi, alpha=0.2)
        ax.set_title(setting if title is None else f"{title}: {setting}")
        ax.set_xlabel("episode")
        ax.set_ylabel(f"return ({smooth_window}-episode mean)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
