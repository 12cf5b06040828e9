"""Exact inference over a hierarchy of options, checked against brute-force enumeration of call-stack histories."""
import math
from collections import defaultdict

import pytest
import torch

from torchrl_options import forward_backward
from torchrl_options.hierarchy import hierarchical_forward_backward, stack_shapes


def _inputs(B, T, A, sizes, seed=0, dtype=torch.float64, requires_grad=False):
    g = torch.Generator().manual_seed(seed)
    log_pi, log_term, log_cont = [], [], []
    n = A
    for K in sizes:
        log_pi.append(torch.randn(B, T, K, n, generator=g, dtype=dtype).log_softmax(-1))
        x = 1.5 * torch.randn(B, T, K, generator=g, dtype=dtype)
        log_term.append(torch.nn.functional.logsigmoid(x))
        log_cont.append(torch.nn.functional.logsigmoid(-x))
        n += K
    log_eta = torch.randn(B, T, sizes[-1], generator=g, dtype=dtype).log_softmax(-1)
    action = torch.randint(A, (B, T), generator=g)
    if requires_grad:
        for x in (*log_pi, *log_term, *log_cont, log_eta):
            x.requires_grad_(True)
    return action, log_pi, log_term, log_cont, log_eta


def _enumerate(action, log_pi, log_term, log_cont, log_eta, length, terminal):
    """Every call-stack history of one trajectory, by simulating the call-and-return process with branching.

    Written from the generative model, independently of the recursion: yields (log-probability, events, stacks)
    where events are the (kind, level, t, option, [child]) factors used and stacks[t] the call stack that
    chose a_t (a tuple of (level, option) from the top).
    """
    D = len(log_pi)
    A = log_pi[0].shape[-1]
    sizes = [x.shape[1] for x in log_pi]
    offsets = [A + sum(sizes[:i]) for i in range(D)]

    def decode(c):
        for i in range(D):
            if offsets[i] <= c < offsets[i] + sizes[i]:
                return i, c - offsets[i]
        raise AssertionError

    def descend(t, stack, lp, ev):
        j, k = stack[-1]
        for c in range(log_pi[j].shape[-1]):
            f = float(log_pi[j][t, k, c])
            e = ev + [("pi", j, t, k, c)]
            if c < A:
                if c == int(action[t]):
                    yield stack, lp + f, e
            else:
                i, m = decode(c)
                yield from descend(t, stack + [(i, m)], lp + f, e + [("start", i, t, m)])

    def run(t, stack, lp, ev, stacks):
        if not stack:
            starts = []
            for h in range(sizes[-1]):
                starts.append(([(D - 1, h)], lp + float(log_eta[t, h]), ev + [("eta", D - 1, t, h), ("start", D - 1, t, h)]))
        else:
            starts = [(stack, lp, ev)]
        for st, lp1, ev1 in starts:
            for full, lp2, ev2 in descend(t, st, lp1, ev1):
                stacks2 = stacks + [tuple(full)]
                if t == length - 1:
                    if terminal:
                        lp3 = lp2 + sum(float(log_term[j][t, k]) for j, k in full)
                        yield lp3, ev2 + [("term", j, t, k) for j, k in full], stacks2
                    else:
                        yield lp2, ev2, stacks2
                    continue
                # pop: the bottom option's child (the primitive) returned
                lp3, ev3 = lp2, list(ev2)
                for depth in range(len(full) - 1, -1, -1):
                    j, k = full[depth]
                    yield from run(t + 1, list(full[: depth + 1]), lp3 + float(log_cont[j][t, k]),
                                   ev3 + [("cont", j, t, k)], stacks2)
                    lp3 += float(log_term[j][t, k])
                    ev3 = ev3 + [("term", j, t, k)]
                yield from run(t + 1, [], lp3, ev3, stacks2)

    return list(run(0, [], 0.0, [], []))


def _brute_force(action, log_pi, log_term, log_cont, log_eta, mask, terminal):
    B, T = action.shape
    D = len(log_pi)
    sizes = [x.shape[2] for x in log_pi]
    ll = torch.zeros(B, dtype=torch.float64)
    u = [torch.zeros(B, T, K, dtype=torch.float64) for K in sizes]
    v = [torch.zeros(B, T, K, dtype=torch.float64) for K in sizes]
    emitter = torch.zeros(B, T, D, dtype=torch.float64)
    counts = []
    for b in range(B):
        length = int(mask[b].sum())
        hist = _enumerate(action[b], [x[b].detach() for x in log_pi], [x[b].detach() for x in log_term],
                          [x[b].detach() for x in log_cont], log_eta[b].detach(), length, bool(terminal[b]))
        logps = torch.tensor([h[0] for h in hist], dtype=torch.float64)
        z = logps.logsumexp(0)
        ll[b] = z
        weights = (logps - z).exp()
        c = defaultdict(float)
        for w, (_, events, stacks) in zip(weights.tolist(), hist):
            for e in events:
                c[e] += w
                if e[0] == "start":
                    v[e[1]][b, e[2], e[3]] += w
            for t, st in enumerate(stacks):
                for j, k in st:
                    u[j][b, t, k] += w
                emitter[b, t, st[-1][0]] += w
        counts.append(c)
    return ll, u, v, emitter, counts


CASES = [
    # (A, sizes, T, lengths, terminal)
    (2, [2, 2], 4, [4, 2, 1], [False, True, True]),
    (3, [2, 3], 3, [3, 3], [True, False]),
    (2, [1, 1, 2], 3, [3, 2], [False, True]),
    (2, [2, 1, 1], 3, [3], [True]),
]


@pytest.mark.parametrize("backend", ["dense", "structured", "chunked"])
@pytest.mark.parametrize("A,sizes,T,lengths,terminal", CASES)
def test_likelihood_and_marginals_match_enumeration(A, sizes, T, lengths, terminal, backend):
    B = len(lengths)
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, sizes, seed=len(sizes) + T)
    mask = torch.arange(T)[None] < torch.tensor(lengths)[:, None]
    terminal = torch.tensor(terminal)
    # an impossible choice: level-D options never invoke the first option of the level below at step 1
    log_pi[-1][:, 1, :, A + sum(sizes[:-2])] = -math.inf
    # padding holds garbage: it must be ignored
    for x in (*log_pi, *log_term, *log_cont, log_eta):
        x[~mask] = float("nan")
    action = torch.where(mask, action, 99)
    out = hierarchical_forward_backward(
        action, log_pi, log_term, log_cont, log_eta, mask, terminal, marginals=True, backend=backend
    )
    ll, u, v, emitter, _ = _brute_force(action, log_pi, log_term, log_cont, log_eta, mask, terminal)
    torch.testing.assert_close(out.log_likelihood, ll)
    for j in range(len(sizes)):
        torch.testing.assert_close(out.u[j], u[j])
        torch.testing.assert_close(out.v[j], v[j])
    torch.testing.assert_close(out.emitter, emitter)
    torch.testing.assert_close(out.u[-1].sum(-1), mask.double())
    assert not out.log_likelihood.requires_grad


@pytest.mark.parametrize("backend", ["dense", "structured", "chunked"])
@pytest.mark.parametrize("A,sizes,T,lengths,terminal", CASES[:3])
def test_gradient_is_the_expected_event_count(A, sizes, T, lengths, terminal, backend):
    """Expectation-Gradient: d log P / d (a log-probability) = posterior expected number of times it is used."""
    B = len(lengths)
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, sizes, seed=7, requires_grad=True)
    mask = torch.arange(T)[None] < torch.tensor(lengths)[:, None]
    terminal = torch.tensor(terminal)
    ll = hierarchical_forward_backward(
        action, log_pi, log_term, log_cont, log_eta, mask, terminal, backend=backend
    ).log_likelihood
    grads = torch.autograd.grad(ll.sum(), [*log_pi, *log_term, *log_cont, log_eta])
    _, _, _, _, counts = _brute_force(action, log_pi, log_term, log_cont, log_eta, mask, terminal)
    D = len(sizes)
    g_pi, g_term, g_cont, g_eta = grads[:D], grads[D : 2 * D], grads[2 * D : 3 * D], grads[3 * D]
    e_pi = [torch.zeros_like(x) for x in log_pi]
    e_term = [torch.zeros_like(x) for x in log_term]
    e_cont = [torch.zeros_like(x) for x in log_cont]
    e_eta = torch.zeros_like(log_eta)
    for b, c in enumerate(counts):
        for (kind, j, t, k, *child), w in c.items():
            if kind == "pi":
                e_pi[j][b, t, k, child[0]] += w
            elif kind == "term":
                e_term[j][b, t, k] += w
            elif kind == "cont":
                e_cont[j][b, t, k] += w
            elif kind == "eta":
                e_eta[b, t, k] += w
    for g, e in zip([*g_pi, *g_term, *g_cont, g_eta], [*e_pi, *e_term, *e_cont, e_eta]):
        torch.testing.assert_close(g, e)


def test_one_level_reduces_to_forward_backward():
    B, T, A, K = 3, 9, 4, 3
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, [K], seed=3)
    mask = torch.arange(T)[None] < torch.tensor([9, 5, 1])[:, None]
    terminal = torch.tensor([True, False, True])
    out = hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta, mask, terminal, marginals=True)
    lp = log_pi[0].gather(-1, action[..., None, None].expand(B, T, K, 1)).squeeze(-1)
    fb = forward_backward(lp, log_term[0], log_cont[0], log_eta, mask, terminal)
    torch.testing.assert_close(out.log_likelihood, fb.log_likelihood)
    torch.testing.assert_close(out.u[0], fb.u)
    torch.testing.assert_close(out.v[0], fb.v)


def test_lower_level_that_is_never_used_changes_nothing():
    """Level-2 options that never invoke level-1 options are flat options over the primitive actions."""
    B, T, A = 2, 8, 3
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, [2, 3], seed=4)
    primitive = log_pi[1][..., :A].log_softmax(-1)
    log_pi[1] = torch.cat([primitive, torch.full((B, T, 3, 2), -math.inf, dtype=torch.float64)], -1)
    out = hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta, marginals=True)
    flat = hierarchical_forward_backward(action, [primitive], log_term[1:], log_cont[1:], log_eta, marginals=True)
    torch.testing.assert_close(out.log_likelihood, flat.log_likelihood)
    torch.testing.assert_close(out.u[1], flat.u[0])
    assert out.u[0].abs().max() == 0


def test_long_trajectories_stay_finite_in_float32():
    B, T, A = 2, 3000, 4
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, [3, 2], seed=5, dtype=torch.float32)
    out = hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta, marginals=True)
    assert torch.isfinite(out.log_likelihood).all() and out.log_likelihood.max() < -T * 0.1
    torch.testing.assert_close(out.u[1].sum(-1), torch.ones(B, T))


def test_stack_shapes():
    assert stack_shapes(1) == [(0,)]
    assert stack_shapes(2) == [(1,), (1, 0)]
    assert len(stack_shapes(4)) == 8


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda a, p, t, c, e: (a, [p[0], p[1][..., :-1]], t, c, e), r"log_pi\[1\] \(level 2\) has 4 actions"),
        (lambda a, p, t, c, e: (a, p, t, c[:1], e), "log_cont must be a list of 2"),
        (lambda a, p, t, c, e: (a, p, t, c, e[..., :1]), "log_eta must be"),
        (lambda a, p, t, c, e: (a + 3, p, t, c, e), "outside the primitive actions"),
        (lambda a, p, t, c, e: (a, p, [t[0], t[1][:, :, :1]], c, e), r"log_term\[1\]"),
    ],
)
def test_bad_inputs_name_the_argument(change, match):
    args = change(*_inputs(2, 4, 3, [2, 2]))
    with pytest.raises(ValueError, match=match):
        hierarchical_forward_backward(*args)


def test_bad_mask_and_zero_likelihood():
    action, log_pi, log_term, log_cont, log_eta = _inputs(2, 4, 3, [2, 2])
    with pytest.raises(ValueError, match="prefix"):
        hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta, torch.tensor([[1, 0, 1, 0]] * 2).bool())
    log_pi = [x.clone() for x in log_pi]
    log_pi[0][0, 2, :, action[0, 2]] = -math.inf
    log_pi[1][0, 2, :, action[0, 2]] = -math.inf
    with pytest.raises(ValueError, match=r"trajectories \[0\] have zero likelihood"):
        hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("sizes,T", [([3, 2], 97), ([2, 1, 2], 50), ([2], 130)])
def test_chunked_matches_the_exact_recursion(sizes, T, dtype):
    """The time-parallel product gives the structured recursion's likelihood, marginals and gradients, with
    padding, terminal rows and impossible choices."""
    B, A = 4, 3
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, sizes, seed=11, dtype=dtype, requires_grad=True)
    mask = torch.arange(T)[None] < torch.tensor([T, T - 1, T // 3, 1])[:, None]
    terminal = torch.tensor([True, False, True, True])
    if len(sizes) > 1:
        with torch.no_grad():
            log_pi[-1][:, 5, :, A] = -math.inf
    args = (action, log_pi, log_term, log_cont, log_eta, mask, terminal)
    outs = {b: hierarchical_forward_backward(*args, backend=b, marginals=True) for b in ("structured", "chunked")}
    grads = {
        b: torch.autograd.grad(hierarchical_forward_backward(*args, backend=b).log_likelihood.sum(),
                               [*log_pi, *log_term, *log_cont, log_eta])
        for b in ("structured", "chunked")
    }  # fmt: skip
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(outs["chunked"].log_likelihood, outs["structured"].log_likelihood, **tol)
    for j in range(len(sizes)):
        torch.testing.assert_close(outs["chunked"].u[j], outs["structured"].u[j], **tol)
        torch.testing.assert_close(outs["chunked"].v[j], outs["structured"].v[j], **tol)
    for gc, gs in zip(grads["chunked"], grads["structured"]):
        assert torch.isfinite(gc).all()
        torch.testing.assert_close(gc, gs, **tol)


def test_chunked_recomputes_rows_whose_float64_products_underflow():
    """In trajectory 0, option 0 costs 60 nats per step and entering it 800: over a chunk of 14 steps, the entries
    of the transfer matrix that end in option 0 fall more than 700 nats below the others. The chunked product
    flags that trajectory and the exact recursion redoes it."""
    from torchrl_options.hierarchy.inference import _forward_chunked
    from torchrl_options.inference.semiring import SAFE_LOG

    B, T, A = 2, 200, 2
    action = torch.zeros(B, T, dtype=torch.long)
    log_pi = torch.zeros(B, T, 2, A, dtype=torch.float64)
    log_pi[0, :, 0, 0] = -60.0  # row 0: option 0 explains the actions very badly
    log_term = torch.full((B, T, 2), -5.0, dtype=torch.float64)
    log_cont = torch.log1p(-log_term.exp())
    log_eta = torch.full((B, T, 2), math.log(0.5), dtype=torch.float64)
    log_eta[0, :, 0] = -800.0
    log_pi.requires_grad_()
    mask = torch.ones(B, T, dtype=torch.bool)
    terminal = torch.tensor([False, False])
    raw = _forward_chunked(action, [log_pi], [log_term], [log_cont], log_eta, mask, terminal, A, [2], None, None,
                           SAFE_LOG)  # fmt: skip
    assert torch.isnan(raw[0]) and torch.isfinite(raw[1])
    args = (action, [log_pi], [log_term], [log_cont], log_eta, mask, terminal)
    chunked = hierarchical_forward_backward(*args, backend="chunked").log_likelihood
    exact = hierarchical_forward_backward(*args, backend="structured").log_likelihood
    torch.testing.assert_close(chunked, exact)
    g_c, = torch.autograd.grad(chunked.sum(), log_pi)
    g_s, = torch.autograd.grad(exact.sum(), log_pi)
    torch.testing.assert_close(g_c, g_s)


def test_chunked_stays_finite_and_normalised_on_100000_steps_in_float32():
    B, T, A = 1, 100_000, 3
    action, log_pi, log_term, log_cont, log_eta = _inputs(B, T, A, [2, 2], seed=6, dtype=torch.float32)
    out = hierarchical_forward_backward(action, log_pi, log_term, log_cont, log_eta, marginals=True, backend="chunked")
    assert torch.isfinite(out.log_likelihood).all() and out.log_likelihood.max() < -T * 0.1
    torch.testing.assert_close(out.u[1].sum(-1), torch.ones(B, T))
    # against the exact recursion on a prefix: the same per-step log-likelihood scale
    short = hierarchical_forward_backward(action[:, :2000], *[[x[:, :2000] for x in y] for y in (log_pi, log_term,
                                          log_cont)], log_eta[:, :2000], backend="structured").log_likelihood  # fmt: skip
    assert abs(out.log_likelihood.item() / T - short.item() / 2000) < 0.05


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planted_hierarchy_posterior_recovers_its_own_labels(seed):
    """With the planted hierarchy's own probabilities, the exact posterior over call stacks labels both levels
    (the Bayes-optimal labelling: not 1 at level 2, where patrols share walks)."""
    from torchrl_options.testing import label_accuracy, planted_two_level_demonstrations
    from torchrl_options.testing import planted_two_level_log_probabilities

    data = planted_two_level_demonstrations(32, 60, seed=seed)
    p = planted_two_level_log_probabilities(data)
    post = hierarchical_forward_backward(**p, marginals=True)
    assert label_accuracy(post.most_likely(1), data["true_option_1"]) > 0.99
    assert label_accuracy(post.most_likely(2), data["true_option_2"]) > 0.92
    chunked = hierarchical_forward_backward(**p, backend="chunked").log_likelihood
    torch.testing.assert_close(chunked, post.log_likelihood)
