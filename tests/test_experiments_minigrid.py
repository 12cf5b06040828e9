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
