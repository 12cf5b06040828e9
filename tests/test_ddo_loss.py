"""DDOLoss: the Expectation-Gradient identity of section 4.2, TorchRL batch layouts, keys and bad input."""
import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_options import as_trajectory_batch, DDOLoss, forward_backward, GaussianOptionsMLP, MetaControlMLP, option_log_probs, OptionsMLP


def _trajectories(B=4, T=12, obs_dim=3, A=4, lengths=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, T + 1, obs_dim, generator=g)
    lengths = lengths or [T] * B
    mask = torch.arange(T)[None] < torch.tensor(lengths)[:, None]
    terminated = torch.zeros(B, T, 1, dtype=torch.bool)
    terminated[0, lengths[0] - 1] = True
    return TensorDict(
        {
            "observation": obs[:, :-1].clone(),
            "action": torch.randint(A, (B, T), generator=g),
            "next": {"observation": obs[:, 1:].clone(), "terminated": terminated},
            ("collector", "mask"): mask,
        },
        [B, T],
    )


@pytest.mark.parametrize("learned_meta", [False, True])
def test_gradient_equals_weighted_cross_entropy(learned_meta):
    """The loss gradient is the explicit G-step of section 4.2 built from detached u, v, w."""
    torch.manual_seed(0)
    data = _trajectories(lengths=[12, 9, 5, 1])
    options = OptionsMLP(3, 4, 3, num_cells=8)
    meta = MetaControlMLP(3, 3, num_cells=8) if learned_meta else None
    loss = DDOLoss(options, meta)
    params = list(loss.parameters())

    grads = torch.autograd.grad(loss(data)["loss_ddo"], params)

    p = loss.log_probabilities(data)
    with torch.no_grad():
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
    mask = p["mask"]
    last = mask.sum(1) - 1
    steps = torch.arange(mask.shape[1])
    before_last = (steps[None] < last[:, None]).unsqueeze(-1)
    at_last_terminal = ((steps[None] == last[:, None]) & p["terminal"][:, None]).unsqueeze(-1)
    u, v, w = fb.u, fb.v, fb.w
    objective = (
        (u * p["log_pi"]).sum()
        + (v * p["log_eta"]).sum()
        + torch.where(before_last, (u - w) * p["log_term"] + w * p["log_cont"], 0.0).sum()
        + torch.where(at_last_terminal, u * p["log_term"], 0.0).sum()
    )
    explicit = torch.autograd.grad(-objective / mask.sum(), params, allow_unused=True)
    assert p["terminal"][0] and not p["terminal"][1:].any()
    for g, e in zip(grads, explicit):
        torch.testing.assert_close(g, torch.zeros_like(g) if e is None else e, rtol=1e-4, atol=1e-6)


def test_single_option_equals_behaviour_cloning():
    torch.manual_seed(1)
    data = _trajectories(lengths=[12, 3, 7, 12])
    options = OptionsMLP(3, 4, 1, num_cells=8)
    # no terminal row: a terminal row would add log psi(s_T) to the likelihood
    out = DDOLoss(options, terminal_at_end=False)(data)
    logits = options(data.select("observation"))["option_logits"][..., 0, :]
    bc = torch.nn.functional.cross_entropy(logits[data["collector", "mask"]], data["action"][data["collector", "mask"]])
    torch.testing.assert_close(out["loss_ddo"], bc)
    torch.testing.assert_close(out["option_entropy"], torch.tensor(0.0))


def test_diagnostics_are_detached_and_sensible():
    data = _trajectories()
    out = DDOLoss(OptionsMLP(3, 4, 3))(data)
    assert out["loss_ddo"].requires_grad
    for key in ("log_likelihood_per_step", "option_duration", "option_entropy", "termination_probability"):
        assert not out[key].requires_grad
    assert out["option_duration"] >= 1
    assert 0 <= out["option_entropy"] <= math.log(3) + 1e-6
    assert 0 < out["termination_probability"] < 1
    torch.testing.assert_close(out["log_likelihood_per_step"], -out["loss_ddo"].detach())


def test_termination_is_evaluated_at_the_next_state():
    """psi enters at s_{t+1}: changing the last next-observation changes the loss only with a terminal row."""
    torch.manual_seed(0)
    options = OptionsMLP(3, 4, 2, num_cells=8)
    data = _trajectories(B=1, T=6)
    changed = data.clone()
    changed["next", "observation"][0, -1] += 5.0
    loss = DDOLoss(options, terminal_at_end=True)
    data["next", "terminated"][:] = False
    changed["next", "terminated"][:] = False
    torch.testing.assert_close(loss(data)["loss_ddo"], loss(changed)["loss_ddo"])
    data["next", "terminated"][0, -1] = True
    changed["next", "terminated"][0, -1] = True
    assert not torch.allclose(loss(data)["loss_ddo"], loss(changed)["loss_ddo"])
    # and the current observation at t=0 does not enter termination: shifting next obs at t=2 changes the loss
    other = data.clone()
    other["next", "observation"][0, 2] += 5.0
    assert not torch.allclose(loss(data)["loss_ddo"], loss(other)["loss_ddo"])


def test_reductions():
    data = _trajectories(lengths=[12, 5, 5, 5])
    options = OptionsMLP(3, 4, 2)
    per_traj = DDOLoss(options, reduction="none")(data)["loss_ddo"]
    assert per_traj.shape == (4,)
    torch.testing.assert_close(DDOLoss(options, reduction="sum")(data)["loss_ddo"], per_traj.sum())
    torch.testing.assert_close(DDOLoss(options)(data)["loss_ddo"], per_traj.sum() / 27)


def test_set_keys_and_one_hot_actions():
    torch.manual_seed(0)
    data = _trajectories()
    options = OptionsMLP(3, 4, 2)
    ref = DDOLoss(options)(data)["loss_ddo"]
    renamed = data.clone()
    renamed.set(("expert", "act"), torch.nn.functional.one_hot(renamed.pop("action"), 4))
    renamed.set("valid", renamed.pop(("collector", "mask")))
    loss = DDOLoss(options)
    loss.set_keys(action=("expert", "act"), mask="valid")
    torch.testing.assert_close(loss(renamed)["loss_ddo"], ref)
    assert ("expert", "act") in loss.in_keys and "valid" in loss.in_keys


def test_padding_is_ignored():
    torch.manual_seed(0)
    data = _trajectories(lengths=[12, 6, 12, 3])
    options = OptionsMLP(3, 4, 2)
    ref = DDOLoss(options)(data)["loss_ddo"]
    data["observation"][1, 6:] = float("nan")
    data["next", "observation"][1, 6:] = float("inf")
    data["action"][1, 6:] = 99
    out = DDOLoss(options)(data)["loss_ddo"]
    torch.testing.assert_close(out, ref)
    out.backward()
    assert all(torch.isfinite(p.grad).all() for p in options.parameters())


def test_gaussian_options_log_probs_match_torch_distributions():
    torch.manual_seed(0)
    options = GaussianOptionsMLP(3, 2, 3, num_cells=8, init_scale=0.7)
    td = options(TensorDict({"observation": torch.randn(5, 3)}, [5]))
    action = torch.randn(5, 2)
    logp = option_log_probs(td, action)
    for h in range(3):
        dist = torch.distributions.Independent(torch.distributions.Normal(td["option_loc"][:, h], td["option_scale"][:, h]), 1)
        torch.testing.assert_close(logp[:, h], dist.log_prob(action))


def test_gaussian_ddo_loss_trains():
    torch.manual_seed(0)
    data = _trajectories()
    data["action"] = torch.randn(4, 12, 2)
    options = GaussianOptionsMLP(3, 2, 2, num_cells=8)
    out = DDOLoss(options)(data)
    out["loss_ddo"].backward()
    assert options.raw_scale.grad.abs().sum() > 0


def test_works_on_slice_sampler_batches():
    """Trajectories from a replay buffer with a SliceSampler, split into [B, T] with a mask."""
    from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer

    flat = _trajectories(B=3, T=20).exclude(("collector", "mask")).reshape(-1)
    flat.set(("collector", "traj_ids"), torch.arange(60) // 20)
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(100),
        sampler=SliceSampler(num_slices=4, traj_key=("collector", "traj_ids"), strict_length=False),
        batch_size=32,
    )
    rb.extend(flat)
    # (TorchRL's split_trajectories merges two slices of one trajectory: as_trajectory_batch keeps them apart)
    batch = as_trajectory_batch(rb.sample(), trajectory_key=("collector", "traj_ids"))
    assert batch.batch_size[0] == 4 and batch["collector", "mask"].sum() == 32
    out = DDOLoss(OptionsMLP(3, 4, 2))(batch)
    assert torch.isfinite(out["loss_ddo"])


def test_works_on_padded_collector_trajectories():
    """Whole episodes from a TorchRL Collector with traj_format='padded'."""
    from torchrl.collectors import Collector
    from torchrl.envs import StepCounter, TransformedEnv
    from torchrl.testing.mocking_classes import DiscreteActionVecMockEnv

    env = TransformedEnv(DiscreteActionVecMockEnv(), StepCounter(max_steps=7))
    collector = Collector(env, policy=None, frames_per_batch=30, total_frames=30, trajs_per_batch=3, traj_format="padded")
    batch = next(iter(collector))
    collector.shutdown()
    obs_dim = batch["observation"].shape[-1]
    A = batch["action"].shape[-1]
    assert batch["collector", "mask"].ndim == 2
    out = DDOLoss(OptionsMLP(obs_dim, A, 2))(batch)  # one-hot actions of the mock env
    out["loss_ddo"].backward()
    assert torch.isfinite(out["loss_ddo"])


class TestBadInput:
    def test_action_out_of_range(self):
        data = _trajectories()
        data["action"][2, 3] = 4
        with pytest.raises(ValueError, match="'action' holds 4, outside"):
            DDOLoss(OptionsMLP(3, 4, 2))(data)

    def test_action_wrong_shape(self):
        data = _trajectories()
        data["action"] = torch.zeros(4, 12, 3, dtype=torch.long)
        with pytest.raises(ValueError, match="action"):
            DDOLoss(OptionsMLP(3, 4, 2))(data)

    def test_nan_observation(self):
        data = _trajectories()
        data["next", "observation"][1, 2, 0] = float("nan")
        with pytest.raises(ValueError, match="'next', 'observation'.*NaN"):
            DDOLoss(OptionsMLP(3, 4, 2))(data)

    def test_mismatched_option_counts(self):
        with pytest.raises(ValueError, match="num_options"):
            DDOLoss(OptionsMLP(3, 4, 2), MetaControlMLP(3, 3))

    def test_meta_control_output_mismatch_at_run_time(self):
        meta = TensorDictModule(torch.nn.Linear(3, 5), in_keys=["observation"], out_keys=["meta_logits"])
        with pytest.raises(ValueError, match="meta_logits.*5"):
            DDOLoss(OptionsMLP(3, 4, 2), meta)(_trajectories())

    def test_termination_output_mismatch(self):
        class Bad(torch.nn.Module):
            def forward(self, obs):
                return torch.zeros(*obs.shape[:-1], 2, 4), torch.zeros(*obs.shape[:-1], 3)

        options = TensorDictModule(Bad(), in_keys=["observation"], out_keys=["option_logits", "termination_logits"])
        with pytest.raises(ValueError, match="termination_logits"):
            DDOLoss(options)(_trajectories())

    def test_empty_batch(self):
        with pytest.raises(ValueError, match="empty"):
            DDOLoss(OptionsMLP(3, 4, 2))(_trajectories()[:0])

    def test_non_prefix_mask(self):
        data = _trajectories()
        data["collector", "mask"][1, 3] = False
        with pytest.raises(ValueError, match="prefix"):
            DDOLoss(OptionsMLP(3, 4, 2))(data)

    def test_wrong_batch_dims(self):
        with pytest.raises(ValueError, match=r"\[B, T\]"):
            DDOLoss(OptionsMLP(3, 4, 2))(_trajectories().unsqueeze(0))


# ---------------------------------------------------------------------------------------------------------------------
# TorchRL's LossModule contract, for both DDO losses (in the style of TorchRL's own loss tests)

from tensordict.nn import TensorDictParams  # noqa: E402

from torchrl_options.hierarchy import HierarchicalDDOLoss, OptionHierarchy  # noqa: E402
from torchrl_options.hierarchy.discover import HierarchicalEStep  # noqa: E402
from torchrl_options.objectives import DDOLossBase  # noqa: E402


def _make_loss(kind, *, meta=False, seed=0, **kwargs):
    """A small loss of each kind over 3 observation features and 4 primitive actions."""
    torch.manual_seed(seed)
    if kind == "flat":
        return DDOLoss(OptionsMLP(3, 4, 2, num_cells=4), MetaControlMLP(3, 2, num_cells=4) if meta else None, **kwargs)
    lower = OptionHierarchy(4, [OptionsMLP(3, 4, 2, num_cells=4)])
    return HierarchicalDDOLoss(
        OptionsMLP(3, 6, 2, num_cells=4), lower, MetaControlMLP(3, 2, num_cells=4) if meta else None, **kwargs
    )


def _flat_params(module):
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


@pytest.mark.parametrize("kind", ["flat", "hierarchical"])
class TestLossModuleContract:
    def test_is_a_loss_module_with_keys(self, kind):
        from torchrl.objectives import LossModule

        loss = _make_loss(kind, meta=True)
        assert isinstance(loss, LossModule) and isinstance(loss, DDOLossBase)
        for key in ["observation", ("next", "observation"), "action", ("collector", "mask"), ("next", "terminated")]:
            assert key in loss.in_keys
        assert loss.out_keys[:2] == ["loss_ddo", "log_likelihood_per_step"]
        assert set(loss(_trajectories()).keys()) == set(loss.out_keys)
        loss.set_keys(action="expert_action", mask="valid", terminal="done")
        assert {"expert_action", "valid", "done"} <= set(loss.in_keys) and "action" not in loss.in_keys
        loss.set_keys(action=None)  # back to the default
        assert loss.tensor_keys.action == "action"
        with pytest.raises(ValueError, match="not an accepted tensordict key"):
            loss.set_keys(actions="a")

    def test_same_keyword_arguments(self, kind):
        import inspect

        def keywords(cls):
            return {n for n, p in inspect.signature(cls.__init__).parameters.items() if p.kind == p.KEYWORD_ONLY}

        assert keywords(HierarchicalDDOLoss) - {"num_actions"} == keywords(DDOLoss)
        assert {"backend", "diagnostics", "reduction", "terminal_at_end", "action_space"} <= keywords(DDOLoss)
        loss = _make_loss(kind, diagnostics=False, backend="auto")
        out = loss(_trajectories())
        assert set(out.keys()) == {"loss_ddo", "log_likelihood_per_step"} == set(loss.out_keys)
        loss.diagnostics = True
        assert "option_entropy" in loss(_trajectories()).keys()

    def test_networks_are_functional(self, kind):
        loss = _make_loss(kind, meta=True)
        assert loss.functional
        assert isinstance(loss.options_params, TensorDictParams)
        assert isinstance(loss.meta_control_params, TensorDictParams)
        # the parameters are the modules' own: an optimizer over loss.parameters() trains loss.options
        own = {id(p) for p in loss.options.parameters()} | {id(p) for p in loss.meta_control.parameters()}
        assert {id(p) for p in loss.parameters()} == own
        data = _trajectories()
        ref = loss(data)["loss_ddo"].detach()
        net = loss.get_stateful_net("options")
        assert net is not loss.options  # a copy
        for p in net.parameters():
            p.data.add_(0.5)
        loss.from_stateful_net("options", net)
        changed = loss(data)["loss_ddo"].detach()
        assert not torch.allclose(changed, ref)
        torch.testing.assert_close(_flat_params(loss.options), _flat_params(net))
        meta = loss.get_stateful_net("meta_control", copy=True)
        meta_params = _flat_params(meta)
        torch.testing.assert_close(meta_params, _flat_params(loss.meta_control))

    def test_reset_parameters(self, kind):
        loss = _make_loss(kind, meta=True)
        before = _flat_params(loss.options).clone(), _flat_params(loss.meta_control).clone()
        lower = _flat_params(loss.lower_levels).clone() if kind == "hierarchical" else None
        loss.reset_parameters_recursive()
        assert not torch.allclose(_flat_params(loss.options), before[0])
        assert not torch.allclose(_flat_params(loss.meta_control), before[1])
        if lower is not None:  # the fixed lower levels are not the loss's parameters
            torch.testing.assert_close(_flat_params(loss.lower_levels), lower)

    def test_state_dict_round_trip(self, kind):
        data = _trajectories()
        loss = _make_loss(kind, meta=True, seed=0)
        other = _make_loss(kind, meta=True, seed=1)
        state = loss.state_dict()
        assert any(k.startswith("options_params.") for k in state)
        assert any(k.startswith("meta_control_params.") for k in state)
        if kind == "hierarchical":
            assert any(k.startswith("lower_levels.") for k in state)
        assert not torch.allclose(other(data)["loss_ddo"], loss(data)["loss_ddo"])
        other.load_state_dict(state)
        torch.testing.assert_close(other(data)["loss_ddo"], loss(data)["loss_ddo"])

    def test_dtype_cast(self, kind):
        data = _trajectories()
        loss = _make_loss(kind, meta=True)
        ref = loss(data)
        loss = loss.double()
        assert all(p.dtype == torch.float64 for p in loss.options_params.values(True, True))
        if kind == "hierarchical":
            assert all(p.dtype == torch.float64 for p in loss.lower_levels.parameters())
        out = loss(data)
        assert out["loss_ddo"].dtype == torch.float64
        torch.testing.assert_close(out["loss_ddo"].float(), ref["loss_ddo"], rtol=1e-4, atol=1e-5)

    def test_every_network_is_registered(self, kind):
        """What module casts (.to(device), .double()) and state_dict() walk: every network, the fixed levels too."""
        loss = _make_loss(kind, meta=True)
        modules = list(loss.modules())
        assert any(m is loss.options_params for m in modules) and any(m is loss.meta_control_params for m in modules)
        if kind == "hierarchical":
            assert any(m is loss.lower_levels for m in modules)
            assert loss.lower_levels.num_levels == 1 and loss.level == 2
            # ... but they are not trained: parameters() leaves them out
            lower = {id(p) for p in loss.lower_levels.parameters()}
            assert lower and not lower & {id(p) for p in loss.parameters()}
            named = dict(loss.named_parameters())
            assert named and not any(k.startswith("lower_levels.") for k in named)

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda(self, kind):
        data = _trajectories()
        loss = _make_loss(kind, meta=True)
        ref = loss(data)["loss_ddo"]
        out = loss.to("cuda")(data.to("cuda"))["loss_ddo"]
        torch.testing.assert_close(out.cpu(), ref.detach(), rtol=1e-4, atol=1e-5)

    def test_keyword_call(self, kind):
        data = _trajectories(lengths=[12, 9, 5, 1])
        loss = _make_loss(kind)
        ref = loss(data)
        out = loss(
            observation=data["observation"],
            action=data["action"],
            next_observation=data["next", "observation"],
            next_terminated=data["next", "terminated"],
            collector_mask=data["collector", "mask"],
        )
        assert isinstance(out, tuple) and len(out) == len(loss.out_keys)
        for key, value in zip(loss.out_keys, out):
            torch.testing.assert_close(value, ref[key])
        loss.select_out_keys("loss_ddo")
        single = loss(observation=data["observation"], action=data["action"],
                      next_observation=data["next", "observation"])  # fmt: skip
        assert single.shape == ()

    def test_loss_mask_key(self, kind):
        """The issue's reproduction: a 6 + 3 step batch whose padding is marked in ("my", "valid") only."""
        torch.manual_seed(0)
        full = _trajectories(B=2, T=6).exclude(("collector", "mask"))
        full["next", "terminated"][:] = False
        valid = torch.tensor([[True] * 6, [True] * 3 + [False] * 3])
        full["my", "valid"] = valid
        loss = _make_loss(kind)
        unmasked = loss(full)["loss_ddo"]
        parts = [loss(full[:1])["loss_ddo"] * 6, loss(full[1:, :3])["loss_ddo"] * 3]
        expected = sum(parts) / 9
        loss.loss_mask_key = ("my", "valid")
        assert ("my", "valid") in loss.in_keys and loss.mask_keys == [("collector", "mask"), ("my", "valid")]
        # padding with non-finite values and out-of-range actions is ignored, gradients stay finite
        full["observation"][1, 3:] = float("nan")
        full["next", "observation"][1, 3:] = float("inf")
        full["action"][1, 3:] = 99
        out = loss(full)["loss_ddo"]
        torch.testing.assert_close(out, expected)
        assert not torch.allclose(out, unmasked)
        out.backward()
        assert all(torch.isfinite(p.grad).all() for p in loss.parameters())
        # None: only tensor_keys.mask (absent here) -> the NaN padding now counts and is refused
        loss.loss_mask_key = None
        assert loss.mask_keys == [("collector", "mask")]
        with pytest.raises(ValueError, match="NaN"):
            loss(full)
        # "auto" reads TorchRL's own masks: ("collector", "mask") and "shifted_valid"
        loss.loss_mask_key = "auto"
        full["shifted_valid"] = full.pop(("my", "valid")).unsqueeze(-1)
        torch.testing.assert_close(loss(full)["loss_ddo"], expected)
        # several masks: a step is valid where all of them say so
        full["collector", "mask"] = torch.tensor([[True] * 5 + [False], [True] * 6])
        both = loss(full)["loss_ddo"]
        torch.testing.assert_close(both, (loss(full[:1, :5])["loss_ddo"] * 5 + parts[1]) / 8)
        with pytest.raises(ValueError, match="loss_mask_key"):
            loss.loss_mask_key = 3

    def test_one_synchronisation_per_check(self, kind, monkeypatch):
        """log_probabilities checks the batch with one read-back (tolist), no item()/bool() on tensors."""
        data = _trajectories(lengths=[12, 9, 5, 1])
        loss = _make_loss(kind, meta=True)
        calls = []
        for name in ("tolist", "item", "__bool__"):
            original = getattr(torch.Tensor, name)

            def counted(self, *args, _name=name, _original=original, **kwargs):
                calls.append(_name)
                return _original(self, *args, **kwargs)

            monkeypatch.setattr(torch.Tensor, name, counted)
        loss.log_probabilities(data)
        monkeypatch.undo()
        assert calls == ["tolist"]


def test_hierarchical_e_step_checks_and_runs_the_recursion_once(monkeypatch):
    """On logged iterations too (diagnostics on): one log_probabilities (one check), one recursion, and the record
    equals the loss's outputs."""
    import torchrl_options.hierarchy.loss as hloss

    data = _trajectories(lengths=[12, 9, 5, 1])
    loss = _make_loss("hierarchical", meta=True)
    expected = loss(data)
    calls = {"log_probabilities": 0, "recursion": 0}
    log_probabilities, recursion = loss.log_probabilities, hloss.hierarchical_forward_backward

    def counted_log_probabilities(td):
        calls["log_probabilities"] += 1
        return log_probabilities(td)

    def counted_recursion(*args, **kwargs):
        calls["recursion"] += 1
        return recursion(*args, **kwargs)

    monkeypatch.setattr(loss, "log_probabilities", counted_log_probabilities)
    monkeypatch.setattr(hloss, "hierarchical_forward_backward", counted_recursion)
    record, objective = HierarchicalEStep(loss)(data)
    assert calls == {"log_probabilities": 1, "recursion": 1}
    assert set(record) == set(expected.keys())
    for key, value in record.items():
        torch.testing.assert_close(value, expected[key].detach(), rtol=1e-5, atol=1e-6)
    # the objective's gradient is the loss's gradient (the Expectation-Gradient identity)
    params = list(loss.parameters())
    g_loss = torch.autograd.grad(expected["loss_ddo"], params)
    g_objective = torch.autograd.grad(objective(), params)
    for a, b in zip(g_loss, g_objective):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


# ---------------------------------------------------------------------------------------------------------------------
# Bad input at the loss's door (issue 26): one row per case, for both losses where the case applies.


def _set(key, value):
    def mutate(td):
        td.set(key, value(td) if callable(value) else value)
        return td

    return mutate


def _at(key, index, value):
    def mutate(td):
        td.get(key)[index] = value
        return td

    return mutate


def _nan_weights(loss):
    with torch.no_grad():
        for p in loss.options.parameters():
            p.fill_(float("nan"))
    return loss


BAD_INPUTS = [
    # (id, mutate the [4, 12] batch, error, phrase of the message)
    ("missing observation", lambda td: td.exclude("observation"), ValueError, r"needs 'observation'"),
    ("missing next observation", lambda td: td.exclude(("next", "observation")), ValueError,
     r"needs \('next', 'observation'\)"),
    ("missing next", lambda td: td.exclude("next"), ValueError, r"under 'next'"),
    ("missing action", lambda td: td.exclude("action"), ValueError, r"action taken at 'action'"),
    ("float action", _set("action", lambda td: td["action"].float()), ValueError, r"'action' must hold integer"),
    ("action of the wrong shape", _set("action", torch.zeros(4, 12, 3, dtype=torch.long)), ValueError,
     r"'action' must hold integer .*\(4, 12, 3\)"),
    ("action out of range", _at("action", (2, 3), 7), ValueError, r"'action' holds 7, outside"),
    ("negative action", _at("action", (0, 0), -1), ValueError, r"'action' holds -1, outside"),
    ("float mask", _set(("collector", "mask"), lambda td: td["collector", "mask"].float()), ValueError,
     r"\('collector', 'mask'\) must be a bool tensor of shape \(4, 12\), got torch.float32"),
    ("mask of the wrong shape", _set(("collector", "mask"), torch.ones(4, 12, 2, dtype=torch.bool)), ValueError,
     r"\('collector', 'mask'\) must be a bool tensor of shape \(4, 12\).*\(4, 12, 2\)"),
    ("mask with a gap", _at(("collector", "mask"), (1, 3), False), ValueError, r"non-empty prefix.*row 1"),
    ("mask with an empty row", _at(("collector", "mask"), (2, slice(None)), False), ValueError,
     r"non-empty prefix.*row 2"),
    ("too many observation features", lambda td: td.set("observation", torch.randn(4, 12, 5)).set(
        ("next", "observation"), torch.randn(4, 12, 5)), ValueError, r"in_features=3.*\(4, 12, 5\)"),
    ("observation without a feature dimension", lambda td: td.set("observation", torch.randn(4, 12)).set(
        ("next", "observation"), torch.randn(4, 12)), ValueError, r"in_features=3.*\(4, 12\)"),
    ("next observation of another shape", _set(("next", "observation"), torch.randn(4, 12, 4)), ValueError,
     r"\('next', 'observation'\) has shape \(4, 12, 4\) but 'observation' has shape \(4, 12, 3\)"),
    ("empty batch", lambda td: td[:0], ValueError, r"empty batch"),
    ("empty trajectories", lambda td: td[:, :0], ValueError, r"empty batch"),
    ("three batch dimensions", lambda td: td.unsqueeze(0), ValueError, r"\[B, T\] tensordict"),
    ("NaN observation at a valid step", _at("observation", (1, 2, 0), float("nan")), ValueError,
     r"'observation' holds NaN or inf at valid step \(b, t\) = \(1, 2\)"),
    ("inf next observation at a valid step", _at(("next", "observation"), (3, 0, 2), float("inf")), ValueError,
     r"\('next', 'observation'\) holds NaN or inf at valid step \(b, t\) = \(3, 0\)"),
    ("terminal of the wrong shape", _set(("next", "terminated"), torch.zeros(4, 12, 2, dtype=torch.bool)),
     ValueError, r"\('next', 'terminated'\) must be a \[B, T\]"),
    ("complex observation", lambda td: td.set("observation", td["observation"].to(torch.complex64)), ValueError,
     r"'observation' must hold real numbers"),
    ("not a tensordict", lambda td: "trajectories", ValueError, r"\[B, T\] tensordict"),
    ("observation not a tensor", _set("observation", lambda td: TensorDict({"x": td["observation"]}, [4, 12])),
     TypeError, r"'observation' \(an input of the networks\) must be a tensor, got TensorDict"),
    ("action not a tensor", _set("action", lambda td: TensorDict({"a": td["action"]}, [4, 12])), TypeError,
     r"'action' must be a tensor of .*actions, got TensorDict"),
]


@pytest.mark.parametrize("kind", ["flat", "hierarchical"])
@pytest.mark.parametrize("case", BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_table(case, kind):
    _, mutate, error, match = case
    loss = _make_loss(kind, meta=True)
    data = mutate(_trajectories())
    with pytest.raises(error, match=match):
        loss(data)


BAD_LOSS_SETUPS = [
    # (id, kinds, make the loss or call it, error, phrase)
    ("options not a module", ["flat"], lambda: DDOLoss(torch.nn.Linear(3, 4)), TypeError,
     r"options must be a TensorDictModuleBase, got Linear"),
    ("meta_control not a module", ["flat"], lambda: DDOLoss(OptionsMLP(3, 4, 2), "learned"), TypeError,
     r"meta_control must be a TensorDictModuleBase or None, got str"),
    ("bad reduction", ["flat", "hierarchical"], lambda kind: _make_loss(kind, reduction="avg"), ValueError,
     r"reduction must be 'mean', 'sum' or 'none', got 'avg'"),
    ("bad backend", ["flat", "hierarchical"], lambda kind: _make_loss(kind, backend="cuda"), ValueError,
     r"backend must be one of .*got 'cuda'"),
    ("bad action space", ["flat", "hierarchical"], lambda kind: _make_loss(kind, action_space="discrete"),
     ValueError, r"action_space must be one of .*got 'discrete'"),
    ("continuous hierarchy", ["hierarchical"], lambda kind: _make_loss(kind, action_space="continuous"),
     ValueError, r"action_space must be one of \('auto', 'categorical'\), got 'continuous'"),
    ("non-bool diagnostics", ["flat", "hierarchical"], lambda kind: _make_loss(kind, diagnostics=1), TypeError,
     r"diagnostics must be True or False, got 1"),
    ("non-bool terminal_at_end", ["flat", "hierarchical"], lambda kind: _make_loss(kind, terminal_at_end="yes"),
     TypeError, r"terminal_at_end must be True or False, got 'yes'"),
    ("lower levels not a hierarchy", ["hierarchical"],
     lambda kind: HierarchicalDDOLoss(OptionsMLP(3, 6, 2), OptionsMLP(3, 4, 2)), TypeError,
     r"lower_levels must be an OptionHierarchy or a sequence"),
    ("options writing NaN", ["flat", "hierarchical"], lambda kind: _nan_weights(_make_loss(kind))(_trajectories()),
     ValueError, r"holds NaN.*at valid step \(b, t\) = \(0, 0\)"),
    ("bad loss_mask_key", ["flat", "hierarchical"],
     lambda kind: setattr(_make_loss(kind), "loss_mask_key", 1.5), ValueError, r"loss_mask_key must be"),
    ("loss mask of the wrong dtype", ["flat", "hierarchical"],
     lambda kind: _with_loss_mask(_make_loss(kind), torch.ones(4, 12, dtype=torch.long)), ValueError,
     r"\('my', 'valid'\) must be a bool tensor of shape \(4, 12\), got torch.int64"),
    ("loss mask not a prefix", ["flat", "hierarchical"],
     lambda kind: _with_loss_mask(_make_loss(kind), torch.arange(12).expand(4, 12) % 2 == 0), ValueError,
     r"\('my', 'valid'\) must mark a non-empty prefix"),
    ("meta-control input NaN at a valid step", ["flat", "hierarchical"], lambda kind: _meta_reading("extra", kind),
     ValueError, r"'extra' holds NaN or inf at valid step \(b, t\) = \(0, 1\)"),
    ("meta-control input missing", ["flat", "hierarchical"], lambda kind: _meta_reading("absent", kind),
     ValueError, r"needs 'absent'"),
]


def _with_loss_mask(loss, mask):
    loss.loss_mask_key = ("my", "valid")
    data = _trajectories()
    data["my", "valid"] = mask
    return loss(data)


def _meta_reading(key, kind):
    loss = _make_loss(kind)
    meta = MetaControlMLP(1, 2, in_keys=[key])
    loss = type(loss)(loss.options, *( [loss.lower_levels] if kind == "hierarchical" else []), meta)
    data = _trajectories()
    data["extra"] = torch.zeros(4, 12, 1)
    data["extra"][0, 1] = float("nan")
    return loss(data)


@pytest.mark.parametrize("case", BAD_LOSS_SETUPS, ids=[c[0] for c in BAD_LOSS_SETUPS])
def test_bad_loss_setup_table(case):
    _, kinds, make, error, match = case
    for kind in kinds:
        with pytest.raises(error, match=match):
            make() if make.__code__.co_argcount == 0 else make(kind)


GAUSSIAN_BAD_INPUTS = [
    ("action of another dimension", _set("action", torch.randn(4, 12, 3)), ValueError,
     r"'action' must be a float tensor of shape \(4, 12, 2\)"),
    ("integer action", _set("action", torch.zeros(4, 12, 2, dtype=torch.long)), ValueError,
     r"'action' must be a float tensor"),
    ("NaN action at a valid step", _at("action", (1, 1, 0), float("nan")), ValueError,
     r"'action' holds NaN or inf at a valid step"),
]


@pytest.mark.parametrize("case", GAUSSIAN_BAD_INPUTS, ids=[c[0] for c in GAUSSIAN_BAD_INPUTS])
def test_gaussian_bad_input_table(case):
    _, mutate, error, match = case
    data = _trajectories()
    data["action"] = torch.randn(4, 12, 2)
    loss = DDOLoss(GaussianOptionsMLP(3, 2, 2, num_cells=4))
    with pytest.raises(error, match=match):
        loss(mutate(data.clone()))
    # padding may hold anything
    data["collector", "mask"][1, 6:] = False
    data["action"][1, 6:] = float("nan")
    assert torch.isfinite(loss(data)["loss_ddo"])


def test_one_hot_action_with_two_ones():
    data = _trajectories()
    data["action"] = torch.nn.functional.one_hot(data["action"], 4)
    data["action"][0, 5, :2] = 1
    with pytest.raises(ValueError, match="one-hot actions must have exactly one 1 per valid step"):
        DDOLoss(OptionsMLP(3, 4, 2))(data)
