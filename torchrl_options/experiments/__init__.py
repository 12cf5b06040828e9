"""What the recipes share: resumable results (and the settings they were made with), summaries with bootstrap
intervals, learning-curve plots."""
from torchrl_options.experiments.plotting import plot_curves
from torchrl_options.experiments.run_settings import check_run_settings
from torchrl_options.experiments.sweep import Cell, CellResult, run_sweep
from torchrl_options.experiments.results import (
    bootstrap_ci,
    ConditionSummary,
    episodes_to_reach,
    merge_results,
    ResultsLog,
    summarize,
    summary_markdown,
)

__all__ = [
    "bootstrap_ci",
    "Cell",
    "check_run_settings",
    "CellResult",
    "run_sweep",
    "ConditionSummary",
    "episodes_to_reach",
    "merge_results",
    "plot_curves",
    "ResultsLog",
    "summarize",
    "summary_markdown",
]
