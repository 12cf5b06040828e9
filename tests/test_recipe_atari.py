"""The Atari RAM recipe end to end with the smoke preset: outputs, resuming, and the Ray backend."""
import csv
import dataclasses
import importlib.util
import json
import os
import re

import numpy as np
import pytest
import torch

from torchrl_options.checkpoints import load_file
from torchrl_options.envs.atari import ATARI_GAMES, atari_available
from torchrl_options.experiments import ResultsLog
from torchrl_options.experiments.atari import AtariConfig, atari_comparison, option_usage, store_atari_config
from torchrl_options.experiments.atari.pipeline import _train_episodes
from torchrl_options.experiments.atari.utils import _close, _make_agent, _num_actions

pytestmark = pytest.mark.skipif(not atari_available(), reason="needs ale-py (the atari extra)")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _recipe():
    spec = importlib.util.spec_from_file_location("atari_ram_recipe", os.path.join(ROOT, "recipes", "atari_ram.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(overrides):
    from hydra import compose, initialize_config_dir

    store_atari_config()  # the schema of the `atari` section (the recipe registers it when imported)
    with initialize_config_dir(config_dir=os.path.join(ROOT, "recipes", "config"), version_base="1.3"):
        return compose("atari_ram", overrides=overrides)


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_presets_compose():
    for preset in ("smoke", "cpu", "cpu-large", "cpu-vec", "cpu-vec-rr", "cores16", "cores16-vec", "gpu-hour", "paper",
                   "faithful", "faithful-cpu"):  # fmt: skip
        cfg = _config([f"preset={preset}"])
        config = AtariConfig.from_dict(dict(cfg.atari))
        assert cfg.preset_name == preset and config.gamma == 0.85 and config.eps_end == 0.05
    paper = AtariConfig.from_dict(dict(_config(["preset=paper"]).atari))
    assert (paper.phase1_episodes, paper.phase3_episodes, paper.num_demonstrations) == (1000, 4000, 100)
    assert _config(["preset=paper"]).seeds == 50
    # cores16-vec: cores16's budget with cpu-vec's batching and greedy evaluation, nothing else changed
    batching = ["atari.num_envs=8", "atari.vector_env=true", "atari.frames_per_batch=400", "atari.updates_per_batch=16",
                "atari.fused_adam=true", "atari.eval_every=30", "atari.eval_episodes=16"]
    assert dict(_config(["preset=cores16-vec"]).atari) == dict(_config(["preset=cores16", *batching]).atari)
    # cpu-vec-rr: cpu-vec's budget at DQN's usual replay ratio, with greedy evaluation, nothing else changed
    ratio = ["atari.updates_per_batch=100", "atari.hard_update_interval=500", "atari.eval_every=50",
             "atari.eval_episodes=16"]
    assert dict(_config(["preset=cpu-vec-rr"]).atari) == dict(_config(["preset=cpu-vec", *ratio]).atari)
    assert dict(_config(["preset=cpu-vec-rr"]).atari) != dict(_config(["preset=cpu-vec"]).atari)
    assert _config(["preset=cpu-vec-rr"]).seeds == 8
    # faithful-cpu: cpu-vec's budget with the faithful protocol's settings (its episode cap aside) and a longer
    # phase 2 of the same cost, nothing else changed
    faithful = ["atari.env_semantics=paper", "atari.max_episode_steps=200", "atari.discount_per=decision",
                "atari.num_demonstrations=100", "atari.ddo_iterations=500", "atari.ddo_batch_size=20",
                "atari.ddo_lr=0.003", "atari.eval_every=150", "atari.eval_episodes=16"]
    assert dict(_config(["preset=faithful-cpu"]).atari) == dict(_config(["preset=cpu-vec", *faithful]).atari)
    full, small = _config(["preset=faithful"]).atari, _config(["preset=faithful-cpu"]).atari
    for name in ("env_semantics", "ram_encoding", "option_encoding", "discount_per", "num_demonstrations"):
        assert small[name] == full[name], name
    assert _config(["preset=faithful-cpu"]).seeds == 8
    assert _config(["preset=smoke", "atari.phase1_episodes=7"]).atari.phase1_episodes == 7  # CLI beats preset
    # seeds: a count (0 .. n-1) or a list, e.g. to split a sweep over machines and join the results
    recipe = _recipe()
    names = [c.name for c in recipe.sweep_cells(_config(["preset=cores16", "seeds=[3,5]", "game=Pooyan"]))]
    assert names == ["Pooyan-A-seed3", "Pooyan-A-seed5", "Pooyan-H1-seed3", "Pooyan-H1-seed5"]
    assert len(recipe.sweep_cells(_config(["preset=cores16"]))) == 5 * 3 * 2
    four = recipe.sweep_cells(_config(["preset=smoke", "conditions=[A,H1,A0,H1w]"]))
    assert [c.condition for c in four] == ["A", "H1", "A0", "H1w"]
    with pytest.raises(ValueError, match="conditions must be a non-empty list of .*got \\['A', 'H2'\\]"):
        recipe.sweep_cells(_config(["preset=smoke", "conditions=[A,H2]"]))
    for bad in ("H1iw", "H1gg", "H1x", "A1"):  # the letters after H1 come once each, in the order w, g, i
        with pytest.raises(ValueError, match=f"conditions must be .*got \\['{bad}'\\]"):
            recipe.sweep_cells(_config(["preset=smoke", f"conditions=[{bad}]"]))


def test_smoke_end_to_end_and_resume(tmp_path):
    recipe = _recipe()
    cfg = _config(["preset=smoke", "game=Seaquest", f"out_dir={tmp_path}"])
    ran = recipe.run(cfg)
    assert [c.name for c in ran] == ["Seaquest-A-seed0", "Seaquest-H1-seed0"]
    rows = _rows(tmp_path / "results.csv")
    n = cfg.atari.phase1_episodes + cfg.atari.phase3_episodes
    for cond in ("A", "H1"):
        r = [row for row in rows if row["condition"] == cond]
        assert len(r) == n
        frames = [int(row["frames"]) for row in r]
        assert frames == sorted(frames) and frames[0] > 0
    a = [row for row in rows if row["condition"] == "A"]
    h = [row for row in rows if row["condition"] == "H1"]
    p1 = cfg.atari.phase1_episodes
    assert [x["return"] for x in a[:p1]] == [x["return"] for x in h[:p1]]  # phase 1 is shared
    # H1's frames include the greedy demonstrations of phase 2
    assert int(h[p1]["frames"]) > int(h[p1 - 1]["frames"]) + cfg.atari.num_demonstrations
    summary = (tmp_path / "summary.md").read_text()
    assert "| Seaquest | 1 | 3 |" in summary and "equal frames" in summary and "verdict (equal episodes)" in summary
    assert "no evidence either way" in summary and "Probability of improvement" in summary
    assert (tmp_path / "curves.png").stat().st_size > 0 and (tmp_path / "aggregates.png").stat().st_size > 0
    frames_dir = tmp_path / "option_frames" / "Seaquest"
    assert (frames_dir / "labels.json").exists()
    assert any(p.suffix == ".png" for p in frames_dir.iterdir()) and any(p.suffix == ".avi" for p in frames_dir.iterdir())
    seed_dir = tmp_path / "Seaquest" / "seed0"
    assert (seed_dir / "phase1.pt").exists() and (seed_dir / "options.pt").exists()
    from torchrl_options import load_options

    _, _, meta = load_options(seed_dir / "options.pt", with_meta_control=True)
    assert meta["num_options"] == 5 and len(meta["demo_returns"]) == cfg.atari.num_demonstrations
    # a re-run skips the finished cells and rewrites the same outputs
    assert recipe.run(cfg) == []
    assert _rows(tmp_path / "results.csv") == rows
    assert atari_comparison(ResultsLog(tmp_path / "results.csv"), phase1_episodes=p1)[0].num_seeds == 1
    # ... but not with other settings: its finished cells and phase-1 checkpoint were made with the old ones
    out = f"out_dir={tmp_path}"
    longer = ["atari.phase1_episodes=5", "atari.phase3_episodes=4"]
    # checkpoint_every sets where training restarts its episodes (a checkpoint ends a chunk): a cell setting
    with pytest.raises(ValueError, match=r"atari.checkpoint_every: 2 there, 7 now"):
        recipe.run(_config(["preset=smoke", "game=Seaquest", out, "atari.checkpoint_every=7"]))
    with pytest.raises(ValueError, match=r"atari.phase1_episodes: 3 there, 5 now.*atari.phase3_episodes: 3 there, 4 now"):
        recipe.run(_config(["preset=smoke", "game=Seaquest", out, *longer]))
    assert _rows(tmp_path / "results.csv") == rows
    # settings of how cells run (checkpoints, greedy evaluation, device) may change; so may seeds and conditions
    same = ["atari.eval_every=2", "atari.fused_adam=true", "atari.torch_threads=1"]
    assert recipe.run(_config(["preset=smoke", "game=Seaquest", out, *same])) == []
    # allow_changed_settings mixes them knowingly, and records the new settings
    mixed = ["atari.lr=0.01", "allow_changed_settings=true"]
    assert recipe.run(_config(["preset=smoke", "game=Seaquest", out, *mixed])) == []
    settings = json.loads((tmp_path / "settings.json").read_text())
    assert settings["atari.lr"] == 0.01 and settings["atari.phase1_episodes"] == 3 and "atari.device" not in settings


def test_fused_adam_setting():
    config = AtariConfig(max_episode_steps=20, hidden_sizes=(8, 8, 8), fused_adam=True)
    assert _make_agent("Pooyan", config, 0, "actions").optimizer.defaults["fused"] is True
    assert not _make_agent("Pooyan", AtariConfig(hidden_sizes=(8, 8, 8)), 0, "actions").optimizer.defaults.get("fused")
    assert _config(["preset=smoke", "atari.fused_adam=true"]).atari.fused_adam is True


def test_periodic_checkpoint_resumes_inside_a_phase(tmp_path):
    config = AtariConfig(max_episode_steps=20, noop_max=0, hidden_sizes=(8, 8, 8), learning_starts=16,
                         frames_per_batch=20, updates_per_batch=1, checkpoint_every=1)
    path = str(tmp_path / "phase1.partial.pt")
    agent = _make_agent("Pooyan", config, 0, "actions")
    _train_episodes(agent, 2, path, config)
    saved = load_file(path)
    saved_returns = list(saved["log"]["episode_returns"])  # load_state_dict keeps (and extends) these lists
    assert len(saved_returns) >= 1
    resumed = _make_agent("Pooyan", config, 0, "actions")
    resumed.load_state_dict(saved)
    before = len(resumed.log.episode_returns)
    for key, value in saved["loss_module"].items():
        torch.testing.assert_close(resumed.loss_module.state_dict()[key], value)
    assert resumed.frames == saved["frames"]
    _train_episodes(resumed, before + 1, path, config)
    assert len(resumed.log.episode_returns) >= before + 1
    assert resumed.log.episode_returns[:before] == saved_returns


def _ray_cfg(tmp_path, game):
    return _config([
        "preset=smoke", f"game={game}", f"out_dir={tmp_path}", "sweep.backend=ray", "sweep.num_workers=2",
        "atari.max_episode_steps=20", "atari.phase1_episodes=2", "atari.phase3_episodes=2",
        "atari.num_demonstrations=2", "atari.demo_max_steps=20", "atari.option_frames=false",
    ])


def _check_ray_outputs(tmp_path, ran):
    assert sorted(c.condition for c in ran) == ["A", "H1"]
    rows = _rows(tmp_path / "results.csv")
    assert {(r["condition"], r["seed"]) for r in rows} == {("A", "0"), ("H1", "0")}
    assert (tmp_path / "summary.md").exists() and (tmp_path / "curves.png").exists()


def test_ray_local_two_cells(tmp_path):
    """The Ray path of the sweep on a local Ray cluster of 2 CPUs: tasks in worker processes, results gathered
    by the driver into one results.csv. (Ray 2.x has no in-process local mode any more.)"""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        _check_ray_outputs(tmp_path, _recipe().run(_ray_cfg(tmp_path, "Pooyan")))
    finally:
        ray.shutdown()


@pytest.mark.slow
def test_smoke_all_five_games(tmp_path):
    recipe = _recipe()
    cfg = _config(["preset=smoke", f"games=[{','.join(ATARI_GAMES)}]", f"out_dir={tmp_path}"])
    recipe.run(cfg)
    rows = _rows(tmp_path / "results.csv")
    assert {r["setting"] for r in rows} == set(ATARI_GAMES)
    summary = (tmp_path / "summary.md").read_text()
    assert all(f"| {g} |" in summary for g in ATARI_GAMES)
    assert "of 5 games" in summary


def test_control_and_warm_start_conditions(tmp_path):
    """A0 (actions, Q reset), H1w (options added to phase 1's DQN), H1g (greedy options) and H1i (primitive values
    also learned inside options) beside the paper's A and H1: all six share phases 1 and 2, and the summary reports
    each pair and the option usage."""
    recipe = _recipe()
    cfg = _config(["preset=smoke", "game=Pooyan", f"out_dir={tmp_path}", "conditions=[A,H1,A0,H1w,H1g,H1i]",
                   "atari.max_episode_steps=20", "atari.phase1_episodes=2", "atari.phase3_episodes=2",
                   "atari.num_demonstrations=2", "atari.demo_max_steps=20", "atari.option_frames=false",
                   "atari.learning_starts=8"])
    ran = recipe.run(cfg)
    assert sorted(c.condition for c in ran) == ["A", "A0", "H1", "H1g", "H1i", "H1w"]
    rows = _rows(tmp_path / "results.csv")
    by = {c: [r for r in rows if r["condition"] == c] for c in ("A", "H1", "A0", "H1w", "H1g", "H1i")}
    p1 = cfg.atari.phase1_episodes
    for c, r in by.items():
        assert len(r) == p1 + cfg.atari.phase3_episodes, c
        assert [x["return"] for x in r[:p1]] == [x["return"] for x in by["A"][:p1]], c  # phase 1 is shared
    # A0 spends no demonstration frames; H1 and H1w do
    seed_dir = tmp_path / "Pooyan" / "seed0"
    import json

    demo_frames = json.loads((seed_dir / "H1.json").read_text())["demo_frames"]
    p1_end = int(by["A"][p1 - 1]["frames"])
    first_len = lambda c: int(by[c][p1]["frames"]) - p1_end  # noqa: E731
    assert first_len("A0") <= cfg.atari.max_episode_steps
    assert all(first_len(c) > demo_frames for c in ("H1", "H1w", "H1g", "H1i"))
    for c in ("H1", "H1w", "H1g", "H1i"):
        info = json.loads((seed_dir / f"{c}.json").read_text())
        assert 0.0 <= info["option_decision_share"] <= 1.0 and 0.0 <= info["option_step_share"] <= 1.0
    summary = (tmp_path / "summary.md").read_text()
    for header in ("## H1 vs A", "## H1w vs A", "## H1g vs A", "## H1i vs A", "## A0 vs A", "## H1 vs A0",
                   "## H1g vs A0", "## H1i vs A0", "## H1g vs H1", "## H1i vs H1", "## Option usage in phase 3"):
        assert header in summary
    assert "| Pooyan | H1g | 1 |" in summary and "| Pooyan | H1i | 1 |" in summary  # their option usage
    comparison = atari_comparison(ResultsLog(tmp_path / "results.csv"), phase1_episodes=p1, condition="H1w")
    assert comparison[0].condition == "H1w" and comparison[0].baseline == "A" and comparison[0].num_seeds == 1


def test_combined_conditions(tmp_path):
    """``H1wi`` (the warm start with intra-option transitions) and ``H1is``; the summary compares them with A, H1w
    and H1."""
    recipe = _recipe()
    cfg = _config(["preset=smoke", "game=Pooyan", f"out_dir={tmp_path}", "conditions=[A,H1,H1w,H1wi,H1is]",
                   "atari.max_episode_steps=20", "atari.phase1_episodes=2", "atari.phase3_episodes=2",
                   "atari.num_demonstrations=2", "atari.demo_max_steps=20", "atari.option_frames=false",
                   "atari.learning_starts=8"])
    assert sorted(c.condition for c in recipe.run(cfg)) == ["A", "H1", "H1is", "H1w", "H1wi"]
    summary = (tmp_path / "summary.md").read_text()
    for header in ("## H1wi vs A", "## H1wi vs H1w", "## H1wi vs H1", "## H1w vs H1", "## H1is vs A", "## H1is vs H1"):
        assert header in summary
    assert "## H1wi vs A0" not in summary and "started from phase 1's DQN" in summary
    assert "| Pooyan | H1wi | 1 |" in summary


def test_intra_option_condition_and_its_option_usage():
    """H1is's agent stores the steps inside options as one-step primitive transitions and the option suffixes;
    ``option_usage`` counts the decisions only, so its figures compare with H1's."""
    from torchrl_options.modules import OptionsMLP

    config = AtariConfig(max_episode_steps=40, hidden_sizes=(8, 8, 8), frames_per_batch=40, learning_starts=10**9)
    n = _num_actions("Pooyan", config)
    torch.manual_seed(0)
    options = OptionsMLP(128, n, 2, num_cells=[8])
    agent = _make_agent("Pooyan", config, 0, "both", options=options, num_options=2, intra_option_actions=True,
                        option_suffixes=True)
    assert agent.config.intra_option_actions and agent.config.option_suffixes
    agent.train(total_frames=200)
    buf = agent.replay_buffer[: len(agent.replay_buffer)]
    intra = buf["intra_option"].reshape(-1)
    decisions = buf[~intra]
    option_steps = int(decisions["steps_to_next_obs"][decisions["action"] >= n].sum())
    primitive = buf[intra & (buf["action"] < n)]
    assert (primitive["steps_to_next_obs"] == 1).all()
    assert 0 < option_steps <= primitive.shape[0]  # (plus the steps of option runs still pending)
    suffixes = buf[intra & (buf["action"] >= n)]
    assert suffixes.shape[0] > 0 and (suffixes["action"] < n + 2).all()
    usage = option_usage(agent, n)
    is_option = decisions["action"] >= n
    assert usage["option_decision_share"] == pytest.approx(float(is_option.float().mean()))
    assert usage["option_step_share"] == pytest.approx(option_steps / float(decisions["steps_to_next_obs"].sum()))
    _close(agent)


def test_option_usage_counts_steps_when_discounting_per_decision():
    """Per decision, ``steps_to_next_obs`` is 1 for the bootstrap whatever an option's length; ``option_usage``
    reads the decisions' true lengths (``"decision_steps"``), so options that run several steps are not reported
    as one-step runs. The lengths add up to the env steps the agent took."""
    from torchrl_options.modules import OptionsMLP

    config = AtariConfig(max_episode_steps=40, hidden_sizes=(8, 8, 8), frames_per_batch=40, learning_starts=10**9,
                         discount_per="decision")
    n = _num_actions("Pooyan", config)
    torch.manual_seed(0)
    options = OptionsMLP(128, n, 2, num_cells=[8])
    with torch.no_grad():  # terminations that rarely fire (sigmoid(-3) = 0.05): options run several steps
        last = [name for name, m in options.termination._empty_net.named_children() if isinstance(m, torch.nn.Linear)][-1]
        options.termination.params.get((last, "weight")).zero_()
        options.termination.params.get((last, "bias")).fill_(-3.0)
    for intra in (False, True):
        agent = _make_agent("Pooyan", config, 0, "both", options=options, num_options=2, intra_option_actions=intra)
        agent.env.set_seed(0)
        agent.train(total_frames=200)
        buf = agent.replay_buffer[: len(agent.replay_buffer)]
        decisions = buf[~buf["intra_option"].reshape(-1)] if intra else buf
        assert (decisions["steps_to_next_obs"] == 1).all()
        lengths = decisions["decision_steps"].reshape(-1)
        is_option = decisions["action"].reshape(-1) >= n
        assert is_option.any() and (lengths[is_option] > 1).any()
        assert (lengths[~is_option] == 1).all()
        assert int(lengths.sum()) <= 200  # (the steps of decisions still running are not stored yet)
        usage = option_usage(agent, n)
        assert usage["mean_option_steps"] == pytest.approx(float(lengths[is_option].float().mean()))
        assert usage["mean_option_steps"] > 1.0
        assert usage["option_step_share"] == pytest.approx(float(lengths[is_option].sum() / lengths.sum()))
        if intra:
            assert (buf[buf["intra_option"].reshape(-1)]["decision_steps"] == 1).all()
        _close(agent)


def test_greedy_options_condition_acts_by_argmax():
    """H1g's agent runs each option with the argmax of its control policy at every step; H1's samples from it."""
    from torchrl_options.modules import OptionsMLP
    from torchrl_options.transforms import OptionExecutor

    config = AtariConfig(max_episode_steps=40, hidden_sizes=(8, 8, 8))
    n = _num_actions("Pooyan", config)
    torch.manual_seed(0)
    options = OptionsMLP(128, n, 2, num_cells=[8])  # untrained: far from deterministic
    for greedy in (False, True):
        agent = _make_agent("Pooyan", config, 0, "both", options=options, num_options=2, greedy_options=greedy)
        executor = next(t for t in agent.env.transform if isinstance(t, OptionExecutor))
        assert executor.greedy is greedy
        agent.env.set_seed(0)
        # every decision starts option 0, so option 0 chooses every primitive action of the rollout
        data = agent.env.rollout(40, policy=lambda td: td.set("action", torch.tensor(n)))
        assert (data["next", "executed_option"] == 0).all()
        with torch.no_grad():
            argmax = options(data.select("observation").clone())["option_logits"][..., 0, :].argmax(-1)
        same = data["next", "executed_action"].reshape(-1) == argmax.reshape(-1)
        assert same.all() if greedy else not same.all(), greedy


def test_vector_env_cells(tmp_path):
    """``atari.vector_env``: each agent's ``num_envs`` games in one gymnasium vector env (batch ``[num_envs]``); the
    greedy demonstrations stay one game at a time; the pipeline and its outputs are unchanged."""
    config = AtariConfig(max_episode_steps=20, hidden_sizes=(8, 8, 8), num_envs=3, vector_env=True, frames_per_batch=60)
    agent = _make_agent("Pooyan", config, 0, "actions")
    assert agent.env.batch_size == (3,) and agent.config.num_envs == 1
    agent.train(total_frames=120)
    assert len(agent.log.episode_returns) == 6 and agent.frames == 120  # 3 games x 2 episodes of 20 steps
    recipe = _recipe()
    cfg = _config(["preset=smoke", "game=Pooyan", f"out_dir={tmp_path}", "atari.max_episode_steps=20",
                   "atari.phase1_episodes=4", "atari.phase3_episodes=4", "atari.num_demonstrations=2",
                   "atari.demo_max_steps=20", "atari.option_frames=false", "atari.learning_starts=8",
                   "atari.num_envs=2", "atari.vector_env=true", "atari.frames_per_batch=20",
                   "atari.eval_every=2", "atari.eval_episodes=2"])
    assert sorted(c.condition for c in recipe.run(cfg)) == ["A", "H1"]
    rows = _rows(tmp_path / "results.csv")
    for cond in ("A", "H1"):
        r = [row for row in rows if row["condition"] == cond]
        assert len(r) == 8
        frames = [int(row["frames"]) for row in r]
        assert frames == sorted(frames)
    import json

    from torchrl_options import load_options

    _, _, meta = load_options(tmp_path / "Pooyan" / "seed0" / "options.pt", with_meta_control=True)
    assert len(meta["demo_returns"]) == 2
    info = json.loads((tmp_path / "Pooyan" / "seed0" / "H1.json").read_text())
    assert 0.0 <= info["option_step_share"] <= 1.0
    assert [p for p, _, _ in info["evaluations"]] == [2, 4, 6, 8]  # greedy evaluations over the vector env too


def test_greedy_evaluation(tmp_path):
    """``atari.eval_every``: greedy evaluations at the same episode counts in every condition, phase 1's shared,
    kept in each cell's json file and compared in summary.md."""
    import json

    recipe = _recipe()
    cfg = _config(["preset=smoke", "game=Pooyan", f"out_dir={tmp_path}", "conditions=[A,H1,A0]",
                   "atari.max_episode_steps=20", "atari.phase1_episodes=4", "atari.phase3_episodes=4",
                   "atari.num_demonstrations=2", "atari.demo_max_steps=20", "atari.option_frames=false",
                   "atari.learning_starts=8", "atari.eval_every=2", "atari.eval_episodes=2"])
    recipe.run(cfg)
    seed_dir = tmp_path / "Pooyan" / "seed0"
    evals = {c: json.loads((seed_dir / f"{c}.json").read_text())["evaluations"] for c in ("A", "H1", "A0")}
    for c, e in evals.items():
        assert [p for p, _, _ in e] == [2, 4, 6, 8], c  # one evaluation per multiple of eval_every, in order
        assert all(ep >= p for p, ep, _ in e), c
    assert evals["A"][:2] == evals["H1"][:2] == evals["A0"][:2]  # phase 1 is shared
    summary = (tmp_path / "summary.md").read_text()
    for header in ("## Greedy evaluation: H1 vs A", "## Greedy evaluation: A0 vs A", "## Greedy evaluation: H1 vs A0"):
        assert header in summary
    row = next(line for line in summary.splitlines() if line.startswith("| Pooyan | 1 | 2 |"))
    h1 = np.mean([m for p, _, m in evals["H1"][2:]])
    a = np.mean([m for p, _, m in evals["A"][2:]])
    assert f"{h1 - a:.2f} [" in row


def test_ddo_m_steps_reaches_discovery_and_fits_closer(tmp_path, monkeypatch):
    import torchrl_options.discovery as discovery
    from torchrl_options.experiments.atari.pipeline import _phase2

    seen = []
    real = discovery.discover_options

    def spy(*args, **kwargs):
        seen.append(kwargs["m_steps"])
        return real(*args, **kwargs)

    monkeypatch.setattr(discovery, "discover_options", spy)
    fits = {}
    for m in (1, 8):
        config = AtariConfig(max_episode_steps=40, noop_max=0, hidden_sizes=(8, 8, 8), num_demonstrations=3,
                             demo_max_steps=40, options_num_cells=(8,), ddo_iterations=5, ddo_batch_size=None,
                             ddo_lr=0.01, ddo_m_steps=m)
        agent = _make_agent("Pooyan", config, 0, "actions")
        (tmp_path / f"m{m}").mkdir()
        _, meta = _phase2("Pooyan", config, 0, str(tmp_path / f"m{m}"), agent)
        _close(agent)
        fits[m] = meta["log_likelihood_per_step"]
    assert seen == [1, 8]
    assert fits[8] > fits[1] + 0.05, fits  # the same demonstrations and E-steps, 8 G-steps each: a closer fit
    assert _config(["preset=smoke", "atari.ddo_m_steps=4"]).atari.ddo_m_steps == 4
    for bad, error in ((0, ValueError), (1.5, TypeError), (True, TypeError)):  # refused when the settings are read
        with pytest.raises(error, match="ddo_m_steps must be an int"):
            AtariConfig.from_dict({"ddo_m_steps": bad})
    assert _config(["preset=faithful-cpu"]).atari.ddo_starts == "one"  # the kept runs: one start
    assert _config(["preset=smoke", "atari.ddo_starts=defaults"]).atari.ddo_starts == "defaults"
    with pytest.raises(ValueError, match="ddo_starts must be one of \\('one', 'defaults'\\), got 'many'"):
        AtariConfig.from_dict({"ddo_starts": "many"})


def test_agent_config_takes_the_shared_settings_by_name():
    """``OptionsDQNConfig`` is built from the ``AtariConfig`` settings of the same name (not copied field by field):
    both derive from ``DQNHyperParameters``, which declares and checks them once."""
    from torchrl_options.agents import DQNHyperParameters, OptionsDQNConfig

    shared = {f.name for f in dataclasses.fields(DQNHyperParameters)}
    assert shared <= {f.name for f in dataclasses.fields(AtariConfig)}
    assert set(AtariConfig().dqn_settings()) == shared
    # one check, one message, for the agent and the recipe
    for bad in ({"gamma": 1.5}, {"discount_per": "option"}, {"batch_size": 0}, {"lr": "fast"}):
        with pytest.raises((ValueError, TypeError)) as agent_err:
            OptionsDQNConfig(**bad)
        with pytest.raises(type(agent_err.value), match=re.escape(str(agent_err.value))):
            AtariConfig(**bad)
    config = AtariConfig(lr=0.02, gamma=0.5, batch_size=7, buffer_size=99, double_dqn=True, eps_init=0.4, eps_end=0.2,
                         eps_annealing_frames=0, hidden_sizes=(8, 8, 8), max_episode_steps=20, noop_max=0,
                         learning_starts=3, frames_per_batch=5, updates_per_batch=2, hard_update_interval=9)
    agent = _make_agent("Pooyan", config, 5, "actions")
    try:
        dqn = agent.config
        assert (dqn.lr, dqn.gamma, dqn.batch_size, dqn.buffer_size, dqn.double_dqn, dqn.eps_init, dqn.eps_end) == (
            0.02, 0.5, 7, 99, True, 0.4, 0.2)
        assert (dqn.learning_starts, dqn.frames_per_batch, dqn.updates_per_batch, dqn.hard_update_interval) == (3, 5, 2, 9)
        assert dqn.hidden_sizes == (8, 8, 8) and dqn.eps_annealing_frames == 0 and dqn.seed == 5
        assert dqn.mode == "actions" and dqn.num_envs == 1
        assert agent.exploration.annealing_num_steps == 1  # 0 frames: annealed after the first
    finally:
        _close(agent)


def test_phase2_one_hot_options_their_fit_and_the_quality_gate(tmp_path, caplog):
    import logging
    import math

    from torchrl_options import OptionsMLP
    from torchrl_options.experiments.atari import demonstration_fit_markdown
    from torchrl_options.experiments.atari.pipeline import _phase2, _quality_gate
    from torchrl_options.modules import OneHotByteOptions

    small = dict(max_episode_steps=40, noop_max=0, hidden_sizes=(8, 8, 8), num_demonstrations=3, demo_max_steps=40,
                 options_num_cells=(8,), ddo_iterations=3, ddo_batch_size=None, demo_random_episodes=2)  # fmt: skip
    config = AtariConfig(**small)
    assert config.option_encoding == "one_hot"  # the paper's, the default
    agent = _make_agent("Pooyan", config, 0, "actions")
    options, meta = _phase2("Pooyan", config, 0, str(tmp_path), agent)
    assert isinstance(options, OneHotByteOptions) and options.value_scale == 1 / 255
    # every demonstration step is the greedy action: the eps-greedy demonstrator's probability 1 - eps + eps / A
    assert meta["demonstrator_log_likelihood_per_step"] == pytest.approx(math.log(1 - 0.05 + 0.05 / 6))
    assert -math.log(6) - 0.5 < meta["options_log_likelihood_per_step"] < 0
    assert len(meta["random_returns"]) == 2
    # DDO's usage of each option on the demonstrations: K shares summing to 1, and the table counts those in use
    assert len(meta["option_usage"]) == config.options_for("Pooyan") and sum(meta["option_usage"]) == pytest.approx(1)
    demo_mean, random_mean = np.mean(meta["demo_returns"]), np.mean(meta["random_returns"])
    assert meta["degenerate_demonstrator"] == bool(demo_mean <= random_mean)
    assert json.loads((tmp_path / "phase2.json").read_text())["options_log_likelihood_per_step"] == pytest.approx(
        meta["options_log_likelihood_per_step"])
    # the phase-2 table reads it (the recipe's summary.md), laid out as <out>/<game>/seed<s>/
    (tmp_path / "out" / "Pooyan" / "seed0").mkdir(parents=True)
    (tmp_path / "out" / "Pooyan" / "seed0" / "phase2.json").write_text((tmp_path / "phase2.json").read_text())
    table = demonstration_fit_markdown(str(tmp_path / "out"))
    in_use = sum(u >= 0.1 / len(meta["option_usage"]) for u in meta["option_usage"])
    assert "| Pooyan | one_hot | 1 |" in table and table.rstrip().endswith(f"| {in_use:.1f} of 7 |")
    # the gate: logged and recorded when the demonstrations are no better than a random policy, runs on regardless
    with caplog.at_level(logging.WARNING):
        assert _quality_gate("Pooyan", config, 0, [-1e9])["degenerate_demonstrator"] is True
    assert "degenerate demonstrator" in caplog.text
    assert _quality_gate("Pooyan", config, 0, [1e9])["degenerate_demonstrator"] is False
    assert _quality_gate("Pooyan", AtariConfig(**{**small, "demo_random_episodes": 0}), 0, [0.0]) == {
        "random_returns": [], "degenerate_demonstrator": None}
    # bytes / 255 options, the project's former networks
    (tmp_path / "bytes").mkdir()
    options, meta = _phase2("Pooyan", AtariConfig(**small, option_encoding="bytes"), 0, str(tmp_path / "bytes"), agent)
    assert isinstance(options, OptionsMLP) and meta["option_encoding"] == "bytes"
    _close(agent)
    with pytest.raises(ValueError, match="option_encoding must be one of"):
        AtariConfig(option_encoding="onehot16")


def test_faithful_settings_reach_the_env_and_the_agent():
    from torchrl_options.envs.atari import PAPER_ENV_SETTINGS
    from torchrl_options.experiments.atari.config import check_atari_recipe_settings
    from omegaconf import OmegaConf

    cfg = _config(["preset=faithful"])
    faithful = AtariConfig.from_dict(dict(cfg.atari))
    assert faithful.env_kwargs() == PAPER_ENV_SETTINGS and faithful.discount_per == "decision"
    assert (faithful.option_encoding, faithful.ram_encoding, faithful.num_demonstrations) == ("one_hot", "one_hot", 100)
    assert (faithful.eval_episodes, faithful.phase1_episodes, faithful.phase3_episodes, cfg.seeds) == (50, 1000, 4000, 50)
    config = AtariConfig(env_semantics="paper", max_episode_steps=20, discount_per="decision", hidden_sizes=(8, 8, 8))
    agent = _make_agent("Atlantis", config, 0, "actions")
    try:
        assert agent.config.discount_per == "decision" and agent.smdp.per_decision
        assert agent.env.rollout(100).shape[-1] == 20  # the cap given beats the paper's 10,000
    finally:
        _close(agent)
    from torchrl.envs import RewardClipping

    from torchrl_options.experiments.atari.utils import _env_factory

    env = _env_factory("Atlantis", config, 0)()
    assert not any(isinstance(t, RewardClipping) for t in env.transform)  # raw rewards
    ale = env.base_env._env.unwrapped.ale
    assert ale.getFloat("repeat_action_probability") == 0.25 and env.base_env._env.unwrapped._frameskip == (2, 5)
    env.close()
    # option suffixes discount per primitive step: refused with the per-decision discount, before any work
    bad = OmegaConf.to_container(_config(["preset=smoke", "conditions=[A,H1s]", "atari.discount_per=decision"]))
    with pytest.raises(ValueError, match=r"\['H1s'\] .* need atari.discount_per=step"):
        check_atari_recipe_settings(bad)


def _sweep_script_overrides(out_dir) -> list[str]:
    """The Hydra overrides of recipes/ray/run_faithful_sweep.sh, with its OUT_DIR."""
    import shlex

    text = (ROOT + "/recipes/ray/run_faithful_sweep.sh")
    words = shlex.split(" ".join(line.rstrip("\\") for line in open(text).read().splitlines() if not line.startswith("#")))
    start = words.index("recipes/atari_ram.py") + 1
    return [w.replace("$OUT_DIR", str(out_dir)) for w in words[start:] if w != "$@"]


def test_ray_cluster_config_and_the_sweep_command():
    import yaml
    from omegaconf import OmegaConf

    from torchrl_options.experiments.atari.config import check_atari_recipe_settings

    with open(os.path.join(ROOT, "recipes", "ray", "atari_faithful.yaml")) as f:
        cluster = yaml.safe_load(f)
    assert cluster["head_node_type"] in cluster["available_node_types"] and cluster["provider"]["type"] == "aws"
    assert any("[atari,recipes,ray]" in c for c in cluster["setup_commands"])
    assert cluster["max_workers"] >= max(t.get("max_workers", 0) for t in cluster["available_node_types"].values())
    overrides = _sweep_script_overrides("/mnt/ddo/atari_faithful")
    cfg = _config(overrides)
    check_atari_recipe_settings(OmegaConf.to_container(cfg, resolve=True))
    assert cfg.preset_name == "faithful" and cfg.sweep.backend == "ray" and cfg.sweep.ray_address == "auto"
    assert cfg.atari.device == "cpu" and cfg.out_dir == "/mnt/ddo/atari_faithful"
    assert len(_recipe().sweep_cells(cfg)) == 5 * 50 * 2


@pytest.mark.slow
def test_faithful_sweep_command_on_local_ray_at_tiny_scale(tmp_path):
    """The sweep script's own settings, at a tiny budget, on a local Ray cluster; run again, it resumes (nothing
    left to run) and rewrites the summary with the phase-2 table."""
    ray = pytest.importorskip("ray")
    tiny = ["game=Pooyan", "seeds=1", "sweep.ray_address=null", "sweep.num_workers=2", "atari.max_episode_steps=20",
            "atari.phase1_episodes=2", "atari.phase3_episodes=2", "atari.num_demonstrations=2",
            "atari.demo_max_steps=20", "atari.demo_random_episodes=1", "atari.ddo_iterations=2", "atari.num_envs=2",
            "atari.frames_per_batch=20", "atari.updates_per_batch=1", "atari.learning_starts=10",
            "atari.hidden_sizes=[8,8,8]", "atari.options_num_cells=[8]", "atari.eval_every=2", "atari.eval_episodes=2",
            "atari.option_frames=false", "atari.checkpoint_every=1"]  # fmt: skip
    cfg = _config(_sweep_script_overrides(tmp_path) + tiny)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        _check_ray_outputs(tmp_path, _recipe().run(cfg))
        assert _recipe().run(cfg) == []
    finally:
        ray.shutdown()
    summary = (tmp_path / "summary.md").read_text()
    assert "| Pooyan | one_hot | 1 |" in summary and "env_semantics=paper" in summary and "discount per decision" in summary
