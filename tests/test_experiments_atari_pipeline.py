"""The Atari pipeline's pieces that need no emulator: the lock that makes the cells of a seed share phases 1 and 2
(a portable file lock, no ``fcntl``). The pipeline end to end is in ``tests/test_recipe_atari.py``."""
import subprocess
import sys
import textwrap

import pytest
from filelock import Timeout

from torchrl_options.experiments.atari import pipeline
from torchrl_options.experiments.atari.pipeline import _seed_lock


def test_pipeline_does_not_need_fcntl():
    assert not hasattr(pipeline, "fcntl")


def test_seed_lock_excludes_another_process(tmp_path):
    """Another process (here a bare one, so that it starts fast) locking ``<seed_dir>/.lock`` waits."""
    code = textwrap.dedent(f"""
        from filelock import FileLock, Timeout
        try:
            FileLock({str(tmp_path / ".lock")!r}).acquire(timeout=0.1)
        except Timeout:
            print("waited")
        else:
            print("acquired")
    """)
    with _seed_lock(str(tmp_path)):
        held = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    free = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert (held.strip(), free.strip()) == ("waited", "acquired")


def test_seed_lock_excludes_another_holder_in_the_process(tmp_path):
    with _seed_lock(str(tmp_path)):
        with pytest.raises(Timeout):
            _seed_lock(str(tmp_path)).acquire(timeout=0.05)
    with _seed_lock(str(tmp_path)):
        pass


def test_option_frame_strip_explains_itself(tmp_path):
    pytest.importorskip("matplotlib")
    import numpy as np
    from _figures import caption

    from torchrl_options.experiments.atari.figures import _strip_figure

    strip = np.zeros((210, 3 * 160, 3), dtype=np.uint8)
    fig = _strip_figure(strip, [4, 6, 9], 1, 3, (4, 10), 12, 40, "Seaquest", 0, str(tmp_path / "option1.png"))
    assert (tmp_path / "option1.png").read_bytes()[:4] == b"\x89PNG"
    [ax] = fig.axes
    assert ax.get_title() == "Seaquest: option 1 of 3, its longest stretch as the most likely option"
    assert [t.get_text() for t in ax.get_xticklabels()] == ["4", "6", "9"] and ax.get_ylabel()
    assert "steps 4 to 9" in caption(fig) and "most likely at 12 of the 40 steps" in caption(fig)


def test_ddo_starts_one_is_the_kept_protocol_and_defaults_a_factory():
    """``ddo_starts="one"`` (the default, every kept run): one one-hot network drawn from the seed and one start;
    ``"defaults"``: a factory of fresh networks, so that discovery gets its default starts."""
    import torch
    from tensordict import TensorDict

    from torchrl_options import discover_options
    from torchrl_options.experiments.atari.config import AtariConfig
    from torchrl_options.experiments.atari.pipeline import _ddo_starts
    from torchrl_options.modules import OneHotByteOptions

    assert AtariConfig().ddo_starts == "one"
    config = AtariConfig(options_num_cells=(4,))
    one = _ddo_starts(config, 6, 3, 2, seed=0)
    again = _ddo_starts(config, 6, 3, 2, seed=0)
    assert one["restarts"] == 1 and isinstance(one["options"], OneHotByteOptions)
    assert all(torch.equal(a, b) for a, b in zip(one["options"].parameters(), again["options"].parameters()))
    assert _ddo_starts(AtariConfig(option_encoding="bytes"), 6, 3, 2, seed=0) == {"options": None, "restarts": 1}

    defaults = _ddo_starts(AtariConfig(options_num_cells=(4,), ddo_starts="defaults"), 6, 3, 2, seed=0)
    factory = defaults.pop("options_factory")
    assert defaults == {} and isinstance(factory(), OneHotByteOptions)
    a, b = factory().state_dict(), factory().state_dict()
    assert not torch.equal(a["embedding.weight"], b["embedding.weight"])  # fresh at each call
    g = torch.Generator().manual_seed(0)
    ram = torch.randint(0, 256, (4, 11, 6), generator=g).float() / 255  # the RAM as the env gives it
    demos = TensorDict({"observation": ram[:, :-1], "action": torch.randint(3, (4, 10), generator=g),
                        "next": {"observation": ram[:, 1:]}}, [4, 10])  # fmt: skip
    result = discover_options(demos, 2, options_factory=factory, num_actions=3, num_iterations=12, restart_iterations=2,
                              tol=None, seed=0, progress=False, return_info=True)  # fmt: skip
    assert len(result.restart_log_likelihoods) == 6  # the default segment starts
    assert AtariConfig.from_dict({"ddo_starts": "defaults"}).ddo_starts == "defaults"


def test_ddo_usage_floor_reaches_discovery_and_is_checked_when_read(monkeypatch, tmp_path):
    """``ddo_usage_floor`` (default ``None``, every kept run) is handed to ``discover_options(usage_floor=...)``
    by phase 2, and a value outside ``(0, 1)`` is refused when the settings are read, naming the setting."""
    import pytest
    import torch
    from tensordict import TensorDict

    import torchrl_options.discovery as discovery
    from torchrl_options.experiments.atari import pipeline
    from torchrl_options.experiments.atari.config import AtariConfig

    assert AtariConfig().ddo_usage_floor is None
    with pytest.raises(ValueError, match=r"ddo_usage_floor must be a share of the uniform usage 1/K in \(0, 1\), got 1.5"):
        AtariConfig.from_dict({"ddo_usage_floor": 1.5})
    seen = {}

    def fake_discover(demos, **kwargs):
        seen.update(kwargs)
        raise RuntimeError("stop here")

    g = torch.Generator().manual_seed(0)
    demo = TensorDict({"observation": torch.rand(5, 6, generator=g), "action": torch.zeros(5, dtype=torch.long),
                       "next": {"observation": torch.rand(5, 6, generator=g), "done": torch.zeros(5, 1, dtype=torch.bool),
                                "terminated": torch.zeros(5, 1, dtype=torch.bool), "reward": torch.zeros(5, 1)}}, [5])  # fmt: skip
    monkeypatch.setattr(discovery, "discover_options", fake_discover)
    monkeypatch.setattr(pipeline, "_greedy_rollouts", lambda *args, **kwargs: [demo])
    monkeypatch.setattr(pipeline, "_num_actions", lambda game, config: 3)
    config = AtariConfig(options_num_cells=(4,), ddo_usage_floor=0.5, num_options=2)
    with pytest.raises(RuntimeError, match="stop here"):
        pipeline._phase2("Pong", config, 0, str(tmp_path), agent=None)
    assert seen["usage_floor"] == 0.5
