"""A suite of planted option problems with their Bayes ceilings, to check that discovery finds the truth.

Each problem draws demonstrations from a known set of options (inside DDO's model class: options with a control
policy and a termination condition evaluated at the next state, a uniform meta-control) and knows its own
log-probabilities, so the exact posterior under the truth (:func:`~torchrl_options.forward_backward`) gives the
best labelling of the steps any model can reach on those demonstrations: the *Bayes ceiling*. A discovered model
is judged against it (accuracy of its most likely option per step, up to relabelling) and against the truth's
log-likelihood (a lower likelihood with a lower accuracy is a local optimum, not a limit of the data).

The problems vary what makes discovery hard: the number of options (2 to 8), the termination style (at a goal
state, at walls, geometric durations), options that share actions in many states, variable lengths with padding,
and continuous (Gaussian) actions. Discrete problems live on grids whose observation is the cell's ``(x, y)``
scaled to ``[0, 1]`` (the policies are not linear in it).

Reference: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep Options" (2017), section 4.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tensordict import TensorDict

from torchrl_options.checks import check_int, check_tensor
from torchrl_options.inference import forward_backward
from torchrl_options.testing.planted import check_labels

__all__ = [
    "PlantedProblem",
    "PLANTED_SUITE",
    "best_matching_accuracy",
    "planted_gaussian_demonstrations",
    "planted_tabular_demonstrations",
    "posterior_accuracy",
]

_MOVES = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]])  # left, right, up, down; y grows downwards


def _check_lengths(lengths: tuple[int, int]) -> None:
    if not isinstance(lengths, (tuple, list)) or len(lengths) != 2:
        raise TypeError(f"lengths must be a pair (shortest, longest), got {lengths!r}.")
    check_int(lengths[0], "lengths[0]", minimum=1)
    check_int(lengths[1], "lengths[1]", minimum=lengths[0])


def best_matching_accuracy(predicted: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Fraction of steps where ``predicted`` equals ``truth``, maximised over one-to-one relabellings of ``predicted``.

    Exact, by dynamic programming over subsets of the truth's labels (``O(K^2 2^K)``, instant up to K = 12), so it
    stays cheap where enumerating the ``K!`` permutations would not. Labels without a partner count as wrong.

    Examples:
        >>> import torch
        >>> best_matching_accuracy(torch.tensor([2, 2, 0, 0, 1]), torch.tensor([0, 0, 1, 1, 1]))
        0.8
    """
    mask = check_labels(predicted, truth, mask, "best_matching_accuracy")
    p, t = predicted[mask].long(), truth[mask].long()
    k = int(max(p.max(), t.max())) + 1
    if k > 16:
        raise ValueError(f"best_matching_accuracy supports at most 16 labels, got {k}.")
    confusion = torch.zeros(k, k, dtype=torch.long)
    confusion.index_put_((p, t), torch.ones_like(p), accumulate=True)
    c = confusion.tolist()
    # best[mask of used truth labels] after assigning predicted labels 0..popcount(mask)-1 (or leaving them out)
    best = {0: 0}
    for i in range(k):
        nxt: dict[int, int] = {}
        for used, score in best.items():
            if score > nxt.get(used, -1):
                nxt[used] = score  # predicted label i matched to nothing
            for j in range(k):
                if not used >> j & 1:
                    key, value = used | 1 << j, score + c[i][j]
                    if value > nxt.get(key, -1):
                        nxt[key] = value
        best = nxt
    return max(best.values()) / p.numel()


def posterior_accuracy(log_probs: dict, truth: torch.Tensor) -> tuple[float, float]:
    """Accuracy of the most likely option per step, and log-likelihood per valid step, of a model's E-step inputs.

    Args:
        log_probs (dict): ``log_pi``, ``log_term``, ``log_cont``, ``log_eta`` ``[B, T, K]`` and ``mask`` ``[B, T]``
            (e.g. from :meth:`~torchrl_options.DDOLoss.log_probabilities` or a problem's ``truth``).
        truth (Tensor): ``[B, T]`` the planted option of each step.

    Returns:
        ``(accuracy up to relabelling, log-likelihood per valid step)``.
    """
    if not isinstance(log_probs, dict):
        raise TypeError(f"posterior_accuracy: log_probs must be a dict of tensors, got {type(log_probs).__name__}.")
    missing = [k for k in ("log_pi", "log_term", "log_cont", "log_eta", "mask") if k not in log_probs]
    if missing:
        raise ValueError(f"posterior_accuracy: log_probs lacks {missing} (expected DDOLoss.log_probabilities' entries).")
    mask = log_probs["mask"]
    with torch.no_grad():
        fb = forward_backward(
            log_probs["log_pi"], log_probs["log_term"], log_probs["log_cont"], log_probs["log_eta"], mask,
            log_probs.get("terminal", False),
        )  # fmt: skip
    steps = mask.sum().item()
    return best_matching_accuracy(fb.u.argmax(-1), truth, mask), fb.log_likelihood.sum().item() / steps


def planted_tabular_demonstrations(
    policy: torch.Tensor,
    termination: torch.Tensor,
    next_state: torch.Tensor,
    features: torch.Tensor,
    *,
    num_trajectories: int,
    lengths: tuple[int, int],
    seed: int = 0,
) -> TensorDict:
    """Demonstrations of tabular options on a finite state space, padded to the longest, with the truth recorded.

    A trajectory starts in a uniformly random state with a uniformly random option ``h``. At each step the action
    is drawn from ``policy[h, s]``, the state moves to ``next_state[s, a]``, and the option terminates with
    probability ``termination[h, s']``; a new option (maybe the same) is then drawn uniformly.

    Args:
        policy (Tensor): ``[K, S, A]`` action probabilities of each option in each state.
        termination (Tensor): ``[K, S]`` termination probabilities, evaluated at the state reached.
        next_state (Tensor): ``[S, A]`` long, the deterministic dynamics.
        features (Tensor): ``[S, F]`` the observation of each state.

    Keyword Args:
        num_trajectories (int): B.
        lengths (tuple of int): each trajectory's length is drawn uniformly in ``[lengths[0], lengths[1]]``.
        seed (int): generator seed.

    Returns:
        A ``[B, T_max]`` TensorDict with ``"observation"``, ``"action"``, ``("next", "observation")``,
        ``("collector", "mask")`` (valid steps), ``"state"`` and ``("next", "state")`` (the state indices), and the
        truth ``"true_option"`` and ``"true_switch"``.

    Examples:
        >>> import torch
        >>> policy = torch.tensor([[[0.9, 0.1]] * 3, [[0.1, 0.9]] * 3])
        >>> data = planted_tabular_demonstrations(policy, torch.full((2, 3), 0.1), torch.tensor([[0, 1], [0, 2],
        ...     [1, 2]]), torch.eye(3), num_trajectories=4, lengths=(5, 8))
        >>> data["collector", "mask"].sum(1).min().item() >= 5, data["true_option"].shape[0]
        (True, 4)
    """
    check_int(num_trajectories, "num_trajectories", minimum=1)
    _check_lengths(lengths)
    check_tensor(policy, "policy", ndim=3, dtype="floating", owner="planted_tabular_demonstrations")
    K, S, A = policy.shape
    check_tensor(termination, "termination", shape=(K, S), dtype="floating", owner="planted_tabular_demonstrations")
    check_tensor(next_state, "next_state", shape=(S, A), dtype="integer", owner="planted_tabular_demonstrations")
    check_tensor(features, "features", ndim=2, owner="planted_tabular_demonstrations")
    if features.shape[0] != S:
        raise ValueError(f"planted_tabular_demonstrations: features must have one row per state (S={S}), got {list(features.shape)}.")
    K, S, A = policy.shape
    g = torch.Generator().manual_seed(seed)
    B, T = num_trajectories, lengths[1]
    length = torch.randint(lengths[0], lengths[1] + 1, (B,), generator=g)
    s = torch.randint(S, (B,), generator=g)
    h = torch.randint(K, (B,), generator=g)
    switch = torch.ones(B, dtype=torch.bool)
    states, actions, options, switches = [s], [], [], []
    for _ in range(T):
        a = torch.multinomial(policy[h, s], 1, generator=g).squeeze(1)
        s = next_state[s, a]
        options.append(h)
        switches.append(switch)
        actions.append(a)
        states.append(s)
        switch = torch.rand(B, generator=g) < termination[h, s]
        h = torch.where(switch, torch.randint(K, (B,), generator=g), h)
    state = torch.stack(states, 1)
    mask = torch.arange(T)[None] < length[:, None]
    return TensorDict(
        {
            "observation": features[state[:, :-1]],
            "action": torch.stack(actions, 1),
            "state": state[:, :-1],
            "next": {"observation": features[state[:, 1:]], "state": state[:, 1:]},
            ("collector", "mask"): mask,
            "true_option": torch.stack(options, 1),
            "true_switch": torch.stack(switches, 1),
        },
        batch_size=[B, T],
    )


def tabular_log_probabilities(
    data: TensorDict, policy: torch.Tensor, termination: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The truth's E-step inputs on demonstrations of :func:`planted_tabular_demonstrations` (float64)."""
    K = policy.shape[0]
    s, s_next, a = data["state"], data["next", "state"], data["action"]
    f64 = torch.float64
    log_pi = policy.to(f64).log()[:, s, a].permute(1, 2, 0)
    psi = termination.to(f64)[:, s_next].permute(1, 2, 0)
    return {
        "log_pi": log_pi,
        "log_term": psi.log(),
        "log_cont": (1 - psi).log(),
        "log_eta": torch.full_like(log_pi, -math.log(K)),
        "mask": data["collector", "mask"],
    }


def _grid(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(xy [S, 2] long, next_state [S, 4], features [S, 2])`` of an empty grid (moves into walls stay put)."""
    xy = torch.stack(torch.meshgrid(torch.arange(width), torch.arange(height), indexing="xy"), -1).reshape(-1, 2)
    moved = xy[:, None, :] + _MOVES[None]
    moved[..., 0].clamp_(0, width - 1)
    moved[..., 1].clamp_(0, height - 1)
    next_state = moved[..., 1] * width + moved[..., 0]
    features = xy.float() / torch.tensor([max(width - 1, 1), max(height - 1, 1)])
    return xy, next_state, features


def _with_noise(preferred: torch.Tensor, noise: float) -> torch.Tensor:
    """``[..., A]`` action probabilities: the ``preferred`` distribution, replaced by a uniform one w.p. ``noise``."""
    A = preferred.shape[-1]
    return (1 - noise) * preferred + noise / A


def landmark_options(
    size: int, landmarks: list[tuple[int, int]], *, noise: float, goal_termination: float = 1.0,
    spontaneous_termination: float = 0.02,
) -> dict:  # fmt: skip
    """Options walking to landmarks on an empty ``size x size`` grid.

    Option ``h`` takes, uniformly, one of the moves that bring it closer to its landmark (uniform at the landmark),
    replaced by a random move with probability ``noise``; it terminates on reaching its landmark with probability
    ``goal_termination`` and anywhere else with ``spontaneous_termination``. Options whose landmarks lie in the
    same direction share their moves in the states between: only the temporal structure tells them apart.
    """
    xy, next_state, features = _grid(size, size)
    S, K = xy.shape[0], len(landmarks)
    goal = torch.tensor(landmarks)
    dist = (xy[None] - goal[:, None]).abs().sum(-1)  # [K, S]
    closer = dist[:, next_state] < dist[:, :, None]  # [K, S, A]
    at_goal = dist == 0
    preferred = torch.where(at_goal[..., None], torch.ones_like(closer, dtype=torch.float), closer.float())
    preferred = preferred / preferred.sum(-1, keepdim=True)
    termination = torch.where(at_goal, goal_termination, spontaneous_termination).expand(K, S)
    return dict(policy=_with_noise(preferred, noise), termination=termination, next_state=next_state,
                features=features)  # fmt: skip


def direction_options(size: int, *, noise: float, termination: str | float) -> dict:
    """Four options walking left / right / up / down on an empty ``size x size`` grid.

    ``termination="wall"``: an option terminates when it stands against the wall it walks to (and with
    probability 0.02 elsewhere); a float: it terminates with that probability at every step (geometric durations,
    independent of the state).
    """
    xy, next_state, features = _grid(size, size)
    S = xy.shape[0]
    preferred = torch.eye(4)[:, None, :].expand(4, S, 4)
    if termination == "wall":
        last = size - 1
        walls = torch.stack([xy[:, 0] == 0, xy[:, 0] == last, xy[:, 1] == 0, xy[:, 1] == last])
        psi = torch.where(walls, 1.0, 0.02)
    else:
        psi = torch.full((4, S), float(termination))
    return dict(policy=_with_noise(preferred, noise), termination=psi, next_state=next_state, features=features)


def corridor_options(size: int, *, noise: float, spontaneous_termination: float = 0.02) -> dict:
    """Two options walking right / left in a 1-D corridor (actions: left, right), terminating at its far end."""
    pos = torch.arange(size)
    next_state = torch.stack([(pos - 1).clamp_min(0), (pos + 1).clamp_max(size - 1)], -1)
    features = torch.stack([pos.float() / (size - 1), torch.ones(size)], -1)
    preferred = torch.tensor([[0.0, 1.0], [1.0, 0.0]])[:, None, :].expand(2, size, 2)
    termination = torch.stack([pos == size - 1, pos == 0]).float().clamp_min(spontaneous_termination)
    return dict(policy=_with_noise(preferred, noise), termination=termination, next_state=next_state,
                features=features)  # fmt: skip


def planted_gaussian_demonstrations(
    num_trajectories: int,
    lengths: tuple[int, int],
    *,
    goals: tuple[tuple[float, float], ...] = ((0.15, 0.15), (0.85, 0.2), (0.5, 0.85)),
    gain: float = 0.35,
    scale: float = 0.04,
    radius: float = 0.12,
    spontaneous_termination: float = 0.02,
    seed: int = 0,
) -> tuple[TensorDict, dict]:
    """Continuous options: a point in the unit square moves towards one of several goals with Gaussian steps.

    Option ``h``'s action is ``N(gain * (goal_h - s), scale^2 I)``; the next state is ``clip(s + a, 0, 1)``. It
    terminates with probability 0.95 once within ``radius`` of its goal (at the state reached) and with
    ``spontaneous_termination`` elsewhere; the next option is drawn uniformly.

    Returns:
        ``(data, truth)``: the ``[B, T_max]`` demonstrations (``"observation"`` ``[.., 2]``, float ``"action"``,
        mask, ``"true_option"`` and ``"true_switch"``: an option starts at the step, the same one redrawn included)
        and the truth's E-step inputs (float64).
    """
    check_int(num_trajectories, "num_trajectories", minimum=1)
    _check_lengths(lengths)
    g = torch.Generator().manual_seed(seed)
    goal = torch.tensor(goals)
    K, B, T = goal.shape[0], num_trajectories, lengths[1]
    length = torch.randint(lengths[0], lengths[1] + 1, (B,), generator=g)

    def psi(state):  # [B, 2] -> [B, K]
        near = (state[:, None] - goal[None]).norm(dim=-1) < radius
        return torch.where(near, 0.95, spontaneous_termination)

    s = torch.rand(B, 2, generator=g)
    h = torch.randint(K, (B,), generator=g)
    switch = torch.ones(B, dtype=torch.bool)
    obs, acts, nxt, opts, switches = [], [], [], [], []
    for _ in range(T):
        a = gain * (goal[h] - s) + scale * torch.randn(B, 2, generator=g)
        s_next = (s + a).clamp(0, 1)
        obs.append(s), acts.append(a), nxt.append(s_next), opts.append(h), switches.append(switch)
        stop = torch.rand(B, generator=g) < psi(s_next).gather(1, h[:, None]).squeeze(1)
        h = torch.where(stop, torch.randint(K, (B,), generator=g), h)
        s, switch = s_next, stop
    mask = torch.arange(T)[None] < length[:, None]
    data = TensorDict(
        {
            "observation": torch.stack(obs, 1),
            "action": torch.stack(acts, 1),
            "next": {"observation": torch.stack(nxt, 1)},
            ("collector", "mask"): mask,
            "true_option": torch.stack(opts, 1),
            "true_switch": torch.stack(switches, 1),
        },
        batch_size=[B, T],
    )
    f64 = torch.float64
    o, a = data["observation"].to(f64), data["action"].to(f64)
    mean = gain * (goal.to(f64)[None, None] - o[:, :, None])  # [B, T, K, 2]
    log_pi = (-0.5 * ((a[:, :, None] - mean) / scale) ** 2 - math.log(scale) - 0.5 * math.log(2 * math.pi)).sum(-1)
    p = psi(data["next", "observation"].reshape(-1, 2)).reshape(B, T, K).to(f64)
    truth = {"log_pi": log_pi, "log_term": p.log(), "log_cont": (1 - p).log(),
             "log_eta": torch.full_like(log_pi, -math.log(K)), "mask": mask}  # fmt: skip
    return data, truth


@dataclass
class PlantedProblem:
    """One member of :data:`PLANTED_SUITE`.

    Attributes:
        name (str): a short label.
        num_options (int): K, the planted number of options (discovery is asked for as many).
        action_space (str): ``"categorical"`` or ``"continuous"``.
        description (str): what makes the problem hard.
        make (callable): ``make(seed, num_trajectories=None) -> (data, truth)``: demonstrations with
            ``"true_option"`` and the truth's E-step inputs (``log_pi``, ``log_term``, ``log_cont``, ``log_eta``,
            ``mask``); ``num_trajectories`` defaults to the problem's own data size (used to ask whether labels
            missed at that size are found with more data).
    """

    name: str
    num_options: int
    action_space: str
    description: str
    make: Callable[[int], tuple[TensorDict, dict]] = field(repr=False)

    def ceiling(self, data: TensorDict, truth: dict) -> tuple[float, float]:
        """The Bayes ceiling: ``(accuracy, log-likelihood per step)`` of the truth's own posterior."""
        return posterior_accuracy(truth, data["true_option"])


def _tabular_problem(spec: dict, num_trajectories: int, lengths: tuple[int, int]) -> Callable[..., tuple]:
    default = num_trajectories

    def make(seed: int, num_trajectories: int | None = None):
        data = planted_tabular_demonstrations(
            spec["policy"], spec["termination"], spec["next_state"], spec["features"],
            num_trajectories=default if num_trajectories is None else num_trajectories, lengths=lengths, seed=seed,
        )  # fmt: skip
        return data, tabular_log_probabilities(data, spec["policy"], spec["termination"])

    return make


PLANTED_SUITE: list[PlantedProblem] = [
    PlantedProblem(
        "corridor-2", 2, "categorical",
        "1-D corridor, 2 options (walk right / left), terminate at the far end; 20% opposite moves",
        _tabular_problem(corridor_options(10, noise=0.4), 64, (40, 100)),
    ),
    PlantedProblem(
        "landmarks-3", 3, "categorical",
        "7x7 grid, 3 options walking to 3 landmarks, 15% random moves, terminate at the landmark (2% elsewhere)",
        _tabular_problem(landmark_options(7, [(0, 0), (6, 1), (2, 6)], noise=0.15), 256, (40, 100)),
    ),
    PlantedProblem(
        "walls-4", 4, "categorical",
        "5x5 grid, 4 options walking left / right / up / down, 10% random moves, terminate at their wall",
        _tabular_problem(direction_options(5, noise=0.1, termination="wall"), 64, (40, 100)),
    ),
    PlantedProblem(
        "geometric-4", 4, "categorical",
        "5x5 grid, the same 4 walks with state-independent termination (geometric durations, mean 8 steps)",
        _tabular_problem(direction_options(5, noise=0.1, termination=0.125), 64, (40, 100)),
    ),
    PlantedProblem(
        "landmarks-8", 8, "categorical",
        "9x9 grid, 8 options walking to the corners and edge midpoints (many share moves), 10% random moves",
        _tabular_problem(
            landmark_options(9, [(0, 0), (4, 0), (8, 0), (8, 4), (8, 8), (4, 8), (0, 8), (0, 4)], noise=0.1),
            256, (40, 100),
        ),
    ),
    PlantedProblem(
        "gaussian-3", 3, "continuous",
        "continuous 2-D point, 3 Gaussian options steering to 3 goals, terminate near the goal",
        lambda seed, num_trajectories=None: planted_gaussian_demonstrations(
            128 if num_trajectories is None else num_trajectories, (40, 100), seed=seed
        ),
    ),
]
"""The one-level problems of the planted suite (``benchmarks/bench_planted_suite.py``). The two-level problem is
:func:`~torchrl_options.testing.planted_two_level_demonstrations` with its own ceiling helper."""
