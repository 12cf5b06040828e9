"""Segmentation of demonstrations by discovered options: posterior, most likely option sequence, boundaries.

Fox, Krishnan, Stoica, Goldberg (2017), section 5.3: with the options of DDO, the posterior over the latent option
chain of a demonstration segments it into the skills that produced it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from torchrl_options.checks import check_int, check_number, check_same_device, check_tensor
from torchrl_options.discovery.validation import check_options_module, check_step_data
from torchrl_options.discovery import as_trajectory_batch, DiscoveryResult
from torchrl_options.inference import forward_backward, most_likely_options, viterbi
from torchrl_options.objectives import DDOLoss

__all__ = ["Segmentation", "segment", "boundaries_from_options"]

_MASK = ("collector", "mask")


def boundaries_from_options(options: Tensor, mask: Tensor | None = None) -> Tensor:
    """``[B, T]`` bool: the steps ``t >= 1`` where the option label differs from the previous step's.

    Examples:
        >>> import torch
        >>> boundaries_from_options(torch.tensor([[0, 0, 1, 1, 0, -1]])).int()
        tensor([[0, 0, 1, 0, 1, 0]], dtype=torch.int32)
    """
    check_tensor(options, "options", ndim=2, dtype="integer", owner="boundaries_from_options")
    if mask is not None:
        check_tensor(mask, "mask", shape=tuple(options.shape), dtype="bool", owner="boundaries_from_options")
        check_same_device({"options": options, "mask": mask}, "boundaries_from_options")
    change = torch.zeros_like(options, dtype=torch.bool)
    change[:, 1:] = options[:, 1:] != options[:, :-1]
    valid = options >= 0 if mask is None else mask.bool()
    return change & valid


@dataclass
class Segmentation:
    """The segmentation of ``B`` trajectories by ``K`` options (returned by :func:`segment`).

    Attributes:
        options (Tensor): ``[B, T]`` long, the option of each step (Viterbi or posterior argmax), ``-1`` on padding.
        boundary_mask (Tensor): ``[B, T]`` bool, a new segment starts at step ``t``; never at ``t = 0`` (the start
            of a trajectory is not counted as a boundary) nor on padding.
        posterior (Tensor): ``[B, T, K]``, ``u_t(h) = P(h_t = h | trajectory)``.
        switch_probability (Tensor): ``[B, T]``, ``P(b_t = 1 | trajectory)``, the posterior probability that an
            option starts at ``t`` (possibly the same one again); 1 at ``t = 0``, 0 on padding.
        log_likelihood (Tensor): ``[B]``, ``log P(trajectory)`` under the options.
        lengths (Tensor): ``[B]`` long, valid steps per trajectory.
        method (str): ``"viterbi"`` or ``"posterior"``.
        boundary (str): ``"change"`` or ``"switch"``, the boundary rule used.
    """

    options: Tensor
    boundary_mask: Tensor
    posterior: Tensor
    switch_probability: Tensor
    log_likelihood: Tensor
    lengths: Tensor
    method: str = "viterbi"
    boundary: str = "change"

    @property
    def num_options(self) -> int:
        """K."""
        return self.posterior.shape[-1]

    @property
    def boundaries(self) -> list[list[int]]:
        """The boundary steps of each trajectory (``t >= 1``), a list of ``B`` sorted lists."""
        return [row.nonzero().flatten().tolist() for row in self.boundary_mask.cpu()]

    def segments(self, index: int) -> list[tuple[int, int, int]]:
        """The segments of trajectory ``index`` as ``(start, stop, option)`` (``stop`` exclusive).

        Under ``boundary="switch"`` two consecutive segments may share their option.
        """
        L = int(self.lengths[index])
        starts = [0, *self.boundaries[index], L]
        opts = self.options[index].tolist()
        return [(a, b, opts[a]) for a, b in zip(starts[:-1], starts[1:])]

    def to_dict(self) -> dict[str, np.ndarray]:
        """NumPy arrays of every tensor (for :func:`numpy.savez`)."""
        return {
            "options": self.options.cpu().numpy(),
            "boundaries": self.boundary_mask.cpu().numpy(),
            "posterior": self.posterior.cpu().numpy(),
            "switch_probability": self.switch_probability.cpu().numpy(),
            "log_likelihood": self.log_likelihood.cpu().numpy(),
            "lengths": self.lengths.cpu().numpy(),
        }


def segment(
    trajectories: TensorDictBase | Sequence[TensorDictBase],
    options: TensorDictModuleBase | DiscoveryResult,
    meta_control: TensorDictModuleBase | None = None,
    *,
    method: str = "viterbi",
    boundary: str = "change",
    threshold: float = 0.5,
    action_space: str = "auto",
    action_key: NestedKey = "action",
    mask_key: NestedKey = _MASK,
    terminal_key: NestedKey = ("next", "terminated"),
    batch_size: int | None = 256,
) -> Segmentation:
    """Segments trajectories into the options that most likely produced them.

    The exact posterior of the options' latent chain (:func:`~torchrl_options.forward_backward`) gives each
    step's option marginals ``u`` and the probability that an option starts there; the option sequence is then
    either the jointly most likely one (``method="viterbi"``, :func:`~torchrl_options.viterbi`: a coherent
    sequence, what the paper's figure 5 shows) or the per-step most likely option (``method="posterior"``).

    Boundaries (steps ``t >= 1`` where a segment starts) follow ``boundary``:

    - ``"change"`` (default): where the option label changes, what a picture of the segmentation shows;
    - ``"switch"``: where an option starts, including an option restarting itself: the Viterbi switches
      ``b_t`` (``method="viterbi"``) or ``P(b_t = 1 | trajectory) > threshold`` (``method="posterior"``).

    Args:
        trajectories: a ``[B, T]`` tensordict in :class:`~torchrl_options.DDOLoss`'s layout (``observation``,
            ``("next", "observation")``, ``action``, ``("collector", "mask")``), one ``[T]`` trajectory or a list
            of them (see :func:`~torchrl_options.as_trajectory_batch`).
        options: the options module (or a :class:`~torchrl_options.DiscoveryResult`, whose meta-control is used).
        meta_control (optional): the meta-control module; ``None``: uniform, or the result's.

    Keyword Args:
        method (str): ``"viterbi"`` (default) or ``"posterior"``.
        boundary (str): ``"change"`` (default) or ``"switch"``.
        threshold (float): for ``method="posterior"`` with ``boundary="switch"``.
        action_space (str): ``"auto"``, ``"categorical"`` or ``"continuous"``.
        action_key, mask_key, terminal_key (NestedKey): entries read, as in :class:`~torchrl_options.DDOLoss`.
        batch_size (int, optional): trajectories per forward pass (memory); ``None``: all at once.

    Returns:
        Segmentation: options, boundaries, posterior, boundary probabilities, log-likelihoods and lengths.

    Examples:
        >>> import torch
        >>> from torchrl_options import discover_options
        >>> from torchrl_options.segmentation import segment
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(8, 40, seed=0)
        >>> options = discover_options(data, 2, num_cells=8, num_iterations=10, lr=0.05, seed=0, progress=False)
        >>> seg = segment(data, options)
        >>> seg.options.shape, seg.posterior.shape, seg.lengths.tolist()[:3]
        (torch.Size([8, 40]), torch.Size([8, 40, 2]), [40, 40, 40])
        >>> seg.segments(0)[0][0]  # the first segment starts at step 0
        0
    """
    if method not in ("viterbi", "posterior"):
        raise ValueError(f"method must be 'viterbi' or 'posterior', got {method!r}.")
    if boundary not in ("change", "switch"):
        raise ValueError(f"boundary must be 'change' or 'switch', got {boundary!r}.")
    check_number(threshold, "threshold", lo=0.0, hi=1.0)
    check_int(batch_size, "batch_size", minimum=1, allow_none=True)
    if isinstance(options, DiscoveryResult):
        meta_control = options.meta_control if meta_control is None else meta_control
        options = options.options
    if meta_control is not None and not isinstance(meta_control, TensorDictModuleBase):
        raise TypeError(f"meta_control must be None or a TensorDictModuleBase, got {type(meta_control).__name__}.")
    data = as_trajectory_batch(trajectories, mask_key=mask_key)
    check_step_data(data, obs_keys=[], action_key=action_key, action_space=action_space, mask_key=mask_key, terminal_key=terminal_key)  # fmt: skip
    check_options_module(options, data, None, action_space=action_space)
    loss = DDOLoss(options, meta_control, action_space=action_space)
    loss.set_keys(action=action_key, mask=mask_key, terminal=terminal_key)
    loss.loss_mask_key = None  # the valid steps are mask_key's alone
    B = data.batch_size[0]
    step = B if not batch_size else int(batch_size)
    parts = []
    with torch.no_grad():
        for start in range(0, B, step):
            chunk = data[start : start + step]
            p = loss.log_probabilities(chunk)
            args = (p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"], p["terminal"])
            fb = forward_backward(*args)
            mask = p["mask"]
            if method == "viterbi":
                vit = viterbi(*args)
                opts, switches = vit.options, vit.switches
            else:
                opts = most_likely_options(fb.u, mask)
                switches = fb.v.sum(-1) > threshold
            switch_prob = torch.where(mask, fb.v.sum(-1), 0.0)
            if boundary == "change":
                bounds = boundaries_from_options(opts, mask)
            else:
                bounds = switches & mask
                bounds[:, 0] = False
            parts.append((opts, bounds, fb.u * mask.unsqueeze(-1), switch_prob, fb.log_likelihood, mask.sum(1)))
    opts, bounds, u, sp, ll, lengths = (torch.cat(x, 0) for x in zip(*parts))
    return Segmentation(
        options=opts, boundary_mask=bounds, posterior=u, switch_probability=sp, log_likelihood=ll, lengths=lengths,
        method=method, boundary=boundary,
    )
