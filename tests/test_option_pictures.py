"""Pictures of options: trajectories until termination and termination maps (figures 1 and 6)."""
import cv2
import numpy as np
import torch
from tensordict.nn import TensorDictModule

from torchrl_options import OptionsMLP
from torchrl_options.envs import GridWorldEnv
from torchrl_options.experiments.option_pictures import draw_options, option_trajectories, termination_map


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


def test_draw_options_writes_one_png(tmp_path):
    path = tmp_path / "options.png"
    image = draw_options(_options(), {"grid": "four-rooms"}, path, cell_size=10, target_pos=(13, 9))
    assert image.shape == (150, 3 * 110 + 2 * 4, 3)
    read = cv2.imread(str(path))
    assert read is not None and read.shape == image.shape
    assert np.array_equal(cv2.cvtColor(read, cv2.COLOR_BGR2RGB), image)
