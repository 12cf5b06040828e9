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
from torchrl_options.discovery import kmeans
from torchrl_options.testing import label_accuracy, planted_corridor_demonstrations


def _posterior(options, data, meta=None):
    with torch.no_grad():
        p = DDOLoss(options, meta).log_probabilities(data)
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
        vit = viterbi(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
    return fb, vit


@pytest.mark.parametrize("init", ["random", "kmeans"])
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
    with pytest.raises(KeyError, match="pixels"):
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
