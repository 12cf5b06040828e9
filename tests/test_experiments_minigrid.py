"""The MiniGrid experiment (torchrl_options.experiments.minigrid): the BabyAI bot's labelled demonstrations."""
import pytest
import torch

from torchrl_options.envs.minigrid import minigrid_available, observation_size
from torchrl_options.experiments.minigrid import (
    bot_demonstrations,
    load_demonstrations,
    save_demonstrations,
    SKILLS,
    SUBGOAL_TYPES,
    TARGETS,
)

needs_minigrid = pytest.mark.skipif(not minigrid_available(), reason="needs minigrid (the minigrid extra)")
TINY = "BabyAI-UnlockLocal-v0"  # find the key, open the door: about 15 bot steps


@pytest.fixture(scope="module")
def demos():
    if not minigrid_available():
        pytest.skip("needs minigrid")
    return bot_demonstrations(TINY, 4, first_seed=0)


@needs_minigrid
def test_demonstrations_layout_and_labels(demos):
    data = demos.data
    mask = data["collector", "mask"]
    lengths = mask.sum(1)
    assert data.batch_size[0] == 4 and len(set(lengths.tolist())) > 1  # variable lengths, padded at the end
    assert data["observation"].shape[-1] == observation_size() and data["action"].dtype == torch.long
    # every episode ends with the bot's success: terminated, with a positive reward, at its last valid step
    last = lengths - 1
    rows = torch.arange(4)
    assert data["next", "terminated"][rows, last].all() and (data["next", "reward"][rows, last] > 0).all()
    assert (data["next", "reward"][mask].squeeze(-1) > 0).sum() == 4
    # consecutive steps chain: s_{t+1} of step t is the observation of step t + 1
    assert torch.equal(data["next", "observation"][0, : lengths[0] - 1], data["observation"][0, 1 : lengths[0]])
    # labels: valid indices on valid steps, -1 on padding; true_option is the subgoal type
    for key, names in (("subgoal_type", SUBGOAL_TYPES), ("subgoal_target", TARGETS), ("skill", SKILLS)):
        assert data[key][mask].min() >= 0 and data[key][mask].max() < len(names)
        assert (data[key][~mask] == -1).all()
    assert torch.equal(data["true_option"], data["subgoal_type"])
    # UnlockLocal's plan: pick up the key, then open the door (the last subgoal is Open door)
    types = [SUBGOAL_TYPES[i] for i in data["subgoal_type"][mask].tolist()]
    assert {"GoNextTo", "Pickup", "Open"} <= set(types)
    for i in range(4):
        assert SUBGOAL_TYPES[int(data["subgoal_type"][i, last[i]])] == "Open"
        assert TARGETS[int(data["subgoal_target"][i, last[i]])] == "door"
        assert int(data["action"][i, last[i]]) == 5  # toggle
    # boundaries: where (type, target) changes, True at step 0; a skill boundary is a subgoal boundary
    sw = data["true_switch"]
    assert sw[:, 0].all()
    change = (data["subgoal_type"][:, 1:] != data["subgoal_type"][:, :-1]) | (
        data["subgoal_target"][:, 1:] != data["subgoal_target"][:, :-1])
    assert torch.equal(sw[:, 1:] & mask[:, 1:], change & mask[:, 1:])
    assert not (data["skill_switch"] & ~sw & mask).any()
    assert demos.env_seeds == [0, 1, 2, 3] and (data["env_seed"][1][mask[1]] == 1).all()


@needs_minigrid
def test_skills_merge_the_walk_with_the_interaction(demos):
    data = demos.data
    mask = data["collector", "mask"]
    for i in range(4):
        L = int(mask[i].sum())
        types = [SUBGOAL_TYPES[t] for t in data["subgoal_type"][i, :L].tolist()]
        skills = [SKILLS[s] for s in data["skill"][i, :L].tolist()]
        for t, (ty, sk) in enumerate(zip(types, skills)):
            if ty == "Pickup":
                assert sk == "pickup key"
            if ty == "Open":
                assert sk == "open door"
            if ty == "Explore":
                assert sk == "explore"
        # the step before the Pickup is a walk to the key, in the same skill
        k = types.index("Pickup")
        if k > 0 and types[k - 1] == "GoNextTo":
            assert skills[k - 1] == "pickup key"


@needs_minigrid
def test_deterministic_and_saved_with_tensors_only(demos, tmp_path):
    again = bot_demonstrations(TINY, 4, first_seed=0)
    assert (again.data == demos.data).all()
    other = bot_demonstrations(TINY, 2, first_seed=10)
    assert other.env_seeds == [10, 11]
    path = save_demonstrations(demos, tmp_path / "demos.pt")
    back = load_demonstrations(path)
    for key in ("observation", "action", "true_option", "true_switch", "skill", "subgoal_target", ("collector", "mask")):
        assert torch.equal(back[key], demos.data[key]), key
    raw = torch.load(path, weights_only=True)  # plain data: nothing to unpickle
    assert isinstance(raw, dict)
    with pytest.raises(ValueError, match=r"\.pt file"):
        save_demonstrations(demos, tmp_path / "demos.npz")


@needs_minigrid
def test_a_bot_whose_plan_grows_without_end_is_a_skipped_layout_not_a_hang():
    # On this layout minigrid's bot pushes exploration subgoals forever inside one replan(); the bounded plan
    # turns that into a layout the bot gives up on, and the next seed is used.
    demos = bot_demonstrations("BabyAI-UnlockToUnlock-v0", 1, first_seed=4)
    assert demos.skipped_seeds == [4] and demos.env_seeds == [5]
    from torchrl_options.experiments.minigrid.demonstrations import _BoundedPlan, _MAX_PLAN_DEPTH, _PlanTooDeep

    plan = _BoundedPlan(range(_MAX_PLAN_DEPTH - 1))
    plan.append("one more")  # up to the bound: a plan like any other
    with pytest.raises(_PlanTooDeep):
        plan.append("too deep")
    cycle = _BoundedPlan()  # pushes and pops at a constant depth: bounded per step, not in total
    for step in range(3):
        cycle.new_step()
        for _ in range(_MAX_PLAN_DEPTH):
            cycle.append(step)
            cycle.pop()
    with pytest.raises(_PlanTooDeep):
        cycle.append("one push too many in this step")


@needs_minigrid
def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="BabyAI level"):
        bot_demonstrations("MiniGrid-DoorKey-5x5-v0", 1)
    with pytest.raises(ValueError, match="num_demonstrations"):
        bot_demonstrations(TINY, 0)
    with pytest.raises(TypeError, match="first_seed"):
        bot_demonstrations(TINY, 1, first_seed=1.5)
    # the bot fails on KeyInBox (its docstring says so): no finished episode within the attempts
    with pytest.raises(ValueError, match="the bot finished 0 of 2 episodes"):
        bot_demonstrations("BabyAI-KeyInBox-v0", 1, max_attempts=2)


# ----------------------------------------------------------------------------------------------- scoring
def _labelled(true, actions=None):
    from tensordict import TensorDict

    true = torch.tensor(true)
    switch = torch.ones_like(true, dtype=torch.bool)
    switch[:, 1:] = true[:, 1:] != true[:, :-1]
    return TensorDict({"true_option": true, "true_switch": switch,
                       "action": torch.tensor(actions) if actions is not None else torch.zeros_like(true),
                       ("collector", "mask"): torch.ones_like(true, dtype=torch.bool)}, list(true.shape))


def test_scores_of_the_truth_and_of_a_shifted_copy():
    from torchrl_options.experiments.minigrid import segmentation_scores

    data = _labelled([[0, 0, 0, 1, 1, 1, 2, 2, 2, 0, 0, 0]] * 3)
    perfect = segmentation_scores(data["true_option"] + 5, data)  # any relabelling
    assert perfect["label_accuracy"] == 1.0 and perfect["f1_w1"] == 1.0 and perfect["f1_w2"] == 1.0
    assert perfect["boundary_rate"] == pytest.approx(3 / 11) and perfect["reference_rate"] == pytest.approx(3 / 11)
    shifted = torch.roll(data["true_option"], 1, dims=1)  # every boundary one step late
    s = segmentation_scores(shifted, data, windows=(0, 1))
    assert s["f1_w0"] == 0.0 and s["f1_w1"] == 1.0 and s["label_accuracy"] == pytest.approx(9 / 12)
    with pytest.raises(ValueError, match=r"predicted must be \[B, T\]"):
        segmentation_scores(torch.zeros(2, 12), data)
    with pytest.raises(KeyError, match="skill"):
        segmentation_scores(shifted, data, label_key="skill")


def test_baselines_on_known_data():
    from torchrl_options.experiments.minigrid import baseline_scores
    from torchrl_options.segmentation import boundary_metrics

    true = [[0, 0, 0, 1, 1, 1, 1, 1, 2, 2]] * 4
    actions = [[3, 3, 1, 1, 1, 2, 2, 4, 4, 4]] * 4
    data = _labelled(true, actions)
    base = baseline_scores(data, seed=0, num_samples=200)
    mask = data["collector", "mask"]
    change = torch.zeros_like(mask)
    change[:, 1:] = data["action"][:, 1:] != data["action"][:, :-1]
    direct = boundary_metrics(change, data["true_switch"], 1, lengths=mask)
    assert base["action_change"]["f1_w1"] == pytest.approx(direct["f1"])
    assert base["one_option"]["label_accuracy"] == pytest.approx(0.5)  # option 1 holds 5 of 10 steps
    assert base["one_option"]["f1_w2"] == 0.0 and base["one_option"]["boundary_rate"] == 0.0
    assert base["random"]["boundary_rate"] == pytest.approx(2 / 9)
    # random boundaries at the true rate: recall about the share of candidate steps within the window (w=2: 5/9)
    assert 0.35 < base["random"]["recall_w2"] < 0.75


def test_composition_names_what_each_option_holds():
    from torchrl_options.experiments.minigrid import option_composition

    data = _labelled([[0, 0, 1, 1, 2, 2, 3, 3]])
    comp = option_composition(torch.tensor([[0, 0, 0, 0, 0, 0, 1, 1]]), data, names=["a", "b", "c", "d"],
                              num_options=3)
    assert comp["usage"] == [0.75, 0.25, 0.0] and comp["options_used"] == 2 and comp["max_usage"] == 0.75
    assert comp["merged"] == [["a", "b", "c"]] and comp["majority_option"]["d"] == [1, 1.0]
    assert comp["contents"][0] == pytest.approx({"a": 1 / 3, "b": 1 / 3, "c": 1 / 3})
    assert comp["mean_segment_length"] == 4.0 and comp["reference_mean_segment_length"] == 2.0


def _viewed(true, actions, carried=None, heading=None):
    """``_labelled`` with the skill labels and a MiniGrid observation: the object type on the agent's own cell
    (``carried``, 1 = empty) and the heading one-hot."""
    from torchrl_options.envs.minigrid import NUM_OBJECT_TYPES, VIEW_CHANNELS

    data = _labelled(true, actions)
    B, T = data.batch_size
    view = torch.zeros(B, T, VIEW_CHANNELS, 7, 7)
    carried = torch.ones(B, T, dtype=torch.long) if carried is None else torch.tensor(carried)
    view[..., :NUM_OBJECT_TYPES, 3, 6] = torch.nn.functional.one_hot(carried, NUM_OBJECT_TYPES).float()
    heading = torch.zeros(B, T, dtype=torch.long) if heading is None else torch.tensor(heading)
    obs = torch.cat([view.flatten(-3), torch.nn.functional.one_hot(heading, 4).float()], -1)
    return data.set("observation", obs).set("skill", data["true_option"].clone())


def test_option_information_is_the_explained_share_of_each_target():
    """Exact cases: options that are the skill explain all of it and none of an independent action; options that
    are the turn's side are handed; options that are what is carried explain it; padding is left out."""
    import math

    from torchrl_options.experiments.minigrid import option_information

    skill = [[0, 0, 1, 1, 0, 0, 1, 1]]
    # actions independent of the skill: each skill sees left, right once each
    data = _viewed(skill, [[0, 1, 0, 1, 1, 0, 1, 0]], carried=[[1, 1, 5, 5, 1, 1, 5, 5]])
    info = option_information(torch.tensor(skill), data)
    assert info["skill"] == 1.0 and info["subgoal"] == 1.0 and info["carrying"] == 1.0
    assert info["action"] == 0.0 and info["turn_side"] == 0.0 and info["handed_turns"] == 0.0
    assert math.isnan(info["direction"])  # one heading throughout: nothing to explain
    sides = torch.tensor([[0, 1, 0, 1, 1, 0, 1, 0]])
    info = option_information(sides + 3, data)
    assert info["turn_side"] == 1.0 and info["handed_turns"] == 1.0 and info["skill"] == 0.0
    # options for the two halves: each half holds both skills and both sides equally, so nothing is explained
    info = option_information(torch.tensor([[0, 0, 0, 0, 1, 1, 1, 1]]), data)
    assert info["skill"] == 0.0 and info["turn_side"] == 0.0
    # I(O; X) / H(X) with H(X) = log 2 and the joint counted exactly: options (0, 0, 1, 1, 1, 1, 1, 1) against the
    # skill (0, 0, 1, 1, 0, 0, 1, 1): H(X) - H(X | O) = log 2 - 6/8 H(1/3)
    info = option_information(torch.tensor([[0, 0, 1, 1, 1, 1, 1, 1]]), data)
    h = -(1 / 3 * math.log(1 / 3) + 2 / 3 * math.log(2 / 3))
    assert info["skill"] == pytest.approx((math.log(2) - 0.75 * h) / math.log(2))
    # padding is ignored: the same data with two padded steps of noise appended
    padded = _viewed([[0, 0, 1, 1, 0, 0, 1, 1, 1, 0]], [[0, 1, 0, 1, 1, 0, 1, 0, 0, 1]],
                     carried=[[1, 1, 5, 5, 1, 1, 5, 5, 1, 1]])
    padded["collector", "mask"][:, 8:] = False
    assert option_information(torch.tensor([[0, 0, 1, 1, 0, 0, 1, 1, 0, 1]]), padded) == option_information(
        torch.tensor(skill), data)


def test_option_information_rejects_bad_input_at_the_door():
    import math

    from torchrl_options.experiments.minigrid import option_information

    data = _viewed([[0, 1]], [[0, 1]])
    with pytest.raises(ValueError, match="predicted must be"):
        option_information(torch.zeros(1, 3, dtype=torch.long), data)
    for handed in (0.4, float("nan"), True):
        with pytest.raises(ValueError, match="handed"):
            option_information(torch.zeros(1, 2, dtype=torch.long), data, handed=handed)
    with pytest.raises(TypeError, match="integer option indices"):
        option_information(torch.zeros(1, 2), data)
    # no valid step: nothing to explain, every share nan (not a crash)
    empty = data.clone().set(("collector", "mask"), torch.zeros(1, 2, dtype=torch.bool))
    assert all(math.isnan(v) for v in option_information(torch.zeros(1, 2, dtype=torch.long), empty).values())
    with pytest.raises(ValueError, match="'observation'"):
        option_information(torch.zeros(1, 2, dtype=torch.long), data.exclude("observation"))
    with pytest.raises(ValueError, match="observation must have"):
        option_information(torch.zeros(1, 2, dtype=torch.long), data.set("observation", torch.zeros(1, 2, 5)))


def test_coverage_and_information_tables_over_seeds():
    from torchrl_options.experiments import mean_interval
    from torchrl_options.experiments.minigrid import coverage_markdown, information_markdown

    def comp(part):  # option 0 holds all of a and 0.9 of its steps; b is split, ``part`` of it in option 1
        return {"usage": [0.5, 0.5], "contents": [{"a": 0.9, "b": 0.1}, {"b": 1.0}],
                "majority_option": {"a": [0, 1.0], "b": [1, part]}}

    recs = [{"level": "L", "seed": s, "method": {"network": "conv"}, "skill": {"composition": comp(p)},
             "information": {"skill": p, "subgoal": p, "action": 0.1, "turn_side": 0.5, "direction": 0.0,
                             "carrying": 0.2, "handed_turns": 0.3}} for s, p in enumerate((0.4, 0.6, 0.8))]
    lines = coverage_markdown(recs).splitlines()
    lo, hi = mean_interval([0.4, 0.6, 0.8])[1:]
    # b (0.55 of the steps) before a (0.45); the split one held at 0.6 on average, under half on one seed
    assert lines[2].startswith("| L | conv K=5 | b | 3 | 0.55 | ") and lines[3].startswith("| L | conv K=5 | a | 3 | 0.45 |")
    assert f"| 0.600 [{lo:.3f}, {hi:.3f}] | 0.400 | 1 |" in lines[2]
    with pytest.raises(ValueError, match="granularity"):
        coverage_markdown(recs, "skills")
    text = information_markdown(recs + [{"level": "M", "seed": 0, "method": {}}])  # records without it are left out
    assert len(text.splitlines()) == 3 and f"| L | conv K=5 | 3 | 0.600 [{lo:.3f}, {hi:.3f}] |" in text


def test_with_previous_action_appends_the_last_action_and_keeps_steps_chained():
    from tensordict import TensorDict

    from torchrl_options.experiments.minigrid import with_previous_action

    obs = torch.arange(2 * 4 * 3, dtype=torch.float32).reshape(2, 4, 3)
    nxt = obs + 100
    mask = torch.tensor([[True] * 4, [True, True, False, False]])
    action = torch.tensor([[3, 0, 6, 1], [2, 5, -1, -1]])  # -1 on padding, as bot_demonstrations pads
    data = TensorDict({"observation": obs, ("next", "observation"): nxt, "action": action,
                       ("collector", "mask"): mask}, [2, 4])
    out = with_previous_action(data)
    assert out["observation"].shape == (2, 4, 10) and torch.equal(data["observation"], obs)  # input unchanged
    assert torch.equal(out["observation"][..., :3], obs) and torch.equal(out["next", "observation"][..., :3], nxt)
    prev = out["observation"][..., 3:]
    assert prev[:, 0].abs().sum() == 0  # no previous action at a trajectory's start
    assert prev[0, 1:].argmax(-1).tolist() == [3, 0, 6] and prev[1, 1].argmax().item() == 2
    assert out["next", "observation"][0, :, 3:].argmax(-1).tolist() == [3, 0, 6, 1]
    assert out["next", "observation"][1, 2:, 3:].abs().sum() == 0 and prev[1, 2:].abs().sum() == 0  # padding zero
    # consecutive valid steps chain: the next observation of step t is the observation of step t + 1
    assert torch.equal(out["next", "observation"][0, :3, 3:], out["observation"][0, 1:, 3:])
    with pytest.raises(ValueError, match="'action' must be in 0..5"):
        with_previous_action(data, 6)
    with pytest.raises(ValueError, match="'action' must be integer"):
        with_previous_action(data.clone().set("action", action.float()))
    with pytest.raises(ValueError, match="has no"):
        with_previous_action(data.exclude(("next", "observation")))
    with pytest.raises(TypeError, match="num_actions"):
        with_previous_action(data, 7.0)


def test_option_factory_refuses_a_view_that_does_not_fit():
    from torchrl_options.experiments.minigrid import option_factory

    assert option_factory("conv", 3, in_features=991, extra_features=11)().extra_features == 11
    with pytest.raises(ValueError, match="in_features must be"):
        option_factory("conv", 3, in_features=991)


def test_summary_table_intervals_are_student_t_over_seeds():
    from torchrl_options.experiments import mean_interval
    from torchrl_options.experiments.minigrid import segmentation_summary
    from torchrl_options.experiments.minigrid.summary import segmentation_markdown

    rows = ("ddo", "action_change", "random", "one_option")
    recs = [{"level": "L", "seed": s, "method": {"network": "mlp", "num_options": 2},
             "subgoal": {**{r: {"label_accuracy": 0.5 + 0.01 * s * (r == "ddo"), "f1_w2": 0.1 * s} for r in rows},
                         "composition": {"max_usage": 0.8}}} for s in range(5)]
    cell = segmentation_summary(recs)[("L", "mlp K=2")]
    assert cell["seeds"] == 5
    assert cell["ddo"]["label_accuracy"] == pytest.approx(mean_interval([0.5, 0.51, 0.52, 0.53, 0.54]))
    assert cell["random"]["f1_w2"] == pytest.approx(mean_interval([0.0, 0.1, 0.2, 0.3, 0.4]))
    text = segmentation_markdown(recs)
    assert "| L | mlp K=2 | DDO | 5 | 0.520 [" in text and "one option everywhere" in text


# ----------------------------------------------------------------------------------------------- pipeline
@needs_minigrid
def test_segmentation_cell_record_is_plain_data_and_baselines_do_not_depend_on_the_method(demos):
    import json

    from torchrl_options.experiments.minigrid import segmentation_cell

    a = segmentation_cell(TINY, 0, method={"num_iterations": 3, "restarts": 1}, demonstrations=demos.data)
    b = segmentation_cell(TINY, 0, method={"network": "conv", "num_options": 2, "num_iterations": 3},
                          demonstrations=demos.data)
    json.dumps(a), json.dumps(b)
    assert a["num_steps"] == int(demos.data["collector", "mask"].sum())
    assert a["method"] == {"network": "mlp", "num_options": 5, "num_iterations": 3, "restarts": 1}
    for gran in ("subgoal", "skill"):
        assert a[gran]["action_change"] == b[gran]["action_change"] and a[gran]["one_option"] == b[gran]["one_option"]
        assert 0 <= a[gran]["ddo"]["label_accuracy"] <= 1 and len(b[gran]["composition"]["usage"]) == 2
    assert a["fit"]["iterations"] == 3 and a["fit"]["cpu_seconds"] > 0
    from torchrl_options.experiments.minigrid.scoring import INFORMATION_TARGETS

    assert set(a["information"]) == {*INFORMATION_TARGETS, "handed_turns"}
    c = segmentation_cell(TINY, 0, method={"network": "conv", "num_options": 2, "num_iterations": 2, "starts": "given",
                                           "previous_action": True}, demonstrations=demos.data)
    assert c["method"]["previous_action"] is True and c["num_steps"] == a["num_steps"]
    assert c["skill"]["one_option"] == a["skill"]["one_option"]  # scored on the bot's own data
    with pytest.raises(TypeError, match="previous_action"):
        segmentation_cell(TINY, 0, method={"previous_action": 1}, demonstrations=demos.data)


@needs_minigrid
def test_custom_modules_get_the_default_starts_through_options_factory(demos, monkeypatch):
    """``starts="factory"`` (the default for option_factory's modules) hands discover_options a factory, so every
    restart is a fresh module; ``starts="given"`` passes one module made from the seed (rounds 1-4)."""
    import torchrl_options
    from torchrl_options.experiments.minigrid import segmentation_cell

    calls = []
    real = torchrl_options.discover_options

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(torchrl_options, "discover_options", spy)
    method = {"network": "conv", "num_options": 2, "num_iterations": 3, "restarts": 2, "restart_iterations": 2}
    a = segmentation_cell(TINY, 0, method=dict(method), demonstrations=demos.data)
    again = segmentation_cell(TINY, 0, method=dict(method), demonstrations=demos.data)
    given = {k: v for k, v in method.items() if not k.startswith("restart")}  # one module: one start
    b = segmentation_cell(TINY, 0, method={**given, "starts": "given"}, demonstrations=demos.data)
    assert callable(calls[0]["options_factory"]) and "options" not in calls[0] and calls[0]["num_actions"] == 7
    assert isinstance(calls[2]["options"], torch.nn.Module) and "options_factory" not in calls[2]
    assert a["method"]["starts"] == "factory" and b["method"]["starts"] == "given"
    assert a["subgoal"]["ddo"] == again["subgoal"]["ddo"] and a["labels"] == again["labels"]  # seeded
    assert a["fit"]["log_likelihood_per_step"] != b["fit"]["log_likelihood_per_step"]
    with pytest.raises(ValueError, match="starts is for the modules of option_factory"):
        segmentation_cell(TINY, 0, method={"starts": "given"}, demonstrations=demos.data)
    with pytest.raises(ValueError, match="starts"):
        segmentation_cell(TINY, 0, method={"network": "conv", "starts": "twice"}, demonstrations=demos.data)


@needs_minigrid
def test_options_files_round_trip_both_networks(tmp_path):
    from tensordict import TensorDict

    from torchrl_options.experiments.minigrid.pipeline import load_minigrid_options, save_minigrid_options
    from torchrl_options.experiments.minigrid.segmentation import option_factory

    x = TensorDict(observation=torch.rand(3, observation_size()), batch_size=[3])
    for network in ("mlp-module", "conv"):
        options = option_factory(network, 3)()
        save_minigrid_options(options, str(tmp_path / f"{network}.pt"), {"k": 3})
        back, meta = load_minigrid_options(str(tmp_path / f"{network}.pt"))
        assert type(back) is type(options) and meta == {"k": 3}
        torch.testing.assert_close(back(x.clone())["option_logits"], options(x.clone())["option_logits"])
    torch.save({"format": "other"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a MiniGrid options file"):
        load_minigrid_options(str(tmp_path / "bad.pt"))


def test_config_refuses_bad_settings():
    from torchrl_options.experiments.minigrid import MiniGridConfig

    with pytest.raises(ValueError, match="conditions must be"):
        MiniGridConfig(conditions=["ppo-B"])
    with pytest.raises(ValueError, match="segmentation_levels"):
        MiniGridConfig(segmentation_levels=["MiniGrid-DoorKey-5x5-v0"])
    with pytest.raises(ValueError, match="H1 condition"):
        MiniGridConfig(rl_level="MiniGrid-DoorKey-5x5-v0", conditions=["ppo-A", "ppo-H1"])
    assert MiniGridConfig(rl_level="MiniGrid-DoorKey-5x5-v0", conditions=["ppo-A", "ppo-H1t"]).rl_level
    with pytest.raises(TypeError, match="rl_frames"):
        MiniGridConfig(rl_frames=1.5)
    with pytest.raises(ValueError, match="network"):
        MiniGridConfig(network="transformer")
    with pytest.raises(ValueError, match="unknown MiniGrid settings"):
        MiniGridConfig.from_dict({"frames": 3})


def test_rl_summary_pairs_with_the_algorithms_actions_only():
    from torchrl_options.experiments import paired_difference_interval
    from torchrl_options.experiments.minigrid import frames_to_reach, rl_summary

    rows = []
    for seed in range(3):
        for cond, successes in (("ppo-A", [0, 0, 0, 0, 1, 1]), ("ppo-H1", [0, 1, 1, 1, 1, 1]),
                                ("dqn-A", [0] * 6), ("dqn-H1", [0, 0, 0, 0, 0, seed % 2])):
            for e, s in enumerate(successes):
                rows.append(dict(setting="L", condition=cond, seed=seed, episode=e, frames=100 * (e + 1),
                                 **{"return": 0.7 * s}))
    out = {s.condition: s for s in rl_summary(rows, target=1.0, window=2)}
    assert out["ppo-H1"].frames_to_reach == [300] * 3 and out["ppo-A"].frames_to_reach == [600] * 3
    assert out["dqn-A"].reached == 0 and out["dqn-A"].reach_interval[0] == 600  # not reached: the budget
    assert out["ppo-H1"].diff_final is None or out["ppo-H1"].diff_final[0] == 0.0  # both end at 1.0
    dqn = out["dqn-H1"]
    assert dqn.diff_final == pytest.approx(paired_difference_interval([0.0, 0.5, 0.0], [0.0, 0.0, 0.0]))
    assert dqn.verdict.endswith("(3 seeds)") and out["ppo-A"].verdict is None
    assert frames_to_reach([1, 1], [5, 9], 1.0, 2) == 9


# ----------------------------------------------------------------------------------------------- recipe
def _recipe():
    import importlib.util
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location("minigrid_recipe", os.path.join(root, "recipes", "minigrid.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(overrides):
    import os

    from hydra import compose, initialize_config_dir

    from torchrl_options.experiments.minigrid import store_minigrid_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    store_minigrid_config()
    with initialize_config_dir(config_dir=os.path.join(root, "recipes", "config"), version_base="1.3"):
        return compose("minigrid", overrides=overrides)


def test_scales_compose():
    from omegaconf import OmegaConf

    from torchrl_options.experiments.minigrid import MiniGridConfig

    for scale in ("tiny", "default", "paper", "unlocklocal", "doorkey", "doorkey16", "keycorridor"):
        cfg = _config([f"minigrid_scale={scale}"])
        config = MiniGridConfig.from_dict(OmegaConf.to_container(cfg.minigrid))
        assert cfg.scale_name == scale and config.conditions
    assert _config(["minigrid_scale=paper"]).minigrid.rl_seeds >= 10
    doorkey = _config(["minigrid_scale=doorkey"]).minigrid  # transfer only: the bot cannot play DoorKey
    assert doorkey.rl_level.startswith("MiniGrid-") and not any(c.endswith("-H1") for c in doorkey.conditions)


@needs_minigrid
def test_episode_cut_warning_flags_short_chunks_and_no_shipped_scale():
    """Each checkpoint chunk of an RL cell restarts the episodes: chunks shorter than ten of the level's episodes per
    env are flagged, naming the setting and the least value that passes; no experiment scale is flagged (the tiny
    test scale is, on purpose: its cells resume from mid-cell checkpoints)."""
    from omegaconf import OmegaConf

    from torchrl_options.experiments.minigrid import MiniGridConfig
    from torchrl_options.experiments.minigrid.pipeline import episode_cut_warning

    for scale in ("tiny", "default", "paper", "unlocklocal", "doorkey", "doorkey16", "keycorridor"):
        config = MiniGridConfig.from_dict(OmegaConf.to_container(_config([f"minigrid_scale={scale}"]).minigrid))
        assert (episode_cut_warning(config) is None) == (scale != "tiny"), scale
    # DoorKey-16x16's 2560-step episodes against 10240-frame chunks over 4 envs: one episode per env per chunk
    short = MiniGridConfig(rl_level="MiniGrid-DoorKey-16x16-v0", conditions=["ppo-A"], rl_frames=50_000,
                           checkpoint_every=10_240)  # fmt: skip
    message = episode_cut_warning(short)
    assert "checkpoint_every=10240" in message and "2560-step episodes" in message and "102400" in message
    assert episode_cut_warning(MiniGridConfig(**{**short.__dict__, "checkpoint_every": 102_400})) is None
    assert episode_cut_warning(MiniGridConfig(**{**short.__dict__, "max_episode_steps": 256})) is None
    # checkpoint_every = rl_frames is still two chunks: 50,000 frames round down to 97 PPO batches of 512
    assert "50176 (one chunk per cell)" in episode_cut_warning(MiniGridConfig(**{**short.__dict__,
                                                                              "checkpoint_every": 50_000}))
    # DQN's 64-frame batches (its default): 51,200 is one chunk for both
    both = MiniGridConfig(**{**short.__dict__, "conditions": ["ppo-A", "dqn-A"], "checkpoint_every": 51_200})
    assert episode_cut_warning(both) is None


@needs_minigrid
def test_recipe_tiny_end_to_end_resumes_and_refuses_changed_settings(tmp_path, capsys):
    import os

    from torchrl_options.experiments import ResultsLog
    from torchrl_options.experiments.minigrid.summary import read_records

    out = str(tmp_path / "run")
    recipe = _recipe()
    summary = recipe.run(_config(["minigrid_scale=tiny", f"out_dir={out}", "progress=false"]))
    for name in ("summary.md", "segmentation.jsonl", "results.csv", "curves.png", "minigrid.log", "settings.json"):
        assert os.path.exists(os.path.join(out, name)), name
    assert "one option everywhere" in summary and "ppo-H1t" in summary and "dqn-H1" in summary
    records = read_records(os.path.join(out, "segmentation.jsonl"))
    # the segmentation level (UnlockLocal, also the RL level) and the transfer source, once each
    assert sorted(r["level"] for r in records) == ["BabyAI-UnlockLocal-v0", "BabyAI-UnlockPickup-v0"]
    rows = ResultsLog(os.path.join(out, "results.csv")).rows()
    assert {r["condition"] for r in rows} == {"ppo-A", "ppo-H1", "ppo-H1t", "dqn-A", "dqn-H1"}
    assert all(r["frames"] <= 256 for r in rows)
    # again: every cell is found finished, nothing is recomputed
    before = open(os.path.join(out, "results.csv")).read()
    recipe.run(_config(["minigrid_scale=tiny", f"out_dir={out}", "progress=false"]))
    assert open(os.path.join(out, "results.csv")).read() == before
    assert len(read_records(os.path.join(out, "segmentation.jsonl"))) == 2
    with pytest.raises(ValueError, match="rl_frames"):
        recipe.run(_config(["minigrid_scale=tiny", f"out_dir={out}", "progress=false", "minigrid.rl_frames=512"]))


@needs_minigrid
def test_an_interrupted_rl_cell_resumes_as_the_uninterrupted_one(tmp_path, monkeypatch):
    from torchrl_options.agents import OptionsPPO
    from torchrl_options.experiments import Cell
    from torchrl_options.experiments.minigrid import MiniGridConfig, run_minigrid_cell

    config = MiniGridConfig(rl_level=TINY, conditions=["ppo-A"], rl_frames=192, num_envs=2, frames_per_batch=64,
                            ppo_minibatch=32, ppo_epochs=1, hidden_sizes=[8], checkpoint_every=64,
                            max_episode_steps=16, segmentation_levels=[], segmentation_seeds=0)
    cell = Cell(TINY, "ppo-A", 0)
    whole = run_minigrid_cell(cell, config=config, out_dir=str(tmp_path / "a"))
    calls = {"n": 0}
    train = OptionsPPO.train

    def interrupted(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return train(self, *args, **kwargs)

    monkeypatch.setattr(OptionsPPO, "train", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_minigrid_cell(cell, config=config, out_dir=str(tmp_path / "b"))
    assert (tmp_path / "b" / "rl" / f"{cell.name}.partial.pt").exists()
    monkeypatch.setattr(OptionsPPO, "train", train)
    resumed = run_minigrid_cell(cell, config=config, out_dir=str(tmp_path / "b"))
    assert resumed.returns == whole.returns and resumed.frames == whole.frames
    assert not (tmp_path / "b" / "rl" / f"{cell.name}.partial.pt").exists()
