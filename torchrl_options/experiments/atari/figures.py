"""Figure 4 of the DDO paper for the Atari RAM experiment: where each discovered option is the most likely one,
as strips of frames and short videos."""
from __future__ import annotations

import json
import os

import numpy as np
import torch

from torchrl_options.experiments.atari.config import AtariConfig
from torchrl_options.experiments.atari.utils import _greedy_rollouts, _load_if, _make_agent

__all__ = ["write_option_frames"]


def agent_for_frames(game: str, config: AtariConfig, seed: int, seed_dir: str):
    """The phase-1 agent (whose greedy trajectories the options were discovered from)."""
    agent = _make_agent(game, config, seed, "actions")
    _load_if(agent, os.path.join(seed_dir, "phase1.pt"))
    return agent


def write_option_frames(agent, options, game: str, config: AtariConfig, seed: int, out_dir: str, *,
                        strip_frames: int = 6, fps: float = 15.0) -> list[str]:
    """Figure 4: for each option, a strip of frames and a short video of where it is the most likely one.

    Rolls out one greedy trajectory of the phase-1 agent with RGB rendering, labels every step with the
    posterior argmax option (forward-backward under the discovered options, uniform meta-control), and writes
    for each option its longest segment as ``option<h>.png`` (``strip_frames`` frames side by side, titled, the
    x axis naming each frame's step, a caption under it) and ``option<h>.avi`` (OpenCV, each frame captioned with
    the option and the step), plus ``labels.json`` with the per-step labels.
    """
    from torchrl_options.envs.render import write_video
    from torchrl_options.experiments.option_pictures import _caption_band
    from torchrl_options.experiments.plotting import _captioned_figure
    from torchrl_options.inference import forward_backward, most_likely_options
    from torchrl_options.objectives import DDOLoss

    os.makedirs(out_dir, exist_ok=True)
    trajs, screens = _greedy_rollouts(agent, game, config, seed, 1, config.option_frames_max_steps, render=True)
    traj, screens = trajs[0], screens[0]
    with torch.no_grad():
        p = DDOLoss(options).log_probabilities(traj.unsqueeze(0))
        fb = forward_backward(p["log_pi"], p["log_term"], p["log_cont"], p["log_eta"], p["mask"])
    labels = most_likely_options(fb.u)[0].tolist()
    written = []
    k = int(p["log_pi"].shape[-1])
    for h in range(k):
        best, start = (0, 0), None
        for t, lab in enumerate(labels + [-1]):
            if lab == h and start is None:
                start = t
            elif lab != h and start is not None:
                if t - start > best[1] - best[0]:
                    best = (start, t)
                start = None
        a, b = best
        if b <= a:
            continue
        segment = screens[a:b]
        picks = np.linspace(0, len(segment) - 1, num=min(strip_frames, len(segment))).round().astype(int)
        strip = np.concatenate([segment[i] for i in picks], axis=1)
        png = os.path.join(out_dir, f"option{h}.png")
        _strip_figure(strip, [a + int(i) for i in picks], h, k, (a, b), labels.count(h), len(labels), game, seed, png)
        captioned = [
            np.concatenate([_caption_band([f"option {h} of {k} most likely", f"step {a + t} of {len(labels)}"],
                                          frame.shape[1]), frame], axis=0)
            for t, frame in enumerate(segment)
        ]  # fmt: skip
        write_video(captioned, os.path.join(out_dir, f"option{h}.avi"), fps=fps)
        written += [png, os.path.join(out_dir, f"option{h}.avi")]
    with open(os.path.join(out_dir, "labels.json"), "w") as f:
        json.dump({"game": game, "labels": labels, "usage": [labels.count(h) for h in range(k)]}, f)
    return written


def _strip_figure(strip: np.ndarray, steps: list[int], h: int, k: int, span: tuple[int, int], usage: int,
                  length: int, game: str, seed: int, path: str):
    """``option<h>.png``: the strip of frames, titled, the x axis naming each frame's step, with a caption."""
    from torchrl_options.experiments.plotting import _captioned_figure

    height, width = strip.shape[:2]
    frame_w = width / len(steps)
    caption = (
        f"Frames of one greedy episode ({length} steps) of the phase-1 agent on {game} (seed {seed}). Every step is "
        f"labelled with its most likely option (the posterior of forward-backward under the {k} discovered options, "
        f"uniform meta-control); shown: {len(steps)} evenly spaced frames of the longest run of steps where option "
        f"{h} is the most likely (steps {span[0]} to {span[1] - 1}). Option {h} is the most likely at {usage} of the "
        f"{length} steps."
    )
    fig, _, axes = _captioned_figure(1, 1, (max(2.0 * len(steps), 4.0), 2.0 * height / frame_w + 0.8), caption)
    ax = axes[0, 0]
    ax.imshow(strip, interpolation="nearest")
    ax.set_xticks([frame_w * (i + 0.5) for i in range(len(steps))], [str(t) for t in steps])
    ax.set_xlabel("step of the episode (one frame each)")
    ax.set_ylabel("screen row (pixels)")
    ax.set_title(f"{game}: option {h} of {k}, its longest stretch as the most likely option")
    fig.savefig(path, dpi=100)
    return fig
