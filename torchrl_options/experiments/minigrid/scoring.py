"""Scores of a segmentation against the BabyAI bot's subgoals, the trivial baselines on the same data, and what the
options learned instead.

For a labelling of the demonstrations' steps (the options of :func:`~torchrl_options.segment`, say) and a reference
granularity (the bot's subgoals, ``"true_option"`` / ``"true_switch"``, or its coarser skills, ``"skill"`` /
``"skill_switch"``; :mod:`~torchrl_options.experiments.minigrid.demonstrations`), :func:`segmentation_scores`
gives:

- ``label_accuracy``: the share of steps whose option matches the reference label under the best one-to-one
  relabelling (:func:`~torchrl_options.testing.best_matching_accuracy`);
- ``precision_w<w>``, ``recall_w<w>``, ``f1_w<w>`` for each window ``w``: boundaries matched one-to-one within
  ``w`` steps (:func:`~torchrl_options.segmentation.boundary_metrics`; the start of a trajectory is not a
  boundary);
- ``boundary_rate`` (predicted boundaries per candidate step) and ``reference_rate``.

:func:`baseline_scores` scores three labellings that need no learning on the same data: ``action_change`` (a
boundary at every change of action; the action itself as the label), ``random`` (boundaries drawn independently at
the reference's own rate, averaged over draws; no labels) and ``one_option`` (one label everywhere: no boundary,
the majority label's share as accuracy). :func:`option_composition` says what each option holds: its share of the
steps and the reference labels it covers, and which reference labels share one option (merged).
:func:`option_information` says what the options track instead, when they are not the skills: the share of the
entropy of the skill, the action, the turn's side, the heading and the carried object that the option explains.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

__all__ = ["GRANULARITIES", "INFORMATION_TARGETS", "baseline_scores", "option_composition", "option_information",
           "segmentation_scores"]

_MASK = ("collector", "mask")

#: The reference granularities: name -> (label key, boundary key) of the demonstrations.
GRANULARITIES = {"subgoal": ("true_option", "true_switch"), "skill": ("skill", "skill_switch")}


def _check(data: TensorDictBase, label_key: str, switch_key: str) -> torch.Tensor:
    keys = data.keys(include_nested=True)
    for key in (label_key, switch_key, _MASK, "action"):
        if key not in keys:
            raise KeyError(f"the demonstrations have no {key!r} entry (needed to score a segmentation).")
    return data.get(_MASK).bool()


def _boundary_scores(predicted: torch.Tensor, data: TensorDictBase, switch_key: str, windows: Sequence[int]) -> dict:
    from torchrl_options.segmentation import boundary_metrics

    mask = data.get(_MASK).bool()
    reference = data.get(switch_key).bool() & mask
    out: dict[str, float] = {}
    for w in windows:
        m = boundary_metrics(predicted & mask, reference, int(w), lengths=mask)
        out[f"precision_w{w}"] = m["precision"]
        out[f"recall_w{w}"] = m["recall"]
        out[f"f1_w{w}"] = m["f1"]
        out["boundary_rate"] = m["rate"]
        out["reference_rate"] = m["num_reference"] / max(int(mask.sum()) - mask.shape[0], 1)
    return out


def _changes(labels: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    change = torch.zeros_like(mask)
    change[:, 1:] = labels[:, 1:] != labels[:, :-1]
    return change & mask


def segmentation_scores(
    predicted: torch.Tensor,
    data: TensorDictBase,
    *,
    label_key: str = "true_option",
    switch_key: str = "true_switch",
    boundaries: torch.Tensor | None = None,
    windows: Sequence[int] = (1, 2),
) -> dict[str, float]:
    """Label accuracy (best matching), boundary precision / recall / F1 within each window, and boundary rates.

    Args:
        predicted (Tensor): ``[B, T]`` integer labels (an option per step); padding is ignored.
        data (TensorDictBase): the demonstrations, with ``label_key``, ``switch_key`` and ``("collector", "mask")``.

    Keyword Args:
        label_key, switch_key (str): the reference labels and boundaries (see :data:`GRANULARITIES`).
        boundaries (Tensor, optional): ``[B, T]`` predicted boundaries; defaults to where ``predicted`` changes.
        windows (sequence of int): the tolerances, in steps. Defaults to ``(1, 2)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"true_option": torch.tensor([[0, 0, 1, 1, 2, 2]]), "action": torch.zeros(1, 6),
        ...                    "true_switch": torch.tensor([[1, 0, 1, 0, 1, 0]]).bool(),
        ...                    ("collector", "mask"): torch.ones(1, 6, dtype=torch.bool)}, [1, 6])
        >>> s = segmentation_scores(torch.tensor([[5, 5, 5, 3, 3, 3]]), data)
        >>> round(s["label_accuracy"], 3), round(s["f1_w1"], 3), s["boundary_rate"]
        (0.667, 0.667, 0.2)
    """
    from torchrl_options.testing import best_matching_accuracy

    mask = _check(data, label_key, switch_key)
    predicted = torch.as_tensor(predicted).long()
    if predicted.shape != mask.shape:
        raise ValueError(f"predicted must be [B, T] = {list(mask.shape)} like the demonstrations, got {list(predicted.shape)}.")
    truth = data.get(label_key).long()
    pred = torch.where(mask, predicted, 0)
    # relabel to 0..n-1 (best_matching_accuracy indexes a square table by label)
    _, pred_ids = torch.unique(pred[mask], return_inverse=True)
    _, true_ids = torch.unique(truth[mask], return_inverse=True)
    out = {"label_accuracy": best_matching_accuracy(pred_ids, true_ids)}
    bounds = _changes(predicted, mask) if boundaries is None else torch.as_tensor(boundaries).bool() & mask
    bounds[:, 0] = False
    out.update(_boundary_scores(bounds, data, switch_key, windows))
    return out


def baseline_scores(
    data: TensorDictBase,
    *,
    label_key: str = "true_option",
    switch_key: str = "true_switch",
    windows: Sequence[int] = (1, 2),
    seed: int = 0,
    num_samples: int = 20,
) -> dict[str, dict[str, float]]:
    """The trivial baselines' scores on the demonstrations (see the module docstring): ``action_change``,
    ``random`` (at the reference's boundary rate, ``num_samples`` draws from ``seed``) and ``one_option``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"true_option": torch.tensor([[0, 0, 0, 1, 1, 1]]), "action": torch.tensor([[2, 2, 2, 3, 3, 3]]),
        ...                    "true_switch": torch.tensor([[1, 0, 0, 1, 0, 0]]).bool(),
        ...                    ("collector", "mask"): torch.ones(1, 6, dtype=torch.bool)}, [1, 6])
        >>> base = baseline_scores(data)
        >>> base["action_change"]["f1_w1"], base["action_change"]["label_accuracy"], base["one_option"]["label_accuracy"]
        (1.0, 1.0, 0.5)
        >>> base["one_option"]["f1_w2"], base["random"]["boundary_rate"]
        (0.0, 0.2)
    """
    from torchrl_options.segmentation import random_baseline

    mask = _check(data, label_key, switch_key)
    actions = data.get("action").long().reshape(mask.shape)
    out = {"action_change": segmentation_scores(actions, data, label_key=label_key, switch_key=switch_key,
                                                windows=windows)}  # fmt: skip
    truth = data.get(label_key).long()[mask]
    counts = torch.bincount(truth - truth.min())
    one = {"label_accuracy": float(counts.max() / counts.sum())}
    n_ref = int((data.get(switch_key).bool() & mask)[:, 1:].sum())
    candidates = max(int(mask.sum()) - mask.shape[0], 1)
    rate = n_ref / candidates
    for w in windows:
        one.update({f"precision_w{w}": math.nan, f"recall_w{w}": 0.0, f"f1_w{w}": 0.0})
    one.update(boundary_rate=0.0, reference_rate=rate)
    out["one_option"] = one
    reference = data.get(switch_key).bool() & mask
    rng = np.random.default_rng(seed)
    rand = {"label_accuracy": math.nan}
    for w in windows:
        r = random_baseline(reference, mask, int(w), rate, num_samples=num_samples, generator=rng)
        rand.update({f"precision_w{w}": r["precision"], f"recall_w{w}": r["recall"], f"f1_w{w}": r["f1"]})
    rand.update(boundary_rate=rate, reference_rate=rate)
    out["random"] = rand
    return out


def option_composition(
    predicted: torch.Tensor, data: TensorDictBase, *, label_key: str = "true_option", names: Sequence[str] | None = None,
    num_options: int | None = None,
) -> dict:
    """What each option holds: its share of the valid steps, the share of its steps per reference label, the
    reference labels it is the majority option of (labels sharing an option are merged), and segment lengths.

    Returns:
        dict with ``usage`` (per option, share of steps), ``options_used`` (options holding at least
        :data:`~torchrl_options.discovery.UNUSED_SHARE` of the steps), ``max_usage``, ``contents`` (per option, a
        dict label name -> share of that option's steps, largest first, shares >= 0.05), ``majority_option`` (per
        label name, the option holding most of its steps and the share it holds), ``merged`` (lists of label names
        whose majority option is the same), ``mean_segment_length`` and ``reference_mean_segment_length``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"true_option": torch.tensor([[0, 0, 1, 1, 2, 2]]),
        ...                    ("collector", "mask"): torch.ones(1, 6, dtype=torch.bool)}, [1, 6])
        >>> c = option_composition(torch.tensor([[0, 0, 0, 0, 1, 1]]), data, names=["a", "b", "c"])
        >>> c["usage"], c["merged"], c["majority_option"]["c"]
        ([0.666..., 0.333...], [['a', 'b']], [1, 1.0])
    """
    from torchrl_options.discovery import UNUSED_SHARE

    mask = data.get(_MASK).bool()
    pred = torch.as_tensor(predicted).long()[mask]
    truth = data.get(label_key).long()[mask]
    K = int(num_options if num_options is not None else int(pred.max()) + 1)
    L = int(truth.max()) + 1
    names = list(names) if names is not None else [str(i) for i in range(L)]
    confusion = torch.zeros(K, L)
    confusion.index_put_((pred, truth), torch.ones(pred.numel()), accumulate=True)
    n = float(pred.numel())
    usage = (confusion.sum(1) / n).tolist()
    contents = []
    for h in range(K):
        total = confusion[h].sum()
        row = {names[j]: float(confusion[h, j] / total) for j in range(L) if total > 0 and confusion[h, j] / total >= 0.05}
        contents.append(dict(sorted(row.items(), key=lambda kv: -kv[1])))
    majority, groups = {}, {}
    for j in range(L):
        col = confusion[:, j]
        if col.sum() == 0:
            continue
        h = int(col.argmax())
        majority[names[j]] = [h, float(col[h] / col.sum())]
        groups.setdefault(h, []).append(names[j])
    lengths = mask.sum(1).float()
    segs = (_changes(torch.as_tensor(predicted).long(), mask).sum(1) + 1).float()
    ref_segs = (_changes(data.get(label_key).long(), mask).sum(1) + 1).float()
    return {
        "usage": usage,
        "options_used": int(sum(u >= UNUSED_SHARE for u in usage)),
        "max_usage": max(usage),
        "contents": contents,
        "majority_option": majority,
        "merged": [g for g in groups.values() if len(g) > 1],
        "mean_segment_length": float((lengths / segs).mean()),
        "reference_mean_segment_length": float((lengths / ref_segs).mean()),
    }


#: What :func:`option_information` measures the options against, in its order.
INFORMATION_TARGETS = ("skill", "subgoal", "action", "turn_side", "direction", "carrying")



def _entropy(counts: np.ndarray) -> float:
    p = counts[counts > 0] / counts.sum()
    return float(-(p * np.log(p)).sum())


def _explained(option: np.ndarray, target: np.ndarray) -> float:
    """I(option; target) / H(target) from the empirical joint (nan when the target is constant)."""
    if target.size == 0:
        return math.nan
    _, t = np.unique(target, return_inverse=True)
    _, o = np.unique(option, return_inverse=True)
    joint = np.zeros((o.max() + 1, t.max() + 1))
    np.add.at(joint, (o, t), 1.0)
    h_t = _entropy(joint.sum(0))
    if h_t == 0.0:
        return math.nan
    mutual = _entropy(joint.sum(0)) + _entropy(joint.sum(1)) - _entropy(joint.ravel())
    return float(min(max(mutual / h_t, 0.0), 1.0))


def option_information(predicted: torch.Tensor, data: TensorDictBase, *, handed: float = 0.9) -> dict:
    """What the options track: for each target, the share of its entropy that the option explains,
    ``I(option; target) / H(target)`` over the valid steps (0: independent, 1: the option determines it).

    Targets (:data:`INFORMATION_TARGETS`): ``skill`` and ``subgoal`` (the bot's labels, ``"skill"`` and
    ``"true_option"``), ``action`` (the bot's action), ``turn_side`` (left or right, over the steps that turn),
    ``direction`` (the agent's heading, from the observation's last four features) and ``carrying`` (the object type
    shown on the agent's own cell of the egocentric view: what it carries). Also ``handed_turns``: the share of the
    turning steps held by options that turn to one side at least ``handed`` of the time (left-turning and
    right-turning walkers). A target that is constant over the steps (or data without a valid step) gives ``nan``.

    Args:
        predicted (Tensor): ``[B, T]`` option per step (padding ignored).
        data (TensorDictBase): :func:`~torchrl_options.experiments.minigrid.bot_demonstrations` data (``"skill"``,
            ``"true_option"``, ``"action"``, ``"observation"``, ``("collector", "mask")``).

    Keyword Args:
        handed (float): the share of one side above which an option counts as turning to that side.
            Defaults to 0.9.

    Returns:
        dict: one float per target, and ``handed_turns``.

    Raises:
        ValueError: a missing key, a shape that is not the data's ``[B, T]``, an observation that is not MiniGrid's
            one-hot view and direction, or ``handed`` outside (0.5, 1].
        TypeError: ``predicted`` that is not integer.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.envs.minigrid import observation_size
        >>> obs = torch.zeros(1, 4, observation_size())
        >>> data = TensorDict({"skill": torch.tensor([[0, 0, 1, 1]]), "true_option": torch.tensor([[0, 0, 1, 1]]),
        ...                    "action": torch.tensor([[0, 1, 0, 1]]), "observation": obs,
        ...                    ("collector", "mask"): torch.ones(1, 4, dtype=torch.bool)}, [1, 4])
        >>> info = option_information(torch.tensor([[0, 1, 0, 1]]), data)  # the options are the turn's side
        >>> info["turn_side"], info["skill"], info["handed_turns"]
        (1.0, 0.0, 1.0)
    """
    from torchrl_options.envs.minigrid import MINIGRID_ACTIONS, NUM_OBJECT_TYPES, view_from_observation

    turns = (MINIGRID_ACTIONS.index("left"), MINIGRID_ACTIONS.index("right"))

    if isinstance(handed, bool) or not isinstance(handed, (int, float)) or not 0.5 < float(handed) <= 1.0:
        raise ValueError(f"handed must be a share in (0.5, 1], got {handed!r}.")
    keys = data.keys(include_nested=True)
    for key in (_MASK, "skill", "true_option", "action", "observation"):
        if key not in keys:
            raise ValueError(f"data has no {key!r}: option_information needs bot_demonstrations' data.")
    mask = data.get(_MASK).bool()
    pred = torch.as_tensor(predicted)
    if pred.is_floating_point() or pred.is_complex() or pred.dtype == torch.bool:
        raise TypeError(f"predicted must hold integer option indices, got {pred.dtype}.")
    if tuple(pred.shape) != tuple(mask.shape):
        raise ValueError(f"predicted must be [B, T] = {tuple(mask.shape)}, like the data, got {tuple(pred.shape)}.")
    view, direction = view_from_observation(data.get("observation"))  # raises on another observation
    w, h = view.shape[-2:]
    carrying = view[..., :NUM_OBJECT_TYPES, w // 2, h - 1].argmax(-1)  # the agent's own cell: bottom centre
    action = data.get("action").reshape(mask.shape)
    option = pred.long()[mask].numpy()
    act = action.long()[mask].numpy()
    targets = {"skill": data.get("skill"), "subgoal": data.get("true_option"), "action": action,
               "direction": direction.argmax(-1), "carrying": carrying}  # fmt: skip
    out = {name: _explained(option, value.long()[mask].numpy()) for name, value in targets.items()}
    turn = np.isin(act, turns)
    out["turn_side"] = _explained(option[turn], act[turn])
    held = 0
    for o in np.unique(option[turn]):
        sel = turn & (option == o)
        if max((act[sel] == side).mean() for side in turns) >= handed:
            held += int(sel.sum())
    out["handed_turns"] = held / int(turn.sum()) if turn.any() else math.nan
    return {name: out[name] for name in (*INFORMATION_TARGETS, "handed_turns")}
