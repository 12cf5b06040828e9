"""Discovery of a two-level hierarchy: planted recovery at both levels, the loss, save/load and bad inputs."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_options import DDOLoss, forward_backward, MetaControlMLP, OptionsMLP
from torchrl_options.hierarchy import (
    discover_hierarchy,
    hierarchical_forward_backward,
    HierarchicalDDOLoss,
    load_hierarchy,
    OptionHierarchy,
)
from torchrl_options.testing import label_accuracy
from torchrl_options.testing.planted_hierarchy import planted_two_level_demonstrations


def _data(B=4, T=10, obs_dim=3, A=3, lengths=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, T + 1, obs_dim, generator=g)
    lengths = lengths or [T] * B
    terminated = torch.zeros(B, T, 1, dtype=torch.bool)
    terminated[0, lengths[0] - 1] = True
    return TensorDict(
        {
            "observation": obs[:, :-1].clone(),
            "action": torch.randint(A, (B, T), generator=g),
            "next": {"observation": obs[:, 1:].clone(), "terminated": terminated},
            ("collector", "mask"): torch.arange(T)[None] < torch.tensor(lengths)[:, None],
        },
        [B, T],
    )


def _level1_accuracy(hierarchy, data):
    p = DDOLoss(hierarchy.options(1)).log_probabilities(data)
    with torch.no_grad():
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
    return label_accuracy(fb.u.argmax(-1), data["true_option_1"])


@pytest.fixture(scope="module")
def planted():
    torch.set_num_threads(1)
    data = planted_two_level_demonstrations(32, 60, seed=0)
    hierarchy = discover_hierarchy(
        data, [4, 4], num_iterations=[200, 500], num_cells=16, lr=3e-2, seed=0, progress=False
    )
    return data, hierarchy


def test_planted_two_level_recovery(planted):
    """The most likely option at each level matches the planted one on >= 90% of steps (up to relabelling)."""
    data, hierarchy = planted
    assert hierarchy.num_levels == 2 and hierarchy.action_space_sizes == [4, 8, 12]
    assert _level1_accuracy(hierarchy, data) >= 0.9
    loss = HierarchicalDDOLoss(hierarchy.options(2), hierarchy.levels[:1], num_actions=4)
    with torch.no_grad():
        post = loss.posterior(data)
    acc2 = label_accuracy(post.most_likely(2), data["true_option_2"])
    acc1 = label_accuracy(post.most_likely(1), data["true_option_1"])
    print(f"planted recovery: level 1 {_level1_accuracy(hierarchy, data):.3f} (flat), {acc1:.3f} (joint); level 2 {acc2:.3f}")
    assert acc2 >= 0.9 and acc1 >= 0.9
    # the level-2 options act through the level-1 options, as planted
    assert post.emitter[..., 0].mean() > 0.9


def test_save_load_round_trip(planted, tmp_path):
    _, hierarchy = planted
    path = tmp_path / "hierarchy.pt"
    hierarchy.save(path, metadata={"planted": True})
    loaded, metadata = load_hierarchy(path, with_metadata=True)
    assert metadata == {"planted": True}
    assert loaded.num_options == hierarchy.num_options and loaded.action_space_sizes == hierarchy.action_space_sizes
    td = TensorDict({"observation": torch.rand(6, 2)}, [6])
    for j in (1, 2):
        a, b = hierarchy.options(j)(td.clone()), loaded.options(j)(td.clone())
        assert torch.equal(a["option_logits"], b["option_logits"])
        assert torch.equal(a["termination_logits"], b["termination_logits"])
    assert OptionHierarchy.load(path).num_levels == 2
    with pytest.raises(ValueError, match="not a hierarchy file"):
        torch.save({"format": "other"}, tmp_path / "x.pt")
        load_hierarchy(tmp_path / "x.pt")


def test_learned_meta_control_and_extending_a_hierarchy():
    data = planted_two_level_demonstrations(4, 20, seed=1)
    h = discover_hierarchy(data, [2], num_iterations=3, seed=0, progress=False)
    h = discover_hierarchy(data, [2, 2], hierarchy=h, meta_control="learned", num_iterations=3, progress=False)
    assert h.num_options == [2, 2, 2] and h.action_space_sizes == [4, 6, 8, 10]
    assert isinstance(h.meta_control(3), MetaControlMLP) and h.meta_control(1) is None
    assert h.options(3).num_actions == 8


def test_loss_gradient_trains_only_the_new_level():
    data = _data(lengths=[10, 6, 3, 1])
    lower = OptionHierarchy(3, [OptionsMLP(3, 3, 2, num_cells=4)])
    options, meta = OptionsMLP(3, 5, 2, num_cells=4), MetaControlMLP(3, 2, num_cells=4)
    loss = HierarchicalDDOLoss(options, lower, meta)
    out = loss(data)
    out["loss_ddo"].backward()
    assert all(p.grad is not None for p in [*options.parameters(), *meta.parameters()])
    assert all(p.grad is None for p in lower.parameters())
    assert set(loss.parameters()) == set(options.parameters()) | set(meta.parameters())
    for key in loss.out_keys[1:]:
        assert not out[key].requires_grad and torch.isfinite(out[key])
    # the loss is the exact hierarchical likelihood per valid step
    p = loss.log_probabilities(data)
    ll = hierarchical_forward_backward(p["action"], p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"],
                                       p["mask"], p["terminal"]).log_likelihood
    assert p["terminal"][0] and not p["terminal"][1:].any()
    torch.testing.assert_close(out["loss_ddo"], -ll.sum() / 20)


def test_no_lower_level_equals_ddo_loss():
    data = _data(lengths=[10, 7, 2, 10])
    options = OptionsMLP(3, 3, 3, num_cells=4)
    ours = HierarchicalDDOLoss(options, OptionHierarchy(3))(data)
    ref = DDOLoss(options)(data)
    for key in ("loss_ddo", "option_duration", "option_entropy", "termination_probability"):
        torch.testing.assert_close(ours[key], ref[key])


def test_set_keys():
    data = _data()
    loss = HierarchicalDDOLoss(OptionsMLP(3, 5, 2), [OptionsMLP(3, 3, 2)])
    loss.set_keys(action="expert_action", mask="valid")
    data.rename_key_("action", "expert_action")
    data.rename_key_(("collector", "mask"), "valid")
    assert "expert_action" in loss.in_keys and "valid" in loss.in_keys
    assert torch.isfinite(loss(data)["loss_ddo"])


@pytest.mark.parametrize(
    "build,match",
    [
        (lambda: HierarchicalDDOLoss(OptionsMLP(3, 4, 2), [OptionsMLP(3, 3, 2)]),
         r"options has num_actions=4, but level-2 options choose among A \+ K1 = 3 \+ 2 = 5"),
        (lambda: HierarchicalDDOLoss(OptionsMLP(3, 7, 2), [OptionsMLP(3, 3, 2), OptionsMLP(3, 4, 2)]),
         r"lower_levels: level 2 options have num_actions=4, but level-2 options choose among A \+ K1 = 5"),
        (lambda: HierarchicalDDOLoss(OptionsMLP(3, 5, 2), [OptionsMLP(3, 3, 2)], MetaControlMLP(3, 3)),
         "meta_control has num_options=3"),
        (lambda: OptionHierarchy(3, [OptionsMLP(3, 4, 2)]), "level 1 options have num_actions=4"),
        (lambda: discover_hierarchy(_data(), []), "num_options must be a non-empty list"),
        (lambda: discover_hierarchy(_data(), [2, 0]), "num_options must be a non-empty list"),
        (lambda: discover_hierarchy(_data(), [2, 2], num_iterations=[1]), "num_iterations has 1 entries"),
        (lambda: discover_hierarchy(_data(), [2], meta_control="mlp"), "meta_control must be"),
        (lambda: discover_hierarchy(_data(), [2], hierarchy=OptionHierarchy(3), num_actions=4), "num_actions=4"),
    ],
)
def test_bad_inputs_name_the_argument(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_bad_trajectories():
    loss = HierarchicalDDOLoss(OptionsMLP(3, 5, 2), [OptionsMLP(3, 3, 2)])
    data = _data()
    data["action"][0, 0] = 3
    with pytest.raises(ValueError, match=r"outside the primitive actions \[0, 3\)"):
        loss(data)
    with pytest.raises(ValueError, match="prefix"):
        bad = _data()
        bad["collector", "mask"][0, 0] = False
        loss(bad)


def test_hierarchy_accessors():
    h = OptionHierarchy(4, [OptionsMLP(2, 4, 3), OptionsMLP(2, 7, 2)])
    assert h.option_index(1, 2) == 6 and h.option_index(2, 0) == 7
    assert h.options(2).num_options == 2 and h.meta_control(2) is None
    with pytest.raises(ValueError, match="level must be in"):
        h.options(3)


def test_nested_executors_run_the_hierarchy_call_and_return():
    """A DQN-facing env over primitives + level-1 + level-2 options; a level-2 option never terminates while the
    level-1 option it invoked runs."""
    from torchrl.envs import check_env_specs, TransformedEnv

    from _tiny_envs import Corridor

    torch.manual_seed(0)
    h = OptionHierarchy(2, [OptionsMLP(8, 2, 2, num_cells=4), OptionsMLP(8, 4, 3, num_cells=4)])
    env = TransformedEnv(Corridor(8, max_steps=40))
    for executor in h.executors():
        env.append_transform(executor)
    assert env.action_spec.n == h.action_space_sizes[-1] == 7
    check_env_specs(env)
    env.set_seed(0)
    data = env.rollout(200, break_when_any_done=False)
    lower_ready = data["next", "option"] < 0
    level2_ended = (data["next", "executed_option_2"] >= 0) & (data["next", "option_2"] < 0)
    assert level2_ended.any() and (data["next", "executed_option"] >= 0).any()
    assert not (level2_ended & ~lower_ready & ~data["next", "done"].squeeze(-1)).any()
