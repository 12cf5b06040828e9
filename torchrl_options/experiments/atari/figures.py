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
    for each option its longest segment as ``option<h>.png`` (``strip_frames`` frames side by side) and
    ``option<h>.avi`` (OpenCV), plus ``labels.json`` with the per-step labels.
    """
    import cv2

    from torchrl_options.envs.render import write_video
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
        cv2.imwrite(png, cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
        write_video(segment, os.path.join(out_dir, f"option{h}.avi"), fps=fps)
        written += [png, os.path.join(out_dir, f"option{h}.avi")]
    with open(os.path.join(out_dir, "labels.json"), "w") as f:
        json.dump({"game": game, "labels": labels, "usage": [labels.count(h) for h in range(k)]}, f)
    return written
