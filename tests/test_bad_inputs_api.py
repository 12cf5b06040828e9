"""The class of problem, not the examples (issue 53): every public function and class of every ``__all__`` is
tried with bad input by a table of tests/test_bad_inputs_*.py, or by a named older test, or is listed below with
the reason it takes no input to check. A new public name without either fails here."""
import importlib

import pytest

TABLES = [
    "test_bad_inputs_agents", "test_bad_inputs_data", "test_bad_inputs_discovery", "test_bad_inputs_envs",
    "test_bad_inputs_experiments", "test_bad_inputs_files", "test_bad_inputs_inference", "test_bad_inputs_modules",
    "test_bad_inputs_segmentation", "test_bad_inputs_streaming",
]  # fmt: skip
PACKAGES = [
    "torchrl_options", "torchrl_options.agents", "torchrl_options.data", "torchrl_options.discovery",
    "torchrl_options.envs", "torchrl_options.experiments", "torchrl_options.experiments.atari",
    "torchrl_options.hierarchy", "torchrl_options.inference", "torchrl_options.modules", "torchrl_options.objectives",
    "torchrl_options.segmentation", "torchrl_options.testing", "torchrl_options.transforms",
]  # fmt: skip

# tried by the tables of issue 26 (tests/test_bad_inputs_io.py) and by the modules' own tests
ELSEWHERE = {
    "as_trajectory_batch": "test_bad_inputs_io.py DISCOVERY",
    "discover_options": "test_bad_inputs_io.py DISCOVERY (issue 51 owns its newer arguments)",
    "discover_hierarchy": "test_bad_inputs_io.py DISCOVERY",
    "load_options": "test_bad_inputs_io.py FILES, test_bad_inputs_files.py",
    "load_hierarchy": "test_bad_inputs_io.py FILES, test_bad_inputs_files.py",
    "save_trajectories": "test_bad_inputs_io.py DISCOVERY, test_bad_inputs_files.py",
    "HierarchicalDDOLoss": "test_hierarchy_discovery.py",
    "DDOLossBase": "test_ddo_loss.py (DDOLoss is its subclass, tried in test_bad_inputs_modules.py)",
    "fit_ddo": "test_discovery.py (discovery/discover.py is issue 51's)",
    "default_options": "test_discovery.py (discovery/discover.py is issue 51's)",
    "converged_at": "test_discovery.py (discovery/discover.py is issue 51's)",
    "kmeans": "test_discovery.py (discovery/initialization.py is issue 51's)",
    "clone_from_labels": "test_discovery.py (discovery/initialization.py is issue 51's)",
    "pretrain_on_clusters": "test_discovery.py (discovery/initialization.py is issue 51's)",
    "pretrain_on_segments": "test_discovery.py (discovery/initialization.py is issue 51's)",
    "change_points": "test_bad_inputs_discovery.py NOT_HERE",
    "rewarded_segments": "test_data_segments.py (test_bad_input_is_refused_at_the_door)",
    "DiscoverySettings": "test_discovery_stages.py (test_settings_refuse_bad_values_when_made)",
    "Networks": "test_discovery_stages.py (test_networks_refuse_what_they_cannot_do)",
    "discover": "test_discovery_stages.py (test_networks_refuse_what_they_cannot_do); its data goes through discover_options' door",
    "hidden_sizes": "test_modules.py through OptionsMLP(num_cells=0 or [4, -1]) (the same check)",
    "EpisodicLife": "test_atari_env.py (a gymnasium wrapper of an ALE game)",
    "room_centers": "test_bad_inputs_segmentation.py through dead_ends (the same map reading)",
    "default_subgoals": "test_bad_inputs_segmentation.py through dead_ends (the same map reading)",
    "write_option_frames": "test_experiments_atari_pipeline.py (needs a trained agent and ALE)",
    "greedy_evaluation_markdown": "test_experiments_atari_summary.py (reads the cell files, as option_usage_markdown)",
    "atari_aggregates": "test_experiments_atari_summary.py (atari_scores and aggregate_scores are tried)",
    "aggregates_markdown": "test_aggregates.py (formats an Aggregates)",
    "comparison_markdown": "test_experiments.py (formats BaselineComparison rows)",
    "atari_summary_markdown": "test_experiments_atari_summary.py (formats AtariComparison rows)",
    "plot_aggregates": "test_aggregates.py (draws an Aggregates)",
}
# no input worth checking: results and records the package builds itself, exceptions, no-argument functions
NO_INPUT = {
    "DiscoveryResult", "ForwardBackwardOutput", "ViterbiOutput", "Segmentation", "OptionDiagnostics",
    "HierarchyDiscoveryResult", "HierarchyPosterior", "ConditionSummary", "BaselineComparison", "Aggregates",
    "AtariComparison", "BoundaryScores", "PlantedProblem", "GridMap",
    "StepLevelDataError", "TrajectoryFileError", "available_maps",
}  # fmt: skip


def public_callables() -> dict[str, str]:
    names = {}
    for package in PACKAGES:
        module = importlib.import_module(package)
        for name in module.__all__:
            obj = getattr(module, name)
            if callable(obj):
                names.setdefault(name, package)
    return names


def tried() -> set[str]:
    names = set()
    for table in TABLES:
        module = importlib.import_module(table)
        for rows in (getattr(module, "CASES", []), getattr(module, "FILES", [])):
            names |= {row[0].split(".")[0] for row in rows}
    return names


def test_every_public_callable_is_tried_with_bad_input():
    covered = tried() | set(ELSEWHERE) | NO_INPUT
    missing = sorted(f"{package}.{name}" for name, package in public_callables().items() if name not in covered)
    assert not missing, f"public names without a bad-input case: {missing}"


def test_the_lists_name_public_callables_only():
    stale = sorted((set(ELSEWHERE) | NO_INPUT) - set(public_callables()))
    assert not stale, f"listed but not public: {stale}"


@pytest.mark.parametrize("table", TABLES)
def test_each_table_has_controls_and_distinct_cases(table):
    module = importlib.import_module(table)
    rows = list(getattr(module, "CASES", [])) + list(getattr(module, "FILES", []))
    assert any(row[3] is None for row in rows), f"{table} has no control (an input that must be accepted)"
    keys = [(row[0], row[1]) for row in rows]
    assert len(keys) == len(set(keys)), f"{table} repeats a case"


def test_case_count():
    """The count reported for issue 53 (rows of the new tables; controls included)."""
    rows = sum(len(getattr(importlib.import_module(t), "CASES", [])) + len(getattr(importlib.import_module(t), "FILES", []))
               for t in TABLES)  # fmt: skip
    assert rows >= 450
