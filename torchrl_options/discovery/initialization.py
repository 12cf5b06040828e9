"""Symmetry-breaking initialisation of options: pre-clustering of steps or of segments.

Appendix B of Fox et al. (2017): as in clustering, the model must be initialised so that options differ; the
state-action pairs can first be clustered, and each option fitted to one cluster before DDO starts
(:func:`pretrain_on_clusters`). Options are temporally extended, so a cluster of single steps often mixes options
that share moves; :func:`pretrain_on_segments` cuts the demonstrations where the actions change regime
(:func:`change_points`), clusters the segments by where they end, and clones each option's policy *and* its
termination from its segments.
"""
from __future__ import annotations

import logging

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_int, check_number, check_positive_number
from torchrl_options.discovery.validation import check_options_module
from torchrl_options.objectives.ddo import option_log_probs

__all__ = ["change_points", "clone_from_labels", "kmeans", "pretrain_on_clusters", "pretrain_on_segments"]

logger = logging.getLogger(__name__)


def kmeans(
    x: torch.Tensor, k: int, *, num_iterations: int = 50, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lloyd's k-means with k-means++ seeding, in torch.

    Args:
        x (Tensor): ``[N, D]`` points.
        k (int): number of clusters (``1 <= k <= N``).

    Keyword Args:
        num_iterations (int): Lloyd iterations. Defaults to 50.
        generator (torch.Generator, optional): for the seeding.

    Returns:
        ``(labels [N] long, centroids [k, D])``.

    Examples:
        >>> import torch
        >>> x = torch.cat([torch.zeros(5, 2), torch.ones(5, 2) * 10])
        >>> labels, centroids = kmeans(x, 2, generator=torch.Generator().manual_seed(0))
        >>> bool((labels[:5] == labels[0]).all() and (labels[5:] != labels[0]).all())
        True
    """
    n = x.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"kmeans needs 1 <= k <= number of points, got k={k} for {n} points.")
    x = x.float()
    idx = torch.randint(n, (1,), generator=generator, device="cpu").to(x.device)
    centroids = x[idx]
    for _ in range(1, k):
        d2 = torch.cdist(x, centroids).min(1).values.pow(2)
        total = d2.sum()
        probs = d2 / total if total > 0 else torch.full_like(d2, 1.0 / n)
        nxt = torch.multinomial(probs.cpu(), 1, generator=generator).to(x.device)
        centroids = torch.cat([centroids, x[nxt]])
    labels = torch.cdist(x, centroids).argmin(1)
    for _ in range(num_iterations):
        one_hot = torch.nn.functional.one_hot(labels, k).to(x.dtype)
        counts = one_hot.sum(0)
        sums = one_hot.T @ x
        centroids = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], centroids)
        new = torch.cdist(x, centroids).argmin(1)
        if torch.equal(new, labels):
            break
        labels = new
    return labels, centroids


def pretrain_on_clusters(
    options: TensorDictModuleBase,
    trajectories: TensorDictBase,
    mask: torch.Tensor,
    *,
    num_options: int,
    action_key: NestedKey = "action",
    action_space: str = "auto",
    num_actions: int | None = None,
    meta_control: TensorDictModuleBase | None = None,
    num_steps: int = 200,
    lr: float = 1e-2,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Clusters the valid state-action pairs into ``num_options`` groups and fits option h to cluster h.

    Each option's control policy is trained by behaviour cloning on its cluster's steps; a learned
    ``meta_control`` is trained to predict the cluster of each step. Termination networks are left as they are.

    Args:
        options (TensorDictModuleBase): the options to initialise (modified in place).
        trajectories (TensorDictBase): ``[B, T]`` trajectories.
        mask (Tensor): ``[B, T]`` bool, the valid steps.

    Keyword Args:
        num_options (int): K.
        action_key (NestedKey): the action entry.
        action_space (str): ``"auto"``, ``"categorical"`` or ``"continuous"``.
        num_actions (int, optional): A, to one-hot discrete actions for the clustering features.
        meta_control (TensorDictModuleBase, optional): a learned meta-control to pre-train as well.
        num_steps (int): Adam steps of the pre-training. Defaults to 200.
        lr (float): its learning rate. Defaults to 1e-2.
        generator (torch.Generator, optional): seeds the k-means.

    Returns:
        The cluster label of every valid step, ``[num_valid]``.
    """
    check_int(num_options, "num_options", minimum=1)
    _check_cloning_inputs(options, trajectories, mask, num_options, action_space=action_space, num_actions=num_actions,
                          needs_next=False)  # fmt: skip
    flat = trajectories[mask]
    obs = torch.cat([flat.get(k).flatten(1).float() for k in options.in_keys], -1)
    action = flat.get(action_key)
    if action.is_floating_point():
        act_feat = action.flatten(1).float()
    else:
        if num_actions is None:
            num_actions = int(action.max()) + 1
        act_feat = torch.nn.functional.one_hot(action.reshape(-1).long(), num_actions).float()
    feats = torch.cat([obs, act_feat], -1)
    feats = (feats - feats.mean(0)) / feats.std(0).clamp_min(1e-6)
    labels, _ = kmeans(feats, num_options, generator=generator)
    counts = torch.bincount(labels, minlength=num_options).tolist()
    logger.info("pre-clustering: cluster sizes %s", counts)
    params = list(options.parameters()) + (list(meta_control.parameters()) if meta_control is not None else [])
    opt = torch.optim.Adam(params, lr=lr)
    weights = torch.nn.functional.one_hot(labels, num_options).to(obs.dtype)
    for _ in range(num_steps):
        out = options(flat.select(*options.in_keys))
        log_pi = option_log_probs(out, action, action_space=action_space, action_key=action_key)
        loss = -(weights * log_pi).sum() / len(labels)
        if meta_control is not None:
            meta = meta_control(flat.select(*meta_control.in_keys)).get("meta_logits")
            loss = loss + torch.nn.functional.cross_entropy(meta, labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return labels


def _check_cloning_inputs(
    options: TensorDictModuleBase,
    trajectories: TensorDictBase,
    mask: torch.Tensor,
    num_options: int | None,
    *,
    action_space: str,
    num_actions: int | None = None,
    needs_next: bool = True,
) -> int:
    """The door of the pre-training functions: ``[B, T]`` trajectories with a ``[B, T]`` mask, an options module
    that reads them and has ``num_options`` options (run once on one step), and the ``("next", key)`` entries of its
    ``in_keys`` when terminations are cloned. Returns the module's K."""
    if not isinstance(trajectories, TensorDictBase) or trajectories.ndim != 2:
        got = list(trajectories.batch_size) if isinstance(trajectories, TensorDictBase) else type(trajectories).__name__
        raise ValueError(f"trajectories must be a [B, T] tensordict (as_trajectory_batch), got {got}.")
    if not isinstance(mask, torch.Tensor) or tuple(mask.shape) != tuple(trajectories.batch_size):
        got = list(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"mask must be a [B, T] = {list(trajectories.batch_size)} bool tensor, got {got}.")
    k = check_options_module(options, trajectories, num_options, num_actions=num_actions, action_space=action_space)
    if needs_next:
        for key in options.in_keys:
            nxt = ("next", *((key,) if isinstance(key, str) else key))
            if nxt not in trajectories.keys(include_nested=True):
                raise ValueError(
                    f"the trajectories have no {nxt!r} entry: the options' terminations are cloned at the next "
                    f"observation of their in_keys {list(options.in_keys)}."
                )
    return k


def _action_features(action: torch.Tensor, num_actions: int | None) -> torch.Tensor:
    """``[B, T, F]`` float features of the actions: one-hot for integer actions, standardised for continuous ones."""
    if action.is_floating_point():
        flat = action.flatten(2).float()
        return flat
    action = action.reshape(*action.shape[:2], -1)[..., 0].long().clamp_min(0)
    if num_actions is None:
        num_actions = int(action.max()) + 1
    return torch.nn.functional.one_hot(action, num_actions).float()


def _distinct_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(index of each distinct row's first occurrence, its count as float)`` of ``[N, D]`` ``x``."""
    if x.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=x.device), x.new_zeros(0)
    _, inverse, counts = torch.unique(x, dim=0, return_inverse=True, return_counts=True)
    first = torch.full((counts.shape[0],), x.shape[0], dtype=torch.long, device=x.device)
    first.scatter_reduce_(0, inverse, torch.arange(x.shape[0], device=x.device), "amin")
    return first, counts.to(x.dtype)


def change_points(
    action: torch.Tensor,
    mask: torch.Tensor,
    *,
    window: int = 5,
    threshold: float = 0.5,
    num_actions: int | None = None,
) -> torch.Tensor:
    """Where the actions change regime: the steps that start a new segment.

    For each step ``t``, the actions of the ``window`` steps before it are compared with those of the ``window``
    steps from it on: discrete actions by the total-variation distance between their (add-half smoothed)
    histograms, continuous actions by the distance between their means in units of the actions' spread (capped
    at 1). A step starts a segment where this score is a local maximum above ``threshold``; the first step of every
    trajectory does too.

    Args:
        action (Tensor): ``[B, T]`` (or ``[B, T, 1]``) integer actions, or ``[B, T, D]`` continuous ones.
        mask (Tensor): ``[B, T]`` bool, the valid steps (padding after them).

    Keyword Args:
        window (int): steps on each side. Defaults to 5.
        threshold (float): the least score of a cut, in ``(0, 1)``. Defaults to 0.5.
        num_actions (int, optional): A, for discrete actions; default ``max(action) + 1``.

    Returns:
        ``[B, T]`` bool: ``True`` where a segment starts (always ``False`` on padding).

    Examples:
        >>> import torch
        >>> action = torch.tensor([[0] * 8 + [1] * 8])
        >>> cuts = change_points(action, torch.ones(1, 16, dtype=torch.bool), window=4)
        >>> cuts.nonzero()[:, 1].tolist()
        [0, 8]
    """
    check_int(window, "window", minimum=1)
    check_number(threshold, "threshold", lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    mask = mask.bool()
    if mask.dim() != 2 or action.shape[:2] != mask.shape:
        raise ValueError(
            f"change_points needs a [B, T] mask and [B, T, ...] actions, got mask {tuple(mask.shape)} and action "
            f"{tuple(action.shape)}."
        )
    if not action.is_floating_point():
        if action.dtype == torch.bool or action.is_complex():
            raise TypeError(f"change_points: action must hold integer (or float) actions, got dtype {action.dtype}.")
        if bool(mask.any()) and int(action[mask].min()) < 0:
            raise ValueError(
                f"change_points: discrete actions must be >= 0 at valid steps, got {int(action[mask].min())} "
                "(a padding value such as -1 must sit under mask=False)."
            )
    elif bool(mask.any()) and not bool(torch.isfinite(action[mask]).all()):
        raise ValueError("change_points: action holds NaN or infinite values at valid steps.")
    if num_actions is not None and not action.is_floating_point():
        top = int(action[mask].max()) + 1 if bool(mask.any()) else 0
        check_int(num_actions, "num_actions")
        if num_actions < max(top, 1):
            raise ValueError(f"num_actions must be an int above every action (max {top - 1}), got {num_actions!r}.")
    B, T = mask.shape
    feats = _action_features(action, num_actions).to(mask.device)
    continuous = action.is_floating_point()
    if continuous:
        valid = feats[mask]
        spread = valid.std(0).clamp_min(1e-6) if valid.shape[0] > 1 else torch.ones(feats.shape[-1])
        feats = (feats - valid.mean(0)) / spread
    feats = feats * mask[..., None]
    F = feats.shape[-1]
    csum = torch.cat([feats.new_zeros(B, 1, F), feats.cumsum(1)], 1)
    length = mask.sum(1)
    t = torch.arange(T, device=mask.device)[None].expand(B, T)
    lo = (t - window).clamp_min(0)
    hi = torch.minimum(t + window, length[:, None])

    def window_sum(i: torch.Tensor) -> torch.Tensor:
        return torch.gather(csum, 1, i[..., None].expand(B, T, F))

    before = window_sum(t) - window_sum(lo)
    after = window_sum(hi) - window_sum(t)
    if continuous:
        n_before = (t - lo).clamp_min(1)[..., None].float()
        n_after = (hi - t).clamp_min(1)[..., None].float()
        score = ((before / n_before - after / n_after).norm(dim=-1) / (2 * F**0.5)).clamp(max=1.0)
    else:
        p_before = (before + 0.5) / (before + 0.5).sum(-1, keepdim=True)
        p_after = (after + 0.5) / (after + 0.5).sum(-1, keepdim=True)
        score = 0.5 * (p_before - p_after).abs().sum(-1)
    score = score * mask
    score[:, 0] = 0
    left = torch.cat([score.new_zeros(B, 1), score[:, :-1]], 1)
    right = torch.cat([score[:, 1:], score.new_zeros(B, 1)], 1)
    cuts = (score >= left) & (score > right) & (score > threshold) & mask
    cuts[:, 0] = mask[:, 0]
    return cuts


def pretrain_on_segments(
    options: TensorDictModuleBase,
    trajectories: TensorDictBase,
    mask: torch.Tensor,
    *,
    num_options: int,
    action_key: NestedKey = "action",
    action_space: str = "auto",
    num_actions: int | None = None,
    meta_control: TensorDictModuleBase | None = None,
    termination_key: NestedKey = "termination_logits",
    features: str = "end",
    window: int = 5,
    threshold: float = 0.5,
    num_steps: int = 500,
    lr: float = 3e-2,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Cuts the demonstrations into segments, clusters the segments by where they end, and clones options from them.

    The segments are the stretches between :func:`change_points`. Each is described by the observation after its
    last step (where an option that ran it would have terminated); k-means (:func:`kmeans`) groups them into
    ``num_options`` clusters, every step taking its segment's cluster. Option ``h`` is then cloned on cluster
    ``h``: its control policy by behaviour cloning on the cluster's steps, its termination by logistic regression
    (terminate after the last step of each of its segments, continue after the others), and ``meta_control``, if
    given, to predict the cluster of each segment's first step. A start from these labels lies near an option
    structure that steps alone cannot show (options that share moves in many states); DDO
    (:class:`~torchrl_options.DDOLoss`, Fox et al., 2017) refines it. Unlike appendix B's pre-clustering of
    state-action pairs (:func:`pretrain_on_clusters`), the clusters see time.

    Args:
        options (TensorDictModuleBase): the options to initialise (modified in place).
        trajectories (TensorDictBase): ``[B, T]`` trajectories with ``("next", obs)`` entries.
        mask (Tensor): ``[B, T]`` bool, the valid steps.

    Keyword Args:
        num_options (int): K.
        action_key (NestedKey): the action entry.
        action_space (str): ``"auto"``, ``"categorical"`` or ``"continuous"``.
        num_actions (int, optional): A, for discrete actions.
        meta_control (TensorDictModuleBase, optional): a learned meta-control to pre-train as well.
        termination_key (NestedKey): where the options write their termination logits.
        features (str): what the segments are clustered by: ``"end"`` (default), the observation after their last
            step (options defined by where they lead), or ``"actions"``, their mean action (one-hot for discrete
            actions: options defined by how they move).
        window, threshold: see :func:`change_points`. Defaults to 5 and 0.5.
        num_steps (int): Adam steps of the cloning. Defaults to 500.
        lr (float): its learning rate. Defaults to 0.03.
        generator (torch.Generator, optional): seeds the k-means.

    Returns:
        The cluster label of every step, ``[B, T]`` (0 on padding).

    Examples:
        >>> import torch
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(num_trajectories=8, length=30, seed=0)
        >>> options = OptionsMLP(data["observation"].shape[-1], 2, 2)
        >>> labels = pretrain_on_segments(options, data, data["collector", "mask"], num_options=2, num_steps=20,
        ...                               generator=torch.Generator().manual_seed(0))
        >>> labels.shape == data["collector", "mask"].shape
        True
    """
    if features not in ("end", "actions"):
        raise ValueError(f"features must be 'end' or 'actions', got {features!r}.")
    check_int(num_options, "num_options", minimum=1)
    check_int(num_steps, "num_steps", minimum=1)
    check_positive_number(lr, "lr")
    _check_cloning_inputs(options, trajectories, mask, num_options, action_space=action_space, num_actions=num_actions)
    mask = mask.bool()
    B, T = mask.shape
    action = trajectories.get(action_key)
    cuts = change_points(action, mask, window=window, threshold=threshold, num_actions=num_actions)
    segment = cuts.long().cumsum(1)
    ids = (torch.arange(B, device=mask.device)[:, None] * (T + 1) + segment)[mask]
    _, inverse = torch.unique(ids, return_inverse=True)
    num_segments = int(inverse.max()) + 1 if inverse.numel() else 0
    step = torch.arange(inverse.numel(), device=mask.device)
    last = torch.zeros(num_segments, dtype=torch.long, device=mask.device).scatter_reduce_(
        0, inverse, step, "amax", include_self=False
    )
    flat = trajectories[mask]
    flat_next = flat.get("next")
    next_obs = torch.cat([flat_next.get(k).flatten(1).float() for k in options.in_keys], -1)
    if features == "end":
        points = next_obs[last]
    else:  # the segment's mean action (discrete: its action histogram)
        acts = _action_features(action, num_actions).to(next_obs.device)[mask]
        points = torch.zeros(num_segments, acts.shape[-1], device=acts.device).index_add_(0, inverse, acts)
        points = points / torch.bincount(inverse, minlength=num_segments).clamp_min(1)[:, None].to(points.dtype)
    points = (points - points.mean(0)) / points.std(0).clamp_min(1e-6) if num_segments > 1 else points
    k = min(num_options, max(num_segments, 1))
    seg_labels, _ = kmeans(points, k, generator=generator)
    counts = torch.bincount(seg_labels, minlength=num_options).tolist()
    logger.info("segment pre-clustering: %d segments, clusters of %s segments", num_segments, counts)
    labels = torch.zeros(B, T, dtype=torch.long, device=mask.device)
    labels[mask] = seg_labels[inverse]
    clone_from_labels(
        options, trajectories, mask, labels, cuts, action_key=action_key, action_space=action_space,
        meta_control=meta_control, termination_key=termination_key, num_steps=num_steps, lr=lr,
    )
    return labels


def clone_from_labels(
    options: TensorDictModuleBase,
    trajectories: TensorDictBase,
    mask: torch.Tensor,
    labels: torch.Tensor,
    starts: torch.Tensor,
    *,
    action_key: NestedKey = "action",
    action_space: str = "auto",
    meta_control: TensorDictModuleBase | None = None,
    termination_key: NestedKey = "termination_logits",
    num_steps: int = 500,
    lr: float = 3e-2,
) -> None:
    """Clones options from a labelling of the demonstrations' steps: policies, terminations and meta-control.

    Option ``h``'s control policy is fitted by behaviour cloning on the steps labelled ``h``; its termination by
    logistic regression at ``s_{t+1}`` (terminate after a step labelled ``h`` when the next step starts an option,
    continue otherwise; the last valid step of a trajectory is no target, since the data's end is not a
    termination); ``meta_control``, if given, to predict the label of each step that starts an option. The two
    terms are averaged over their own steps and summed, and ``num_steps`` Adam steps minimise them: the
    complete-data negative log-likelihood of DDO's model (Fox et al., 2017) along the given labels. Used by
    :func:`pretrain_on_segments` (labels from clustered segments) and by diagnoses that start from the truth.

    Args:
        options (TensorDictModuleBase): the options to fit (modified in place).
        trajectories (TensorDictBase): ``[B, T]`` trajectories with ``("next", obs)`` entries.
        mask (Tensor): ``[B, T]`` bool, the valid steps.
        labels (Tensor): ``[B, T]`` integer option of every step (read on valid steps only).
        starts (Tensor): ``[B, T]`` bool, the steps where an option starts (the same option redrawn included).

    Keyword Args:
        action_key (NestedKey): the action entry.
        action_space (str): ``"auto"``, ``"categorical"`` or ``"continuous"``.
        meta_control (TensorDictModuleBase, optional): a learned meta-control to fit as well.
        termination_key (NestedKey): where the options write their termination logits.
        num_steps (int): Adam steps. Defaults to 500.
        lr (float): the learning rate. Defaults to 0.03.

    Examples:
        >>> import torch
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(num_trajectories=8, length=30, seed=0)
        >>> mask = data["collector", "mask"]
        >>> starts = torch.zeros_like(mask)
        >>> starts[:, 0] = True
        >>> options = OptionsMLP(data["observation"].shape[-1], 2, 2)
        >>> clone_from_labels(options, data, mask, data["true_option"].clamp_min(0), starts, num_steps=20)
    """
    check_int(num_steps, "num_steps", minimum=1)
    check_positive_number(lr, "lr")
    num_options = _check_cloning_inputs(options, trajectories, mask, None, action_space=action_space)
    mask = mask.bool()
    for name, value in (("labels", labels), ("starts", starts)):
        if not isinstance(value, torch.Tensor) or value.shape != mask.shape:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(f"{name} must be a tensor of the mask's shape {tuple(mask.shape)}, got {got}.")
    if labels.is_floating_point() or labels.dtype == torch.bool:
        raise TypeError(f"labels must be an integer tensor, got {labels.dtype}.")
    valid_labels = labels[mask]
    if valid_labels.numel() and (int(valid_labels.min()) < 0 or int(valid_labels.max()) >= num_options):
        raise ValueError(
            f"labels must lie in [0, {num_options}) on valid steps, got {int(valid_labels.min())} to "
            f"{int(valid_labels.max())}."
        )
    starts = starts.bool()
    labels = torch.where(mask, labels, torch.zeros_like(labels)).long()
    flat = trajectories[mask]
    flat_next = flat.get("next")
    next_obs = torch.cat([flat_next.get(k).flatten(1).float() for k in options.in_keys], -1)
    # a step is its option's last (terminate after it) when the next step starts an option
    ends_here = torch.zeros_like(mask)
    ends_here[:, :-1] = starts[:, 1:] | ~mask[:, 1:]
    ends_here[:, -1] = True
    ends_here &= mask
    # the last valid step of a trajectory may be cut by the data's end, not by a termination: not a target
    has_next = mask.clone()
    has_next[:, :-1] &= mask[:, 1:]
    has_next[:, -1] = False
    flat_labels = labels[mask]
    flat_action = flat.get(action_key)
    act_cols = flat_action.reshape(flat_action.shape[0], -1).to(next_obs.dtype)
    now_obs = torch.cat([flat.get(k).flatten(1).float() for k in options.in_keys], -1)
    # identical rows give identical loss terms: train on the distinct ones, weighted by their counts (the same loss)
    now_rows, now_w = _distinct_rows(torch.cat([now_obs, act_cols, flat_labels[:, None].to(now_obs.dtype)], -1))
    valid_next = has_next[mask]
    next_rows, next_w = _distinct_rows(torch.cat(
        [next_obs, flat_labels[:, None].to(next_obs.dtype), ends_here[mask][:, None].to(next_obs.dtype)], -1
    )[valid_next])  # fmt: skip
    next_rows = valid_next.nonzero().squeeze(-1)[next_rows]
    in_now = flat[now_rows].select(*options.in_keys)
    in_next = flat_next[next_rows].select(*options.in_keys)
    action_now, label_now, label_next = flat_action[now_rows], flat_labels[now_rows], flat_labels[next_rows]
    target_next = ends_here[mask][next_rows].to(now_obs.dtype)
    start_rows = starts[mask]
    params = list(options.parameters()) + (list(meta_control.parameters()) if meta_control is not None else [])
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(num_steps):
        out = options(in_now.clone(False))
        log_pi = option_log_probs(out, action_now, action_space=action_space, action_key=action_key)
        policy = -(log_pi.gather(-1, label_now[:, None]).squeeze(-1) * now_w).sum() / now_w.sum()
        loss = policy
        if next_rows.numel():
            term = options(in_next.clone(False)).get(termination_key).gather(-1, label_next[:, None]).squeeze(-1)
            bce = torch.nn.functional.binary_cross_entropy_with_logits(term, target_next, reduction="none")
            loss = loss + (bce * next_w).sum() / next_w.sum()
        if meta_control is not None and bool(start_rows.any()):
            meta = meta_control(flat[start_rows].select(*meta_control.in_keys)).get("meta_logits")
            loss = loss + torch.nn.functional.cross_entropy(meta, flat_labels[start_rows])
        opt.zero_grad()
        loss.backward()
        opt.step()
