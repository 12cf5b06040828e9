"""Symmetry-breaking initialisation of options: pre-clustering of state-action pairs (k-means).

Appendix B of Fox et al. (2017): as in clustering, the model must be initialised so that options differ; the
state-action pairs can first be clustered, and each option fitted to one cluster before DDO starts.
"""
from __future__ import annotations

import logging

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_options.objectives.ddo import option_log_probs

__all__ = ["kmeans", "pretrain_on_clusters"]

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
