"""Pictures of options: trajectories until termination and termination maps (figures 1 and 6)."""
import cv2
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from torchrl_options import OptionHierarchy, OptionsMLP
from torchrl_options.envs import GridWorldEnv
from torchrl_options.experiments.option_pictures import (
    draw_hierarchy,
    draw_options,
    option_trajectories,
    option_video,
    termination_map,
)

from _figures import assert_explained, caption, legend_labels, texts


class _GoDown(torch.nn.Module):
    """Two options: option 0 always moves down and never stops by itself; option 1 stops at once."""

    def forward(self, obs):
        logits = torch.full((*obs.shape[:-1], 2, 4), -20.0)
        logits[..., 0, 2] = 20.0
        logits[..., 1, 0] = 20.0
        term = torch.tensor([-20.0, 20.0]).expand(*obs.shape[:-1], 2)
        return logits, term


def _options():
    module = TensorDictModule(_GoDown(), ["observation"], ["option_logits", "termination_logits"])
    module.num_options = 2
    return module


def test_trajectories_follow_the_option_until_it_terminates():
    env = GridWorldEnv("four-rooms", noise=0.0)
    paths = option_trajectories(_options(), env, num_starts=5, max_length=12, seed=0)
    assert len(paths) == 2 and all(len(p) == 5 for p in paths)
    for path in paths[0]:  # straight down, never terminated: max_length steps
        assert len(path) == 13 and np.all(np.diff(path[:, 1]) == 0) and np.all(np.diff(path[:, 0]) >= 0)
    for path in paths[1]:  # terminates after its first step
        assert len(path) == 2


def test_termination_map_is_a_probability_per_free_cell():
    env = GridWorldEnv("four-rooms")
    probs = termination_map(OptionsMLP(4, 4, 3), env, target_pos=(13, 9))
    assert probs.shape == (3, env.grid.num_free)
    assert bool(((probs > 0) & (probs < 1)).all())
    fixed = termination_map(_options(), env)
    assert torch.allclose(fixed[0], torch.zeros(env.grid.num_free), atol=1e-6)


def test_draw_options_writes_one_explained_png(tmp_path):
    path = tmp_path / "options.png"
    fig = draw_options(_options(), {"grid": "four-rooms"}, path, cell_size=10, target_pos=(13, 9), title="my run")
    read = cv2.imread(str(path))
    assert read is not None and read.shape[0] > 200 and read.shape[1] > 600
    assert_explained(fig)
    titles = [ax.get_title() for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert titles == ["every option, 3 starts each", "option 0: termination", "option 1: termination"]
    [bar] = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bar.get_ylabel() == "termination probability"
    assert legend_labels(fig)[:3] == ["option 0", "option 1", "start"]
    text = caption(fig)
    assert "3 uniformly random start cells" in text and "(13, 9)" in text and "red: 1" in text
    assert "my run" in texts(fig)


def test_draw_hierarchy_writes_one_explained_png(tmp_path):
    h = OptionHierarchy(4, [OptionsMLP(4, 4, 2), OptionsMLP(4, 6, 2)])
    fig = draw_hierarchy(h, {"grid": "four-rooms"}, tmp_path / "h.png", num_starts=1, max_length=4, cell_size=4)
    assert cv2.imread(str(tmp_path / "h.png")) is not None
    assert_explained(fig)
    assert legend_labels(fig)[:3] == ["level-1 option 0", "level-1 option 1", "primitive action"]
    assert "2-level hierarchy" in caption(fig)


def test_option_video_plays_every_trajectory(tmp_path):
    path = tmp_path / "options.avi"
    env = GridWorldEnv("four-rooms", noise=0.0)
    n = option_video(_options(), env, path, num_starts=2, max_length=6, cell_size=8, target_pos=(13, 9))
    # option 0 walks down without stopping (7 cells), option 1 stops after one step (2 cells); 2 starts each
    paths = option_trajectories(_options(), env, num_starts=2, max_length=6, target_pos=(13, 9))
    assert n == sum(len(p) for option_paths in paths for p in option_paths) == 2 * 7 + 2 * 2
    video = cv2.VideoCapture(str(path))
    assert video.isOpened() and int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == n
    ok, frame = video.read()
    assert ok and frame.shape[0] > 15 * 8 and frame.shape[1] == 11 * 8  # a caption band above the map
    count = 1
    while video.read()[0]:
        count += 1
    assert count == n
    with pytest.raises(ValueError, match="num_starts >= 1"):
        option_video(_options(), env, tmp_path / "x.avi", num_starts=0)
