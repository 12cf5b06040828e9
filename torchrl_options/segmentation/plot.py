"""A picture of a segmentation like figure 5 of Fox et al. (2017): one row per trajectory, coloured by option,
reference boundaries marked with crosses. Needs matplotlib (the ``recipes`` extra), imported on use."""
from __future__ import annotations

import importlib.util
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from torchrl_options.checks import check_int
from torchrl_options.segmentation.metrics import as_boundary_lists

__all__ = ["plot_segmentation"]


def plot_segmentation(
    options: torch.Tensor | np.ndarray,
    reference: torch.Tensor | np.ndarray | Sequence[Sequence[int]] | None = None,
    *,
    lengths: torch.Tensor | np.ndarray | Sequence[int] | None = None,
    num_options: int | None = None,
    max_trajectories: int | None = 10,
    title: str | None = None,
    option_names: Sequence[str] | None = None,
    path: str | Path | None = None,
    ax=None,
):
    """Draws trajectories as rows of steps coloured by their option, with reference boundaries as crosses.

    Args:
        options: ``[B, T]`` option of each step, ``-1`` (or beyond ``lengths``) on padding (drawn white).
        reference: reference boundaries, ``[B, T]`` booleans or a list of step lists (drawn as ``x`` above the
            rows, at the step where a segment starts; ``t = 0`` is not drawn).

    Keyword Args:
        lengths: ``[B]`` valid steps; default: the non-negative entries of ``options``.
        num_options (int, optional): K, for the colours; default ``max(options) + 1``.
        max_trajectories (int, optional): draw the first this many rows (the paper shows 10). ``None``: all.
        title (str, optional): the axes title; default says how many trajectories and options.
        option_names (list of str, optional): legend labels; default ``"option k"``.
        path (str or Path, optional): save the figure there (e.g. ``segmentation.png``).
        ax (matplotlib Axes, optional): draw into it instead of a new figure.

    Returns:
        The matplotlib ``Figure`` (in a new figure, a caption under the legend says what the colours and crosses
        are).

    Examples:
        >>> import torch
        >>> fig = plot_segmentation(torch.tensor([[0, 0, 1, 1, 2], [1, 1, 1, 0, -1]]), [[2, 4], [3]])
        >>> len(fig.axes)
        1
        >>> import matplotlib.pyplot as plt
        >>> plt.close(fig)
    """
    if importlib.util.find_spec("matplotlib") is None:
        raise ImportError("plot_segmentation needs matplotlib: pip install matplotlib")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    check_int(max_trajectories, "max_trajectories", minimum=1, allow_none=True)
    check_int(num_options, "num_options", minimum=1, allow_none=True)
    opts = np.asarray(options.detach().cpu() if isinstance(options, torch.Tensor) else options).astype(np.int64)
    if opts.ndim != 2:
        raise ValueError(f"options must be [B, T], got shape {opts.shape}.")
    B, T = opts.shape
    if lengths is None:
        lens = (opts >= 0).sum(1)
    else:
        lens = np.asarray(lengths.cpu() if isinstance(lengths, torch.Tensor) else lengths).reshape(-1)
    valid = (np.arange(T)[None] < lens[:, None]) & (opts >= 0)
    K = int(num_options) if num_options is not None else int(max(opts.max(), 0)) + 1
    rows = B if max_trajectories is None else min(B, int(max_trajectories))
    T_show = int(lens[:rows].max()) if rows else T

    base = plt.get_cmap("tab10" if K <= 10 else "tab20")
    colors = [base(i % base.N) for i in range(K)]
    image = np.ma.masked_array(opts[:rows, :T_show], ~valid[:rows, :T_show])
    cmap = ListedColormap(colors).with_extremes(bad="white")
    own_figure = ax is None
    if own_figure:
        fig, ax = plt.subplots(figsize=(10, 0.45 * rows + 2.0))
    else:
        fig = ax.figure
    ax.imshow(image, aspect="auto", interpolation="nearest", cmap=cmap, vmin=-0.5, vmax=K - 0.5,
              extent=(-0.5, T_show - 0.5, rows - 0.5, -0.5))
    if reference is not None:
        ref = as_boundary_lists(reference, lens, name="reference")
        xs = [t for i in range(rows) for t in ref[i]]
        ys = [i - 0.38 for i in range(rows) for _ in ref[i]]
        ax.scatter(np.asarray(xs) - 0.5, ys, marker="x", color="black", s=28, linewidths=1.2, zorder=3,
                   label="reference boundary")
    ax.set_yticks(range(rows))
    ax.set_yticklabels([str(i) for i in range(rows)])
    ax.set_ylabel("trajectory")
    ax.set_xlabel("step")
    ax.set_xlim(-0.5, T_show - 0.5)
    ax.set_ylim(rows - 0.5, -0.9)
    names = list(option_names) if option_names is not None else [f"option {k}" for k in range(K)]
    handles = [Patch(color=colors[k], label=names[k]) for k in range(K)]
    if reference is not None:
        handles.append(ax.collections[-1])
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.12 if rows > 3 else -0.3),
              ncol=min(len(handles), 6), frameon=False, fontsize=8)
    ax.set_title(title or f"Segmentation of {rows} trajectories into {K} options")
    if own_figure:  # a caption under the legend says what the picture shows
        caption = (
            "Each row is one trajectory, each cell one step, coloured by the option the segmentation assigns to it "
            "(white: padding after the trajectory's end)."
        )
        if reference is not None:
            caption += " Crosses: the reference boundaries (a new segment starts at that step)."
        fig.text(0.01, 0.01, "\n".join(textwrap.wrap(caption, 150)), fontsize=8, va="bottom", ha="left")
        fig.tight_layout(rect=(0, 0.6 / fig.get_figheight(), 1, 1))
    else:
        fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
