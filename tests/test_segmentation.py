"""segment(): agreement with the inference functions, the true options of the generators, the design of the
GridWorld benchmark, and recovery of planted boundaries by discovered options on small instances of both
benchmarks."""
import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_options import DDOLoss, discover_options, forward_backward, viterbi
from torchrl_options.envs import load_map, value_iteration
from torchrl_options.segmentation import (
    boundaries_from_options,
    boundary_metrics,
    expected_random_accuracy,
    gridworld_subgoal_demonstrations,
    reach_grasp_demonstrations,
    room_centers,
    segment,
)
from torchrl_options.segmentation.generators import dead_ends, default_subgoals, diamond_map
from torchrl_options.testing import planted_corridor_demonstrations

BIG = 30.0


class TrueReachGraspOptions(TensorDictModuleBase):
    """The generating skills of reach_grasp_demonstrations as Gaussian options (termination logits +-BIG)."""

    def __init__(self, radius=0.05, noise=0.3):
        super().__init__()
        self.in_keys = ["observation"]
        self.out_keys = ["option_loc", "option_scale", "termination_logits"]
        self.radius, self.noise = radius, noise

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        o = td["observation"]
        zero, one = torch.zeros_like(o[..., :1]), torch.ones_like(o[..., :1])
        loc = torch.stack(
            [
                torch.cat([o[..., 2:4], zero], -1),
                torch.cat([zero, zero, one], -1),
                torch.cat([o[..., 5:7], zero], -1),
                torch.cat([zero, zero, -one], -1),
            ],
            -2,
        )
        done = torch.stack([o[..., 4] < self.radius, o[..., 8] >= 1, o[..., 7] < self.radius, o[..., 8] <= 0], -1)
        td["option_loc"] = loc
        td["option_scale"] = torch.full_like(loc, self.noise)
        td["termination_logits"] = torch.where(done, BIG, -BIG)
        return td


class TrueReachGraspMeta(TensorDictModuleBase):
    """The generator's fixed skill order as a meta-control policy: the next skill is a function of the state."""

    def __init__(self, radius=0.05):
        super().__init__()
        self.in_keys = ["observation"]
        self.out_keys = ["meta_logits"]
        self.radius = radius

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        o = td["observation"]
        holding = o[..., 9] > 0.5
        near = torch.where(holding, o[..., 7], o[..., 4]) < self.radius
        nxt = torch.where(holding, torch.where(near, 3, 2), torch.where(near, 1, 0))
        td["meta_logits"] = torch.where(torch.nn.functional.one_hot(nxt, 4).bool(), BIG, -BIG)
        return td


class TrueSubgoalOptions(TensorDictModuleBase):
    """The sub-goal skills of gridworld_subgoal_demonstrations (one-hot observations) as discrete options."""

    def __init__(self, grid="diamond", noise=0.3):
        super().__init__()
        self.in_keys = ["observation"]
        self.out_keys = ["option_logits", "termination_logits"]
        grid = load_map(diamond_map() if grid == "diamond" else grid)
        goals = torch.tensor([int(grid.cell_index[r, c]) for r, c in default_subgoals(grid)])
        _, q = value_iteration(grid, noise)
        q = q[goals].float()
        optimal = q <= q.min(-1, keepdim=True).values + 1e-5 * (1 + q.min(-1, keepdim=True).values.abs())
        self.logits = torch.where(optimal, 0.0, -BIG).transpose(0, 1)  # [F, K, 4]
        self.term = torch.where(torch.arange(grid.num_free)[:, None] == goals[None], BIG, -BIG)  # [F, K]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        cell = td["observation"].argmax(-1)
        td["option_logits"] = self.logits[cell]
        td["termination_logits"] = self.term[cell]
        return td


def test_generators_are_consistent():
    data = reach_grasp_demonstrations(6, seed=1)
    mask = data["collector", "mask"]
    obs, nxt = data["observation"], data["next", "observation"]
    both = mask[:, 1:] & mask[:, :-1]
    assert torch.allclose(nxt[:, :-1][both], obs[:, 1:][both])
    # a skill starts after the previous one's end condition holds; skills run in order
    opt = data["true_option"]
    change = boundaries_from_options(opt, mask)
    assert torch.equal(change, data["true_switch"] & (torch.arange(opt.shape[1]) > 0))
    assert ((opt[:, 1:] - opt[:, :-1])[both] >= 0).all()
    assert data["next", "terminated"].squeeze(-1).sum(1).eq(1).all()

    for name, goals in (("diamond", dead_ends(diamond_map())), ("four-rooms", room_centers("four-rooms"))):
        grid = gridworld_subgoal_demonstrations(4, 120, grid=name, seed=1)
        assert torch.equal(grid["next", "observation"][:, :-1], grid["observation"][:, 1:])
        b, t = grid["true_switch"][:, 1:].nonzero().unbind(-1)
        prev = grid["true_option"][b, t]  # the option that just ended at step t + 1
        assert torch.equal(grid["agent_pos"][b, t + 1], torch.tensor(goals)[prev])
        assert (grid["true_option"][b, t + 1] == (prev + 1) % 4).all()  # a patrol


def test_diamond_benchmark_design():
    grid = diamond_map(4, 3)
    assert grid.shape == (17, 17) and grid.num_rooms == 0
    moves = (grid.next_cell != torch.arange(grid.num_free)[:, None]).sum(1)
    assert torch.bincount(moves).tolist() == [0, 4, 36, 4]  # dead ends, corridor cells, vertices
    assert default_subgoals(grid) == dead_ends(grid) == [(8, 1), (1, 8), (8, 15), (15, 8)]
    with pytest.raises(ValueError, match="radius"):
        diamond_map(1, 3)
    with pytest.raises(ValueError, match="subgoals"):
        gridworld_subgoal_demonstrations(2, 10, subgoals="corners")
    data = gridworld_subgoal_demonstrations(16, 200, seed=0)
    action, switch = data["action"], data["true_switch"]
    # every sub-goal is a dead end: at each true boundary the supervisor turns back (the opposite move)
    b, t = switch[:, 1:].nonzero().unbind(-1)
    assert torch.equal(action[b, t + 1], (action[b, t] + 2) % 4)
    # the skills alternate two moves: the action changes far more often than the skill
    change = action[:, 1:] != action[:, :-1]
    assert change.float().mean() > 5 * switch[:, 1:].float().mean()


@pytest.mark.parametrize("method", ["viterbi", "posterior"])
def test_segment_agrees_with_inference(method):
    data = planted_corridor_demonstrations(6, 30, seed=2)
    data["collector", "mask"][3, 20:] = False  # padding
    options = discover_options(data, 2, num_cells=4, num_iterations=5, seed=0, progress=False)
    seg = segment(data, options, method=method, batch_size=4)  # two chunks
    p = DDOLoss(options).log_probabilities(data)
    args = (p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
    fb, vit = forward_backward(*args), viterbi(*args)
    mask = p["mask"]
    assert torch.allclose(seg.posterior, fb.u * mask[..., None], atol=1e-5)
    assert torch.allclose(seg.log_likelihood, fb.log_likelihood, atol=1e-4)
    assert seg.lengths.tolist() == [30, 30, 30, 20, 30, 30]
    if method == "viterbi":
        assert torch.equal(seg.options, vit.options)
    else:
        assert torch.equal(seg.options, torch.where(mask, fb.u.argmax(-1), -1))
    assert not seg.boundary_mask[:, 0].any() and not seg.boundary_mask[3, 20:].any()
    assert torch.allclose(seg.switch_probability[:, 0], torch.ones(6))
    segs = seg.segments(3)
    assert segs[0][0] == 0 and segs[-1][1] == 20
    assert all(a < b for a, b, _ in segs)

    sw = segment(data, options, method=method, boundary="switch")
    if method == "viterbi":
        expected = vit.switches.clone()
    else:
        expected = (fb.v.sum(-1) > 0.5) & mask
    expected[:, 0] = False
    assert torch.equal(sw.boundary_mask, expected)
    # every label change is a switch
    assert not (seg.boundary_mask & ~sw.boundary_mask).any() or method == "posterior"


def test_segment_arguments():
    data = planted_corridor_demonstrations(2, 10)
    options = discover_options(data, 2, num_iterations=1, progress=False)
    with pytest.raises(ValueError, match="method"):
        segment(data, options, method="argmax")
    with pytest.raises(ValueError, match="boundary"):
        segment(data, options, boundary="edges")
    out = segment(list(data.unbind(0)), options).to_dict()
    assert set(out) == {"options", "boundaries", "posterior", "switch_probability", "log_likelihood", "lengths"}


def test_true_options_recover_continuous_boundaries_exactly():
    data = reach_grasp_demonstrations(8, seed=4)
    seg = segment(data, TrueReachGraspOptions(), TrueReachGraspMeta())
    mask = data["collector", "mask"]
    m = boundary_metrics(seg.boundary_mask, data["true_switch"], 0, lengths=mask)
    assert m["accuracy"] == 1.0 and m["recall"] == 1.0
    assert torch.equal(seg.options, data["true_option"])


@pytest.mark.parametrize("grid", ["diamond", "four-rooms"])
def test_true_options_recover_gridworld_boundaries_exactly(grid):
    data = gridworld_subgoal_demonstrations(4, 150, grid=grid, seed=4)
    seg = segment(data, TrueSubgoalOptions(grid))
    m = boundary_metrics(seg.boundary_mask, data["true_switch"], 0, lengths=[150] * 4)
    assert m["accuracy"] == 1.0 and m["recall"] == 1.0


@pytest.mark.slow
def test_discovered_options_segment_continuous_demonstrations():
    # the benchmark's setting (benchmarks/bench_segmentation.py), about a minute on one core
    data = reach_grasp_demonstrations(32, seed=0)
    result = discover_options(
        data, 4, action_space="continuous", meta_control="learned", num_cells=16, num_iterations=300, lr=0.01,
        seed=0, progress=False, return_info=True,
    )
    seg = segment(data, result)
    lengths = data["collector", "mask"].sum(1)
    m = boundary_metrics(seg.boundary_mask, data["true_switch"], 2, lengths=lengths)
    assert m["accuracy"] >= 0.9 and m["recall"] >= 0.9, m
    assert expected_random_accuracy(data["true_switch"], lengths, 2) < 0.2


def test_discovered_options_segment_gridworld_demonstrations():
    # a small instance of the benchmark (benchmarks/bench_segmentation.py: 32 x 200 steps, 300 iterations, where
    # the accuracy is about 0.95); 5-10 s on one core
    N, T = 16, 150
    data = gridworld_subgoal_demonstrations(N, T, seed=1)
    options = discover_options(  # the settings this test was calibrated with (plain Expectation-Gradient)
        data, 8, num_cells=16, num_iterations=100, lr=0.03, m_steps=1, tol=None, seed=1, progress=False, init="random"
    )
    seg = segment(data, options)
    m = boundary_metrics(seg.boundary_mask, data["true_switch"], 1, lengths=[T] * N)
    random_accuracy = expected_random_accuracy(data["true_switch"], [T] * N, 1)  # whatever the rate
    assert random_accuracy < 0.2, random_accuracy
    assert m["accuracy"] >= 0.85 and m["recall"] >= 0.95, m
    # the defaults (segment starts, run to the stopping rule) segment at least as well: 0.974 when this was written
    seg = segment(data, discover_options(data, 8, seed=1, progress=False))
    m = boundary_metrics(seg.boundary_mask, data["true_switch"], 1, lengths=[T] * N)
    assert m["accuracy"] >= 0.9 and m["recall"] >= 0.95, m
