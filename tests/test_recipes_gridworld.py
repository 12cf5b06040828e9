"""Recipe smoke runs at the tiny scale: every output file, and resuming after an interruption."""
import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"
PNG = b"\x89PNG\r\n\x1a\n"


def _load(name):
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"recipe_{name}", RECIPES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cfg(name, out_dir, *overrides):
    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        return compose(
            config_name=name,
            overrides=["scale=tiny", f"out_dir={out_dir}", "progress=false", *overrides],
        )


def _check_outputs(out, cells):
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert set(rows[0]) >= {"setting", "condition", "seed", "episode", "return"}
    found = {(r["setting"], r["condition"], int(r["seed"])) for r in rows}
    assert found == set(cells)
    for cell in cells:
        episodes = [int(r["episode"]) for r in rows if (r["setting"], r["condition"], int(r["seed"])) == cell]
        assert episodes == list(range(len(episodes))) and episodes
    summary = (out / "summary.md").read_text()
    for setting, condition, _ in cells:
        assert f"| {setting} | {condition} |" in summary
    assert (out / "curves.png").read_bytes()[:8] == PNG
    pictures = list((out / "pictures").glob("*.png"))
    assert pictures and all(p.read_bytes()[:8] == PNG for p in pictures)
    assert list((out / "logs").rglob("*.csv")), "the TorchRL csv logger wrote nothing"
    return rows


def test_two_rooms_recipe_resumes(tmp_path, monkeypatch):
    recipe = _load("two_rooms")
    out = tmp_path / "two_rooms"
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")  # the recipe writes under out_dir only
    assert recipe.run(_cfg("two_rooms", out, "stop_after_cells=1")) is None  # interrupted after one cell
    ran = (out / "cells" / "ran.txt").read_text().split()
    assert ran == ["supervised-A-seed0"]
    assert not (out / "summary.md").exists()
    first_log = (out / "two_rooms.log").read_text()
    assert "Two rooms: 1 cells to run" in first_log and "cell supervised-A-seed0 finished" in first_log
    summary = recipe.run(_cfg("two_rooms", out))
    assert "episodes to a 50-episode mean return" in summary
    ran = (out / "cells" / "ran.txt").read_text().split()
    assert sorted(ran) == sorted(["supervised-A-seed0", "supervised-O-seed0", "supervised-AO-seed0"])  # A not redone
    _check_outputs(out, [("supervised", c, 0) for c in ("A", "O", "AO")])
    # the log file holds the log: the resumed run names the cells it skips, the cells run, the summary
    log = (out / "two_rooms.log").read_text()
    assert "1 finished cells skipped (supervised-A-seed0)" in log and "cell supervised-AO-seed0 finished" in log
    assert "summary:" in log and "| supervised | AO |" in log
    # rows in the recipe's order of its conditions (A, O, AO), not alphabetical
    rows = [line.split("|")[2].strip() for line in summary.splitlines() if line.startswith("| supervised |")]
    assert rows[:3] == ["A", "O", "AO"]
    # finished cells keep what a resume needs, not their replay buffers
    from torchrl_options.checkpoints import load_file

    for cell in ("A", "O", "AO"):
        state = load_file(out / "cells" / f"supervised-{cell}-seed0" / "dqn.pt")
        assert "replay_buffer" not in state and state["log"]["episode_returns"]
    assert list((tmp_path / "cwd").iterdir()) == []
    assert [p.name for p in (out / "pictures").glob("*.png")] == ["supervised-seed0-K2-uniform.png"]
    import cv2  # the options' video: 2 options x 4 starts (pictures.num_starts), a frame per visited cell

    video = cv2.VideoCapture(str(out / "pictures" / "supervised-seed0-K2-uniform.avi"))
    assert video.isOpened() and 2 * 4 * 2 <= video.get(cv2.CAP_PROP_FRAME_COUNT) <= 2 * 4 * 31
    # resuming with other settings is refused (the finished cells were made with the old ones), naming them;
    # other seeds or conditions, or how cells run, are not settings of the cells
    with pytest.raises(ValueError, match=r"dqn.lr: [0-9.e-]+ there, 0.5 now.*episodes: \d+ there, 7 now"):
        recipe.run(_cfg("two_rooms", out, "dqn.lr=0.5", "episodes=7"))
    assert recipe.run(_cfg("two_rooms", out, "seeds=[5]", "conditions_to_run=[A]", "stop_after_cells=0",
                           "backend=local", "summary.final_window=3")) is None  # fmt: skip
    assert recipe.run(_cfg("two_rooms", out, "dqn.lr=0.5", "allow_changed_settings=true", "stop_after_cells=0",
                           "seeds=[5]")) is None  # fmt: skip


def test_ddo_progress_bar_names_the_run(tmp_path, monkeypatch):
    """The DDO bar says which setting, seed, number of options and meta-control it fits."""
    import torchrl_options.experiments.gridworld as gridworld
    from omegaconf import OmegaConf

    seen = {}

    class Stop(Exception):
        pass

    def fake_discover(*args, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(gridworld, "discover_options", fake_discover)
    cfg = OmegaConf.to_container(_cfg("four_rooms", tmp_path), resolve=True)
    monkeypatch.setattr(gridworld, "_trajectories", lambda cfg, seed: None)
    with pytest.raises(Stop):
        gridworld.cell_options(cfg, gridworld.Cell("supervised", "H1s", 2), progress=True)
    assert seen["desc"] == "DDO supervised seed 2: 4 options, learned meta-control" and seen["progress"]


def test_quickstart_writes_under_its_out_dir(tmp_path, monkeypatch, capsys):
    import functools

    recipe = _load("quickstart")
    # a short discovery: this test is about where it writes and what it prints, not about the options
    monkeypatch.setattr(recipe, "discover_options", functools.partial(recipe.discover_options, num_iterations=3,
                                                                      restarts=1))  # fmt: skip
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    result = recipe.main([f"out_dir={tmp_path / 'qs'}"])
    assert sorted(p.name for p in (tmp_path / "qs").iterdir()) == ["options.pt"]
    assert list((tmp_path / "cwd").iterdir()) == []
    printed = capsys.readouterr().out
    assert "option 0: walks" in printed and "option 1: walks" in printed and "used at" in printed
    assert f"Segmentation: {result['accuracy']:.1%} of the steps labelled with their planted option" in printed
    assert f"saved the options to {tmp_path / 'qs' / 'options.pt'}" in printed
    with pytest.raises(ValueError, match="quickstart takes out_dir=PATH .*got 'outdir=x'"):
        recipe.main(["outdir=x"])


def test_time_claims_agree():
    """The config, the scale and the recipe's docstring state the same time for a default four-rooms run."""
    import re

    config = (RECIPES / "config" / "four_rooms.yaml").read_text().splitlines()
    claims = [
        next(line for line in config if "default scale" in line),
        (RECIPES / "config" / "scale" / "default.yaml").read_text().splitlines()[0],
        next(line for line in (RECIPES / "four_rooms.py").read_text().splitlines() if "# default scale" in line),
    ]
    claims.append(next(line for line in (RECIPES.parent / "README.md").read_text().splitlines() if "minutes on 2 free" in line))
    minutes = {re.search(r"([\d.]+) min", line).group(1) for line in claims}
    assert minutes == {"4.5"}, claims


def test_three_rooms_recipe(tmp_path):
    out = tmp_path / "three_rooms"
    _load("three_rooms").run(_cfg("three_rooms", out))
    _check_outputs(out, [("exploration", c, 0) for c in ("A", "H1u")])
    assert (out / "cells" / "exploration-seed0" / "pretrain.pt").exists()
    assert (out / "cells" / "exploration-seed0" / "greedy_trajectories.pt").exists()


@pytest.mark.slow
def test_four_rooms_recipe_command_line(tmp_path):
    out = tmp_path / "four_rooms"
    result = subprocess.run(
        [sys.executable, str(RECIPES / "four_rooms.py"), "scale=tiny", f"out_dir={out}", "progress=false"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "| supervised | H1u |" in result.stdout
    cells = [(s, c, 0) for s in ("supervised", "exploration") for c in ("A", "H1u", "H2u")]  # scale=tiny
    _check_outputs(out, cells)
    assert (out / ".hydra" / "config.yaml").exists()  # hydra.run.dir is the output dir
    assert list(tmp_path.iterdir()) == [out]  # nothing written outside out_dir
    log = (out / "four_rooms.log").read_text()  # the package's log, not Hydra's (empty) one
    assert "Four rooms: 6 cells to run" in log and "summary:" in log
    assert "DDO supervised seed 0: 4 options, uniform meta-control" not in result.stdout  # progress=false
    # a second run finds every cell finished and only rewrites the outputs
    again = subprocess.run(
        [sys.executable, str(RECIPES / "four_rooms.py"), "scale=tiny", f"out_dir={out}", "progress=false"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )  # fmt: skip
    assert again.returncode == 0
    assert len((out / "cells" / "ran.txt").read_text().split()) == len(cells)
    assert "resuming" in again.stdout and "6 finished cells skipped (supervised-A-seed0" in again.stdout


def test_four_rooms_recipe_with_two_level_hierarchy(tmp_path):
    """H2u: level-2 options discovered over level-1 ones, run by nested executors under the DQN."""
    out = tmp_path / "four_rooms"
    cfg = _cfg("four_rooms", out, "settings_to_run=[supervised]", "conditions_to_run=[A,H2u]")
    summary = _load("four_rooms").run(cfg)
    assert "| supervised | H2u |" in summary
    _check_outputs(out, [("supervised", c, 0) for c in ("A", "H2u")])
    assert (out / "cells" / "supervised-seed0" / "hierarchy-K4x2-uniform.pt").exists()


def test_merge_results_recipe(tmp_path):
    """Two runs over different seeds merged into one results.csv, summary.md (all seeds) and curves.png."""
    from torchrl_options.experiments import ResultsLog

    for name, seeds in (("run0", (0, 1)), ("run1", (2,))):
        log = ResultsLog(tmp_path / name / "results.csv")
        for seed in seeds:
            log.append_cell("supervised", "A", seed, [0.0] * 5 + [1.0] * 5)
            log.append_cell("supervised", "H1u", seed, [1.0] * 10)
    out = tmp_path / "merged"
    summary = _load("merge_results").main(
        [str(tmp_path / "run0"), str(tmp_path / "run1" / "results.csv"), "--out", str(out), "--title", "Merged",
         "--final-window", "2", "--smooth-window", "2"]
    )  # fmt: skip
    merged = ResultsLog(out / "results.csv")
    assert merged.done_cells() == {("supervised", c, s) for c in ("A", "H1u") for s in (0, 1, 2)}
    assert merged.returns("supervised", "A")[2] == [0.0] * 5 + [1.0] * 5
    assert (out / "summary.md").read_text() == summary
    assert "| supervised | H1u | 3 | 10 | 1.000 [1.000, 1.000] | 2 [2, 2] | 3/3 |" in summary
    assert (out / "curves.png").read_bytes()[:8] == PNG


def test_two_rooms_ao_diagnostic(tmp_path):
    """The AO diagnostic: per chunk of episodes, a return, a share of primitive decisions in [0, 1] and finite
    Q-values; with per-decision discounting too."""
    diag = _load("two_rooms_ao_diagnostic")
    for extra in ([], ["dqn.discount_per=decision"]):
        rows = diag.main(["--episodes", "32", "--every", "16", "scale=tiny", f"out_dir={tmp_path}",
                          "env.max_steps=100", "dqn.max_decisions=10", *extra])
        assert [r[0] >= 16 * (i + 1) for i, r in enumerate(rows)] == [True, True]
        for _, ret, share, q_primitive, q_option in rows:
            assert 0.0 <= ret <= 1.0 and 0.0 <= share <= 1.0
            assert torch.isfinite(torch.tensor([q_primitive, q_option])).all()


@pytest.mark.parametrize("name", ["four_rooms", "three_rooms"])
def test_protocol_paper_gives_back_the_paper_settings(name, tmp_path):
    """``protocol=paper`` resolves to the DDO keyword arguments and rollouts that the recipes ran before the
    measured defaults (PAPER_SETTINGS with the recipe's batch size and iterations; 100 greedy rollouts, all kept),
    and the default protocol to discover_options' own defaults on the agent's rewarded one-episode rollouts."""
    from omegaconf import OmegaConf

    from torchrl_options.experiments.gridworld import _discovery_iterations, _discovery_kwargs, apply_protocol

    def resolved(*overrides):
        with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
            cfg = compose(config_name=name, overrides=["scale=paper", f"out_dir={tmp_path}", *overrides])
        return apply_protocol(OmegaConf.to_container(cfg, resolve=True))

    paper, ours = resolved("protocol=paper"), resolved()
    batch = {"four_rooms": 10, "three_rooms": 20}[name]
    assert _discovery_kwargs(paper["discovery"]) == dict(
        num_actions=4, num_cells=2, activation="tanh", init="random", batch_size=batch, lr=0.01, m_steps=1,
        restarts=1, tol=None,
    )  # fmt: skip
    assert _discovery_iterations(paper["discovery"]) == 500
    assert paper["settings"]["exploration"]["greedy"]["epsilon"] == 0.0
    assert paper["settings"]["exploration"]["greedy"]["keep"] == "all"
    assert paper["settings"]["exploration"]["greedy"]["num"] == 100
    assert _discovery_kwargs(ours["discovery"]) == {"num_actions": 4}  # everything else: discover_options' defaults
    assert _discovery_iterations(ours["discovery"]) == 1000
    assert ours["settings"]["exploration"]["greedy"] == {"num": 1000, "length": 100, "epsilon": "agent", "keep": "rewarded"}
    assert "paper" not in ours["discovery"] and "paper" not in ours["settings"]["exploration"]
    with pytest.raises(ValueError, match="protocol must be one of"):
        resolved("protocol=faithful")
