"""discover_options: planted structure recovered, inputs, optimizer, seeds, initialisation, save/load."""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_options import (
    as_trajectory_batch,
    DDOLoss,
    discover_options,
    forward_backward,
    load_options,
    MetaControlMLP,
    most_likely_options,
    OptionsMLP,
    save_options,
    viterbi,
)
from torchrl_options.discovery import (
    change_points,
    clone_from_labels,
    CONTINUOUS_PATIENCE,
    converged_at,
    DEFAULT_PATIENCE,
    default_options,
    fit_ddo,
    kmeans,
    pretrain_on_clusters,
    pretrain_on_segments,
    TabulatedDDO,
    unique_rows,
)
from torchrl_options import GaussianOptionsMLP
from torchrl_options.testing import label_accuracy, planted_corridor_demonstrations
from torchrl_options.testing.planted_suite import planted_gaussian_demonstrations


def _posterior(options, data, meta=None):
    with torch.no_grad():
        p = DDOLoss(options, meta).log_probabilities(data)
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
        vit = viterbi(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
    return fb, vit


@pytest.mark.parametrize("init", ["random", "kmeans", "segments"])
def test_planted_two_option_hierarchy_is_recovered(init):
    """The most likely option matches the planted one on at least 90% of steps (up to relabelling)."""
    data = planted_corridor_demonstrations(32, 100, seed=0)
    truth = data["true_option"]
    action_only = label_accuracy(1 - data["action"], truth)  # what a memoryless per-step labelling gets
    options = discover_options(data, 2, num_cells=8, num_iterations=150, lr=0.05, seed=0, init=init, progress=False)
    fb, vit = _posterior(options, data)
    posterior_acc = label_accuracy(most_likely_options(fb.u), truth)
    viterbi_acc = label_accuracy(vit.options, truth)
    assert posterior_acc >= 0.9, posterior_acc
    assert viterbi_acc >= 0.9, viterbi_acc
    assert posterior_acc > action_only + 0.08, (posterior_acc, action_only)


def test_learned_meta_control_trains_and_returns_info():
    data = planted_corridor_demonstrations(8, 40, seed=1)
    result = discover_options(
        data, 2, meta_control="learned", num_cells=4, num_iterations=30, seed=0, progress=False, return_info=True
    )
    assert isinstance(result.meta_control, MetaControlMLP)
    assert len(result.history) == 30
    assert result.history[-1]["loss_ddo"] < result.history[0]["loss_ddo"]
    assert result.final_log_likelihood_per_step == result.history[-1]["log_likelihood_per_step"]


def test_log_likelihood_is_the_returned_modules_own():
    """``result.log_likelihood_per_step`` is the returned modules' exact likelihood (DDOLoss on the same data), which
    with the stopping rule is the best recorded iteration's (the modules are restored there), whatever the last
    record says (``final_log_likelihood_per_step``, the training curve's end)."""
    data = planted_corridor_demonstrations(8, 40, seed=1)
    for meta_control in ("uniform", "learned"):
        result = discover_options(data, 2, meta_control=meta_control, num_cells=4, num_iterations=60, lr=0.2, seed=0,
                                  progress=False, return_info=True)  # fmt: skip
        with torch.no_grad():
            exact = float(DDOLoss(result.options, result.meta_control)(data)["log_likelihood_per_step"])
        assert result.log_likelihood_per_step == pytest.approx(exact, abs=1e-5)
        best = max(h["log_likelihood_per_step"] for h in result.history)
        assert result.log_likelihood_per_step == pytest.approx(best, abs=1e-4)
        assert result.final_log_likelihood_per_step <= result.log_likelihood_per_step + 1e-4


def test_seeded_runs_are_reproducible():
    data = planted_corridor_demonstrations(8, 30, seed=2)
    kw = dict(num_cells=4, num_iterations=10, batch_size=4, seed=3, progress=False)
    a = discover_options(data, 2, **kw)
    b = discover_options(data, 2, **kw)
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.equal(p, q)


def test_user_optimizer_is_honoured():
    data = planted_corridor_demonstrations(4, 20, seed=0)
    torch.manual_seed(0)
    options = OptionsMLP(2, 2, 2)
    before = [p.detach().clone() for p in options.parameters()]
    frozen = torch.optim.SGD(options.parameters(), lr=0.0)
    discover_options(data, 2, options=options, optimizer=frozen, num_iterations=5, progress=False)
    assert all(torch.equal(p, q) for p, q in zip(before, options.parameters()))
    seen = {}

    def factory(params, lr):
        seen["lr"] = lr
        return torch.optim.SGD(params, lr=lr)

    discover_options(data, 2, options=options, optimizer=factory, lr=0.123, num_iterations=2, progress=False)
    assert seen["lr"] == 0.123
    assert not all(torch.equal(p, q) for p, q in zip(before, options.parameters()))


def test_list_of_variable_length_trajectories():
    data = planted_corridor_demonstrations(3, 25, seed=0)
    trajs = [data[0, :25], data[1, :10], data[2, :17]]
    batch = as_trajectory_batch(trajs)
    assert batch["collector", "mask"].sum(1).tolist() == [25, 10, 17]
    options = discover_options(trajs, 2, num_iterations=3, progress=False)
    assert options.num_actions == 2


def test_replay_buffer_input():
    from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer

    data = planted_corridor_demonstrations(6, 30, seed=0)
    flat = data.exclude(("collector", "mask")).reshape(-1)
    flat.set(("collector", "traj_ids"), torch.arange(6).repeat_interleave(30))
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(200), sampler=SliceSampler(slice_len=10, traj_key=("collector", "traj_ids")), batch_size=40
    )
    rb.extend(flat)
    result = discover_options(rb, 2, num_actions=2, num_iterations=5, progress=False, return_info=True)
    assert len(result.history) == 5


def test_kmeans_separates_clusters():
    g = torch.Generator().manual_seed(0)
    x = torch.cat([torch.randn(50, 3, generator=g), torch.randn(50, 3, generator=g) + 8])
    labels, centroids = kmeans(x, 2, generator=g)
    assert label_accuracy(labels, torch.arange(100) // 50) == 1.0
    with pytest.raises(ValueError, match="k"):
        kmeans(x, 0)


def _near(cuts, truth, slack=1):
    """Share of ``cuts`` within ``slack`` steps of a ``truth`` step (both ``[B, T]`` bool)."""
    near = torch.zeros_like(truth)
    for d in range(-slack, slack + 1):
        near |= torch.roll(truth, d, 1)
    return float((cuts & near).sum() / cuts.sum().clamp_min(1))


def test_change_points_find_the_planted_switches():
    """On planted landmark walks the cuts land next to the true switches (precision and recall), and nowhere on padding."""
    from torchrl_options.testing import PLANTED_SUITE

    problem = next(p for p in PLANTED_SUITE if p.name == "landmarks-8")
    data, _ = problem.make(0)
    data = data[:64]
    mask = data["collector", "mask"]
    truth = data["true_switch"] & mask
    truth[:, 0] = False
    cuts = change_points(data["action"], mask)
    assert not (cuts & ~mask).any() and cuts[:, 0].all()
    inner = cuts.clone()
    inner[:, 0] = False
    precision, recall = _near(inner, truth), _near(truth, inner)
    assert precision > 0.6 and recall > 0.6, (precision, recall)
    # a stricter threshold cuts less often and more precisely
    strict = change_points(data["action"], mask, threshold=0.7)
    strict[:, 0] = False
    assert strict.sum() < inner.sum() and _near(strict, truth) > precision


def test_change_points_continuous_actions():
    g = torch.Generator().manual_seed(0)
    action = torch.cat([torch.randn(2, 20, 2, generator=g) * 0.1 - 1, torch.randn(2, 20, 2, generator=g) * 0.1 + 1], 1)
    mask = torch.ones(2, 40, dtype=torch.bool)
    mask[1, 30:] = False
    cuts = change_points(action, mask)
    assert cuts[:, 0].all() and cuts[:, 20].all() and int(cuts.sum()) == 4
    assert not cuts[1, 30:].any()


def test_segment_clusters_see_options_that_steps_cannot():
    """Segments clustered by where they end label landmark walks far better than k-means over state-action pairs."""
    from torchrl_options.testing import best_matching_accuracy, PLANTED_SUITE

    problem = next(p for p in PLANTED_SUITE if p.name == "landmarks-8")
    data, _ = problem.make(1)
    data = data[:128]
    mask = data["collector", "mask"]
    kwargs = dict(num_options=8, num_actions=4, action_space="categorical", num_steps=1)
    torch.manual_seed(0)
    by_segments = pretrain_on_segments(OptionsMLP(2, 4, 8), data, mask, generator=torch.Generator().manual_seed(0), **kwargs)
    by_steps = torch.zeros_like(by_segments)
    by_steps[mask] = pretrain_on_clusters(OptionsMLP(2, 4, 8), data, mask, generator=torch.Generator().manual_seed(0), **kwargs)
    acc_segments = best_matching_accuracy(by_segments, data["true_option"], mask)
    acc_steps = best_matching_accuracy(by_steps, data["true_option"], mask)
    assert acc_segments > 0.55 and acc_segments > acc_steps + 0.15, (acc_segments, acc_steps)


@pytest.mark.parametrize("seed", [2, 3])
def test_segments_clustered_by_actions_see_direction_walks(seed):
    """Walks that end anywhere (geometric termination) are told apart by how they move, not by where they end."""
    from torchrl_options.testing import best_matching_accuracy, PLANTED_SUITE

    problem = next(p for p in PLANTED_SUITE if p.name == "geometric-4")
    data, _ = problem.make(seed)
    mask = data["collector", "mask"]
    acc = {}
    for features in ("end", "actions"):
        labels = pretrain_on_segments(
            OptionsMLP(data["observation"].shape[-1], 4, 4), data, mask, num_options=4, num_actions=4, num_steps=1,
            features=features, generator=torch.Generator().manual_seed(0),
        )  # fmt: skip
        acc[features] = best_matching_accuracy(labels, data["true_option"], mask)
    assert acc["actions"] > 0.7 and acc["actions"] > acc["end"] + 0.2, acc
    with pytest.raises(ValueError, match="features"):
        pretrain_on_segments(OptionsMLP(2, 4, 4), data, mask, num_options=4, features="middle")


def test_auto_init_mixes_segment_starts_and_leaves_given_options_alone():
    """init='auto' (the default) draws AUTO_RESTARTS segment starts for fresh modules, none for given options."""
    from torchrl_options.discovery import AUTO_RESTARTS

    data = planted_corridor_demonstrations(8, 60, seed=0)
    result = discover_options(data, 2, num_iterations=AUTO_RESTARTS * 5, restart_iterations=5, seed=0, progress=False,
                              return_info=True)  # fmt: skip
    assert len(result.restart_log_likelihoods) == AUTO_RESTARTS
    given = OptionsMLP(data["observation"].shape[-1], 2, 2)
    before = [p.detach().clone() for p in given.parameters()]
    after = discover_options(data, 2, options=given, num_iterations=1, m_steps=1, lr=1e-9, seed=0, progress=False)
    # one optimizer step at a negligible learning rate: the given weights were not re-initialised by a pre-training
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(after.parameters(), before))


def test_segment_start_clones_terminations():
    """After the segment pre-training alone, each option terminates where its segments end far more than elsewhere."""
    data = planted_corridor_demonstrations(32, 100, seed=0)
    mask = data["collector", "mask"]
    options = OptionsMLP(data["observation"].shape[-1], 2, 2)
    torch.manual_seed(0)
    labels = pretrain_on_segments(options, data, mask, num_options=2, generator=torch.Generator().manual_seed(0))
    assert label_accuracy(labels[mask], data["true_option"][mask]) > 0.65
    with torch.no_grad():
        psi = torch.sigmoid(options(data["next"].select("observation"))["termination_logits"])
    own = psi.gather(-1, labels[..., None]).squeeze(-1)
    switch_next = torch.zeros_like(mask)
    switch_next[:, :-1] = data["true_switch"][:, 1:] & mask[:, 1:]
    cont_next = mask.clone()
    cont_next[:, :-1] &= mask[:, 1:] & ~data["true_switch"][:, 1:]
    cont_next[:, -1] = False
    assert own[switch_next].mean() > 3 * own[cont_next].mean(), (own[switch_next].mean(), own[cont_next].mean())


def test_change_points_bad_arguments():
    action, mask = torch.zeros(1, 5, dtype=torch.long), torch.ones(1, 5, dtype=torch.bool)
    for window, error in ((0, ValueError), (-2, ValueError), (1.5, TypeError), (True, TypeError)):
        with pytest.raises(error, match="window"):
            change_points(action, mask, window=window)
    for threshold, error in ((0.0, ValueError), (1.0, ValueError), (-1, ValueError), (float("nan"), ValueError),
                             ("0.5", TypeError)):  # fmt: skip
        with pytest.raises(error, match="threshold"):
            change_points(action, mask, threshold=threshold)
    for num_actions, error in ((0, ValueError), (1.5, TypeError)):  # actions 0..1 need num_actions >= 2
        with pytest.raises(error, match="num_actions"):
            change_points(torch.tensor([[0, 1, 1, 0, 1]]), mask, num_actions=num_actions)
    with pytest.raises(ValueError, match="mask"):
        change_points(action, torch.ones(2, 5, dtype=torch.bool))


def test_segment_start_bad_arguments():
    data = planted_corridor_demonstrations(4, 20, seed=0)
    mask = data["collector", "mask"]
    options = OptionsMLP(data["observation"].shape[-1], 2, 2)
    for name, value, error in (("num_options", 0, ValueError), ("num_options", 1.0, TypeError),
                               ("num_steps", 0, ValueError), ("num_steps", -1, ValueError), ("lr", 0.0, ValueError),
                               ("lr", float("nan"), ValueError), ("lr", "0.1", ValueError)):  # fmt: skip
        kwargs = dict(num_options=2, num_steps=5, generator=torch.Generator().manual_seed(0))
        kwargs[name] = value
        with pytest.raises(error, match=name):
            pretrain_on_segments(options, data, mask, **kwargs)


def test_bad_arguments():
    data = planted_corridor_demonstrations(2, 5)
    with pytest.raises(ValueError, match="num_options"):
        discover_options(data, 0, progress=False)
    with pytest.raises(ValueError, match="init"):
        discover_options(data, 2, init="spectral", num_iterations=1, progress=False)
    with pytest.raises(ValueError, match="meta_control"):
        discover_options(data, 2, meta_control="deep", num_iterations=1, progress=False)
    with pytest.raises(ValueError, match="empty"):
        discover_options([], 2, progress=False)
    with pytest.raises(ValueError, match="no .pixels. entry \\(obs_keys\\)"):
        discover_options(data, 2, obs_keys="pixels", progress=False)


def test_save_and_load_round_trip(tmp_path):
    torch.manual_seed(0)
    options = OptionsMLP(2, 3, 2, num_cells=[4, 4], in_keys=[("obs", "pos")], architecture="shared")
    meta = MetaControlMLP(2, 2, in_keys=[("obs", "pos")])
    path = tmp_path / "options.pt"
    save_options(options, path, meta_control=meta, metadata={"K": 2, "note": "test"})
    loaded, loaded_meta, metadata = load_options(path, with_meta_control=True)
    td = TensorDict({"obs": {"pos": torch.randn(5, 2)}}, [5])
    torch.testing.assert_close(options(td.clone())["option_logits"], loaded(td.clone())["option_logits"])
    torch.testing.assert_close(meta(td.clone())["meta_logits"], loaded_meta(td.clone())["meta_logits"])
    assert loaded.in_keys == [("obs", "pos")] and metadata == {"K": 2, "note": "test"}
    assert load_options(path).config == options.config


def test_save_rejects_hand_written_modules_and_load_rejects_foreign_files(tmp_path):
    module = TensorDictModule(torch.nn.Linear(2, 2), in_keys=["observation"], out_keys=["option_logits"])
    with pytest.raises(ValueError, match="cannot save"):
        save_options(module, tmp_path / "x.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not an options file"):
        load_options(tmp_path / "foreign.pt")


def _corridor_accuracy(options, data):
    fb, _ = _posterior(options, data)
    return label_accuracy(most_likely_options(fb.u), data["true_option"])


def test_tol_stops_early_and_still_recovers_the_planted_options():
    data = planted_corridor_demonstrations(32, 100, seed=0)
    kw = dict(num_cells=8, lr=0.05, seed=0, progress=False, return_info=True)
    result = discover_options(data, 2, num_iterations=1000, m_steps=5, tol=1e-3, patience=10, restarts=1, **kw)
    assert result.converged and len(result.history) < 300, len(result.history)
    assert _corridor_accuracy(result.options, data) >= 0.9
    ll = [h["log_likelihood_per_step"] for h in result.history]
    assert converged_at(ll, 1e-3, 10) == len(ll) - 1
    # without tol: every iteration runs and converged is None
    plain = discover_options(data, 2, num_iterations=7, tol=None, **kw)
    assert len(plain.history) == 7 and plain.converged is None


def test_m_steps_recovers_the_planted_options_in_fewer_e_steps():
    data = planted_corridor_demonstrations(32, 100, seed=0)
    kw = dict(num_cells=8, lr=0.05, seed=0, progress=False, return_info=True)
    em = discover_options(data, 2, num_iterations=30, m_steps=10, **kw)
    eg = discover_options(data, 2, num_iterations=30, m_steps=1, **kw)
    assert _corridor_accuracy(em.options, data) >= 0.9
    assert em.final_log_likelihood_per_step > eg.final_log_likelihood_per_step
    # m_steps=1 is the plain Expectation-Gradient: the first step is the gradient of DDOLoss
    assert eg.history[0]["loss_ddo"] == pytest.approx(em.history[0]["loss_ddo"])


@pytest.mark.parametrize("meta", [False, True])
def test_tabulated_e_step_matches_ddo_loss(meta):
    """Diagnostics and gradient of the tabulated E-step / G-step objective equal DDOLoss's, with padding, a terminal
    flag and a learned meta-control, for a batch and for a minibatch of its rows."""
    data = planted_corridor_demonstrations(6, 40, seed=1)
    data["collector", "mask"][2, 30:] = False
    data["next", "terminated"] = torch.zeros(6, 40, 1, dtype=torch.bool)
    data["next", "terminated"][0, -1] = True
    torch.manual_seed(0)
    loss = DDOLoss(OptionsMLP(2, 2, 3, num_cells=4), MetaControlMLP(2, 3, num_cells=4) if meta else None)
    table = TabulatedDDO(loss, data)
    assert (table.num_states, table.num_pairs) == (10, 20)
    rows = torch.tensor([4, 2, 0])
    for tab, batch in ((table, data), (table.subset(rows), data[rows])):
        out = loss(batch)
        out["loss_ddo"].backward()
        expected = [p.grad.clone() for p in loss.parameters()]
        loss.zero_grad()
        record, objective = tab.e_step()
        objective().backward()
        for key in loss.out_keys:
            torch.testing.assert_close(record[key], out[key].detach())
        for p, g in zip(loss.parameters(), expected):
            torch.testing.assert_close(p.grad, g, atol=1e-6, rtol=1e-5)
        loss.zero_grad()


class _BlockedOptions(torch.nn.Module):
    """OptionsMLP whose option 0 cannot take action 1 (logit -inf): zero counts times -inf must contribute nothing."""

    def __init__(self):
        super().__init__()
        self.net = OptionsMLP(2, 3, 2, num_cells=4)

    def forward(self, obs):
        td = self.net(TensorDict({"observation": obs}, obs.shape[:-1]))
        logits = td["option_logits"].clone()
        logits[..., 0, 1] = float("-inf")
        return logits, td["termination_logits"]


def _tabulated_matches_ddo_loss(loss, data):
    out = loss(data)
    out["loss_ddo"].backward()
    expected = [p.grad.clone() for p in loss.parameters()]
    loss.zero_grad()
    record, objective = TabulatedDDO(loss, data).e_step()
    value = objective()
    assert torch.isfinite(value)
    value.backward()
    for key in loss.out_keys:
        torch.testing.assert_close(record[key], out[key].detach())
    for p, g in zip(loss.parameters(), expected):
        assert torch.isfinite(p.grad).all()
        torch.testing.assert_close(p.grad, g, atol=1e-6, rtol=1e-5)


def test_tabulated_e_step_matches_ddo_loss_gaussian_one_hot_and_impossible_actions():
    """The tabulated objective's gradient is DDOLoss's for Gaussian options, one-hot actions, and options that cannot
    take some action (a -inf logit)."""
    from torchrl_options import GaussianOptionsMLP

    torch.manual_seed(0)
    B, T = 3, 25
    obs = torch.randint(4, (B, T + 1, 2)).float()  # few distinct states, so that the tables are small
    base = {"observation": obs[:, :-1], "next": {"observation": obs[:, 1:]}}
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[1, 18:] = False
    base["collector", "mask"] = mask
    action = (obs[:, :-1, 0] > 1).long() * 2  # 0 or 2: option 0's blocked action 1 is never taken
    continuous = TensorDict({**base, "action": obs[:, :-1, :1] * 0.3 + 0.1 * torch.randn(B, T, 1)}, [B, T])
    _tabulated_matches_ddo_loss(DDOLoss(GaussianOptionsMLP(2, 1, 2, num_cells=4)), continuous)
    one_hot = TensorDict({**base, "action": torch.nn.functional.one_hot(action, 3)}, [B, T])
    _tabulated_matches_ddo_loss(DDOLoss(OptionsMLP(2, 3, 2, num_cells=4)), one_hot)
    blocked = TensorDictModule(
        _BlockedOptions(), in_keys=["observation"], out_keys=["option_logits", "termination_logits"]
    )
    _tabulated_matches_ddo_loss(DDOLoss(blocked), TensorDict({**base, "action": action}, [B, T]))


def test_tabulated_objective_reuses_the_e_step_forward_only_at_its_parameters():
    """The first objective() reuses the E-step's forward pass, but not once the parameters have changed."""
    data = planted_corridor_demonstrations(4, 30, seed=0)
    torch.manual_seed(0)
    loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
    table = TabulatedDDO(loss, data)
    (_, first), (_, second) = table.e_step(), table.e_step()  # same parameters: same counts
    at_start = first()
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(0.1)
    moved = second()  # its cached forward pass is from before the change: it must not be used
    assert moved.item() != at_start.item()
    assert moved.item() == first().item()  # first's cache is spent: evaluated anew too


def test_tabulated_e_step_refuses_nan_outputs_naming_the_step():
    data = planted_corridor_demonstrations(3, 20, seed=0)
    loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
    with torch.no_grad():
        loss.options.control.params.get(("2", "bias")).fill_(float("nan"))
    with pytest.raises(ValueError, match=r"log pi .* holds NaN or \+inf at valid step \(b, t\) = \(0, 0\)"):
        TabulatedDDO(loss, data).e_step()


def test_tabulated_e_step_reads_the_loss_mask_keys():
    """TabulatedDDO masks as its loss does: tensor_keys.mask and the loss_mask_key entries (NaN padding ignored)."""
    data = planted_corridor_demonstrations(4, 30, seed=2).exclude(("collector", "mask"))
    valid = torch.ones(4, 30, dtype=torch.bool)
    valid[1, 20:] = False
    data["my", "valid"] = valid
    data["observation"][1, 20:] = float("nan")
    torch.manual_seed(0)
    loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
    loss.loss_mask_key = ("my", "valid")
    record, _ = TabulatedDDO(loss, data).e_step()
    expected = loss(data)
    for key in loss.out_keys:
        torch.testing.assert_close(record[key], expected[key].detach())
    torch.testing.assert_close(TabulatedDDO(loss, data).num_steps, torch.tensor(110))
    with pytest.raises(ValueError, match="reads other entries"):
        TabulatedDDO(loss, data).for_loss(DDOLoss(loss.options))  # another mask key
    loss.loss_mask_key = None
    with pytest.raises(ValueError, match="'observation' holds NaN"):
        TabulatedDDO(loss, data)


def test_unique_rows_is_exact():
    x = torch.tensor([[0.1, 1.0], [0.1, 1.0 + 1e-7], [0.1, 1.0]])
    inverse, first = unique_rows([x, torch.tensor([3, 3, 3], dtype=torch.uint8)])
    assert inverse.tolist()[0] == inverse.tolist()[2] != inverse.tolist()[1] and len(first) == 2


def test_lr_scheduler_is_stepped_once_per_iteration():
    data = planted_corridor_demonstrations(4, 20, seed=0)
    seen = []

    def scheduler(opt):
        seen.append(opt)
        return torch.optim.lr_scheduler.StepLR(opt, step_size=1, gamma=0.5)

    discover_options(data, 2, num_iterations=3, m_steps=2, lr=0.4, lr_scheduler=scheduler, progress=False)
    assert seen[0].param_groups[0]["lr"] == pytest.approx(0.05)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(m_steps=0), "m_steps"),
        (dict(m_steps=1.5), "m_steps"),
        (dict(tol=-1e-3), "tol"),
        (dict(tol="small"), "tol"),
        (dict(tol=1e-3, patience=0), "patience"),
        (dict(num_iterations=-1), "num_iterations"),
        (dict(lr_scheduler="cosine"), "lr_scheduler"),
    ],
)
def test_bad_schedule_arguments_name_the_argument(kwargs, match):
    data = planted_corridor_demonstrations(2, 5)
    with pytest.raises((TypeError, ValueError), match=match):  # TypeError for a wrong type (1.5 steps, "small")
        discover_options(data, 2, progress=False, **kwargs)


def test_fit_ddo_needs_an_e_step_for_several_g_steps():
    data = planted_corridor_demonstrations(2, 5)
    loss = DDOLoss(OptionsMLP(2, 2, 2))
    opt = torch.optim.Adam(loss.parameters())
    with pytest.raises(ValueError, match="m_steps"):
        fit_ddo(loss, opt, lambda it: data, 2, m_steps=3, progress=False)
    with pytest.raises(ValueError, match="patience"):
        converged_at([0.0, 1.0], 1e-3, 0)


def test_restarts_keep_the_best_start_and_continue_training_it(monkeypatch):
    """Restarts: each start gets ``restart_iterations``, the best by log-likelihood is kept and trained to
    ``num_iterations``. The first start is made to look best, so the continuation must train that start's
    networks (not the last start's) and the returned options must be the ones trained."""
    import torchrl_options.discovery.stages as discover_module

    calls = []
    real_fit = discover_module.fit_ddo

    def fit(loss_module, *args, **kwargs):
        records = real_fit(loss_module, *args, **kwargs)
        calls.append((loss_module, [dict(r) for r in records]))
        if len(calls) == 1:  # the first start reports the best final log-likelihood
            records[-1]["log_likelihood_per_step"] = 0.0
        return records

    monkeypatch.setattr(discover_module, "fit_ddo", fit)
    data = planted_corridor_demonstrations(8, 40, seed=4)
    result = discover_options(
        data, 2, num_cells=4, num_iterations=25, restarts=3, restart_iterations=5, lr=0.05, seed=0,
        progress=False, return_info=True,
    )  # fmt: skip
    assert len(calls) == 4  # three starts and the continuation
    assert len(result.restart_log_likelihoods) == 3 and result.restart_log_likelihoods[0] == 0.0
    first_module, first_records = calls[0]
    continuation_module, continuation_records = calls[3]
    assert continuation_module is first_module
    assert result.options is first_module.options
    assert len(result.history) == 25 and len(continuation_records) == 20
    # the continuation starts where the first start stopped and improves it
    with torch.no_grad():
        ll = DDOLoss(result.options)(data)["log_likelihood_per_step"].item()
    assert continuation_records[0]["log_likelihood_per_step"] > first_records[-1]["log_likelihood_per_step"] - 1e-3
    assert ll > first_records[-1]["log_likelihood_per_step"] + 1e-3
    assert ll == pytest.approx(continuation_records[-1]["log_likelihood_per_step"], abs=0.02)


def _complete_data_objective(loss, data, labels, starts):
    """The negative complete-data log-likelihood along ``labels``, read from DDOLoss (policy and termination terms)."""
    mask = data["collector", "mask"]
    p = loss.log_probabilities(data)
    switch_next = torch.zeros_like(mask)
    switch_next[:, :-1] = starts[:, 1:]
    has_next = mask.clone()
    has_next[:, :-1] &= mask[:, 1:]
    has_next[:, -1] = False
    own = labels[..., None]
    policy = (p["log_pi"].gather(-1, own).squeeze(-1) * mask).sum() / mask.sum()
    term = torch.where(switch_next, p["log_term"].gather(-1, own).squeeze(-1), p["log_cont"].gather(-1, own).squeeze(-1))
    return -(policy + (term * has_next).sum() / has_next.sum())


def _small_demonstrations(continuous: bool):
    """A few short planted demonstrations and their action space: Gaussian goal-reaching or the discrete corridor."""
    if continuous:
        return planted_gaussian_demonstrations(6, (8, 15), seed=0)[0], "continuous"
    return planted_corridor_demonstrations(6, 15, seed=0), "categorical"


@pytest.mark.parametrize("continuous", [False, True])
def test_clone_from_labels_minimises_the_complete_data_likelihood(continuous):
    """clone_from_labels takes the Adam steps of the complete-data NLL that DDOLoss's probabilities give."""
    data, space = _small_demonstrations(continuous)
    mask = data["collector", "mask"]
    labels, starts = data["true_option"].clamp_min(0), data["true_switch"]
    torch.manual_seed(0)
    cloned = default_options(data, 2 if not continuous else 3, action_space=space)
    manual = type(cloned)(**{k: v for k, v in cloned.config.items() if k not in ("in_keys", "out_keys")})
    manual.load_state_dict(cloned.state_dict())
    clone_from_labels(cloned, data, mask, labels, starts, action_space=space, num_steps=5)
    loss = DDOLoss(manual, action_space=space)
    opt = torch.optim.Adam(manual.parameters(), lr=0.03)
    for _ in range(5):
        objective = _complete_data_objective(loss, data, labels, starts)
        opt.zero_grad()
        objective.backward()
        opt.step()
    for a, b in zip(cloned.parameters(), manual.parameters()):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    # and the steps went down the objective
    fresh = _complete_data_objective(DDOLoss(cloned, action_space=space), data, labels, starts)
    assert torch.isfinite(fresh)


def test_clone_from_true_labels_recovers_the_planted_options():
    """Cloned from the true labels and switches, the options' posterior labels the steps as the truth does."""
    data = planted_corridor_demonstrations(32, 100, seed=0)
    mask = data["collector", "mask"]
    torch.manual_seed(0)
    options = default_options(data, 2)
    clone_from_labels(options, data, mask, data["true_option"].clamp_min(0), data["true_switch"], num_steps=300)
    fb, _ = _posterior(options, data)
    assert label_accuracy(most_likely_options(fb.u)[mask], data["true_option"][mask]) > 0.9


def test_clone_from_labels_bad_arguments():
    data = planted_corridor_demonstrations(4, 20, seed=0)
    mask = data["collector", "mask"]
    options = OptionsMLP(data["observation"].shape[-1], 2, 2)
    labels, starts = data["true_option"].clamp_min(0), data["true_switch"]
    with pytest.raises(ValueError, match="labels"):
        clone_from_labels(options, data, mask, labels[:, :-1], starts)
    with pytest.raises(ValueError, match="starts"):
        clone_from_labels(options, data, mask, labels, starts[:2])
    with pytest.raises(TypeError, match="labels"):
        clone_from_labels(options, data, mask, labels.float(), starts)
    with pytest.raises(ValueError, match="labels must lie in"):
        clone_from_labels(options, data, mask, labels + 2, starts)
    for name, value in (("num_steps", 0), ("lr", 0.0), ("lr", float("nan"))):
        with pytest.raises(ValueError, match=name):
            clone_from_labels(options, data, mask, labels, starts, **{name: value})


@pytest.mark.parametrize("continuous", [False, True])
def test_default_options_are_the_ones_discover_options_starts_from(continuous):
    """default_options draws the modules discover_options trains when given none (same seed, same weights)."""
    data, space = _small_demonstrations(continuous)
    torch.manual_seed(3)
    built = default_options(data, 3, action_space=space, num_cells=5)
    fitted = discover_options(data, 3, action_space=space, num_cells=5, num_iterations=0, init="random", seed=3,
                              progress=False)  # fmt: skip
    assert type(built) is type(fitted)
    for a, b in zip(built.parameters(), fitted.parameters()):
        torch.testing.assert_close(a, b)
    if continuous:
        assert isinstance(built, GaussianOptionsMLP)
        mask = data["collector", "mask"]
        spread = float(data["action"][mask].std(0).mean())
        scale = built(data.select("observation").clone())["option_scale"]
        torch.testing.assert_close(scale, torch.full_like(scale, spread), atol=1e-5, rtol=1e-4)
    else:
        assert built.config["num_actions"] == int(data["action"].max()) + 1
    with pytest.raises(ValueError, match="action_space"):
        default_options(data, 3, action_space="discrete")
    deep = discover_options(data, 3, action_space=space, num_cells=5, termination_cells=[4, 4], num_iterations=2,
                            init="random", seed=3, progress=False)  # fmt: skip
    assert deep.config["termination_cells"] == [4, 4] and deep.config["num_cells"] == [5]


def test_init_scale_sets_the_gaussian_options_starting_scale():
    """init_scale replaces the action spread as the fresh Gaussian options' start, in default_options and
    discover_options alike; anything but a positive number, or a scale for discrete actions, is refused."""
    data, space = _small_demonstrations(True)
    torch.manual_seed(0)
    built = default_options(data, 3, action_space=space, init_scale=0.25)
    scale = built(data.select("observation").clone())["option_scale"]
    torch.testing.assert_close(scale, torch.full_like(scale, 0.25), atol=1e-5, rtol=1e-4)
    assert built.config["init_scale"] == 0.25 and built.config["min_scale"] < 0.25
    fitted = discover_options(data, 3, action_space=space, init_scale=0.25, num_iterations=0, init="random", seed=0,
                              progress=False)  # fmt: skip
    for a, b in zip(built.parameters(), fitted.parameters()):
        torch.testing.assert_close(a, b)
    for bad in (0.0, -1.0, float("nan"), float("inf"), True, "1.0"):
        with pytest.raises(ValueError, match="init_scale must be a positive finite number"):
            default_options(data, 3, action_space=space, init_scale=bad)
        with pytest.raises(ValueError, match="init_scale must be a positive finite number"):
            discover_options(data, 3, action_space=space, init_scale=bad, progress=False)
    corridor, _ = _small_demonstrations(False)
    with pytest.raises(ValueError, match="init_scale .* action_space='continuous'"):
        discover_options(corridor, 2, init_scale=1.0, progress=False)


@pytest.mark.parametrize("continuous", [False, True])
def test_default_patience_depends_on_the_action_space(continuous):
    """patience=None is DEFAULT_PATIENCE for discrete actions and CONTINUOUS_PATIENCE for Gaussian options: with a
    tol no gain can reach, training stops at the first iteration the window allows."""
    data, space = _small_demonstrations(continuous)
    expected = CONTINUOUS_PATIENCE if continuous else DEFAULT_PATIENCE
    result = discover_options(data, 2, action_space=space, tol=1e9, num_iterations=300, restarts=1, init="random",
                              m_steps=1, seed=0, progress=False, return_info=True)  # fmt: skip
    assert result.converged and len(result.history) == expected + 1
    explicit = discover_options(data, 2, action_space=space, tol=1e9, patience=7, num_iterations=300, restarts=1,
                                init="random", m_steps=1, seed=0, progress=False, return_info=True)  # fmt: skip
    assert len(explicit.history) == 8
    with pytest.raises(ValueError, match="patience must be an int >= 1"):
        discover_options(data, 2, action_space=space, patience=0, progress=False)


def test_fit_ddo_keep_best_restores_the_best_recorded_iteration():
    """keep_best leaves the module at the parameters of the highest recorded log-likelihood; without it, at the
    last step's (a learning rate large enough to make the likelihood go up and down tells the two apart)."""
    data = planted_corridor_demonstrations(8, 30, seed=0)

    def run(keep_best: bool):
        torch.manual_seed(0)
        loss = DDOLoss(OptionsMLP(2, 2, 2, num_cells=4))
        opt = torch.optim.Adam(loss.parameters(), lr=0.8)
        records = fit_ddo(loss, opt, lambda it: data, 40, progress=False, keep_best=keep_best)
        with torch.no_grad():
            final = loss(data)["log_likelihood_per_step"].item()
        return [r["log_likelihood_per_step"] for r in records], final

    lls, final = run(True)
    assert any(b < a for a, b in zip(lls, lls[1:])), "the test needs a likelihood that goes down somewhere"
    assert final == pytest.approx(max(lls), abs=1e-6)
    lls_last, final_last = run(False)
    assert lls_last == lls and final_last != pytest.approx(max(lls), abs=1e-6)


def test_discover_options_with_the_stopping_rule_returns_its_best_iteration():
    data = planted_corridor_demonstrations(8, 30, seed=0)
    result = discover_options(data, 2, restarts=1, init="random", lr=0.5, num_iterations=60, tol=1e-4, seed=0,
                              progress=False, return_info=True)  # fmt: skip
    with torch.no_grad():
        ll = DDOLoss(result.options)(data)["log_likelihood_per_step"].item()
    assert ll == pytest.approx(max(h["log_likelihood_per_step"] for h in result.history), abs=1e-5)
