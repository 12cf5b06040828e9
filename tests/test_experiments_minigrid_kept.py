"""The MiniGrid figures quoted on docs/experiments/minigrid.md, recomputed from the kept results in results/minigrid/:
every table line of the page is what the package's summaries make of the kept records (means and 95% Student-t
intervals over the seeds), so the page cannot drift from the data."""
import gzip
import os
import shutil

import pytest

from torchrl_options.experiments import ResultsLog
from torchrl_options.experiments.minigrid import rl_summary, rl_summary_markdown, segmentation_markdown
from torchrl_options.experiments.minigrid.summary import composition_markdown, read_records

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KEPT = os.path.join(ROOT, "results", "minigrid")
PAGE = os.path.join(ROOT, "docs", "experiments", "minigrid.md")
ROUNDS = ("round1_probe", "round2_networks", "round3_levels", "round4_heldout")


def _page() -> str:
    with open(PAGE) as f:
        return f.read()


def _records(name):
    return read_records(os.path.join(KEPT, "segmentation", f"{name}.jsonl"))


def _table_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| level")]


def _quoted(lines, page):
    missing = [line for line in lines if line not in page]
    return missing


@pytest.mark.parametrize("name", ROUNDS)
def test_kept_rounds_have_five_seeds_per_method(name):
    records = _records(name)
    assert records, name
    counts = {}
    for r in records:
        counts.setdefault((r["level"], str(sorted(r["method"].items()))), set()).add(r["seed"])
    assert all(seeds == set(range(5)) for seeds in counts.values()), counts


def test_segmentation_tables_on_the_page_are_the_kept_records():
    page = _page()
    quoted = 0
    for name in ROUNDS:
        records = _records(name)
        if name == "round3_levels":  # its UnlockPickup cells re-ran round 2's (identical: checked below)
            records = [r for r in records if r["level"] != "BabyAI-UnlockPickup-v0"]
        for granularity in ("subgoal", "skill"):
            lines = _table_lines(segmentation_markdown(records, granularity))
            ddo = [line for line in lines if "| DDO |" in line]
            assert not _quoted(ddo, page), (name, granularity, _quoted(ddo, page))
            quoted += len(ddo)
    assert quoted >= 16


def test_the_baselines_on_the_page_are_the_kept_records():
    page = _page()
    for name in ("round1_probe", "round3_levels", "round4_heldout"):
        records = _records(name)
        level = {"round1_probe": "BabyAI-UnlockPickup-v0", "round3_levels": "BabyAI-BlockedUnlockPickup-v0",
                 "round4_heldout": "BabyAI-KeyCorridorS3R2-v0"}[name]
        one_method = [r for r in records if r["level"] == level]
        label = one_method[0]["method"]
        one_method = [r for r in one_method if r["method"] == label]
        for granularity in ("subgoal", "skill"):
            lines = [line for line in _table_lines(segmentation_markdown(one_method, granularity))
                     if "| DDO |" not in line]
            # the page gives the baselines once per level, without the method column
            for line in lines:
                cells = line.split(" | ")
                short = " | ".join([cells[0], *cells[2:]])
                assert short in page, (granularity, short)


def test_rerun_cells_are_identical():
    """Round 3 re-ran round 2's UnlockPickup cells (conv and mlp-module, seeds 0-4): the same scores to the digit
    (discovery and demonstrations are seeded)."""
    again = {(r["method"]["network"], r["seed"]): r for r in _records("round3_levels")
             if r["level"] == "BabyAI-UnlockPickup-v0"}
    first = {(r["method"]["network"], r["seed"]): r for r in _records("round2_networks")
             if r["method"]["network"] != "mlp"}
    assert set(again) == set(first) and len(first) == 10
    for key, r in first.items():
        assert again[key]["subgoal"]["ddo"] == r["subgoal"]["ddo"] and again[key]["skill"]["ddo"] == r["skill"]["ddo"]


@pytest.mark.parametrize("name", ["round1_probe", "round4_heldout"])
def test_composition_tables_on_the_page_are_the_kept_records(name):
    """What the options held, per seed: the page quotes the tables of the probe and of the held-out level in full."""
    page = _page()
    lines = _table_lines(composition_markdown(_records(name), "subgoal"))
    assert lines and not _quoted(lines, page), _quoted(lines, page)


def test_default_scale_rl_table_is_the_kept_run(tmp_path):
    folder = os.path.join(KEPT, "default")
    csv_path = tmp_path / "results.csv"
    with gzip.open(os.path.join(folder, "results.csv.gz"), "rb") as src, open(csv_path, "wb") as dst:
        shutil.copyfileobj(src, dst)
    rows = ResultsLog(csv_path).rows()
    text = rl_summary_markdown(rl_summary(rows, target=0.5, window=50), target=0.5, window=50)
    lines = _table_lines(text)
    assert len(lines) == 3 and not _quoted(lines, _page()), _quoted(lines, _page())
    summary = {s.condition: s for s in rl_summary(rows, target=0.5, window=50)}
    assert summary["ppo-A"].seeds == [0, 1, 2]
    segmentation = read_records(os.path.join(folder, "segmentation.jsonl"))
    assert {r["level"] for r in segmentation} == {"BabyAI-UnlockPickup-v0", "BabyAI-UnlockLocal-v0"}


def test_throughput_table_is_the_kept_benchmark_output():
    with open(os.path.join(KEPT, "bench_minigrid.txt")) as f:
        kept = f.read()
    lines = [line for line in _table_lines(kept) if line.startswith(("| serial", "| parallel"))]
    assert len(lines) == 8 and not _quoted(lines, _page())
