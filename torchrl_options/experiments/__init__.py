"""What the recipes share: resumable results (and the settings they were made with), summaries with Student-t
intervals over seeds and paired comparisons, aggregates over tasks (Agarwal et al. 2021), learning-curve plots."""
from torchrl_options.experiments.aggregates import (
    aggregate_scores,
    aggregates_markdown,
    Aggregates,
    interquartile_mean,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap_interval,
)
from torchrl_options.experiments.intervals import interval_verdict, mean_interval, paired_difference_interval
from torchrl_options.experiments.plotting import plot_aggregates, plot_curves
from torchrl_options.experiments.run_settings import check_run_settings
from torchrl_options.experiments.sweep import Cell, CellResult, run_sweep
from torchrl_options.experiments.results import (
    BaselineComparison,
    compare_to_baseline,
    comparison_markdown,
    ConditionSummary,
    episodes_to_reach,
    merge_results,
    ResultsLog,
    summarize,
    summary_markdown,
)

__all__ = [
    "aggregate_scores",
    "Aggregates",
    "aggregates_markdown",
    "BaselineComparison",
    "compare_to_baseline",
    "comparison_markdown",
    "interquartile_mean",
    "interval_verdict",
    "mean_interval",
    "paired_difference_interval",
    "performance_profile",
    "plot_aggregates",
    "probability_of_improvement",
    "stratified_bootstrap_interval",
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
