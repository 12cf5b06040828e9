"""Recipe settings checked before any work starts: a bad value stops the run at once with one line naming the
setting and what it accepts (``python recipes/four_rooms.py episodes=-5`` ends in a second, not after DDO).

:func:`check_gridworld_settings` covers every key of the GridWorld recipes (``recipes/config/*rooms*.yaml``);
the Atari recipe's ``atari`` section is checked by :class:`~torchrl_options.experiments.atari.AtariConfig` and its
own keys by :func:`check_atari_recipe_settings`.
"""
from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

__all__ = ["SettingError", "check_gridworld_settings", "check_atari_recipe_settings", "check_segment_settings"]


class SettingError(ValueError):
    """A recipe setting out of range: the message names it (dotted, as on the command line) and what it accepts."""


def _int(cfg: Mapping[str, Any], key: str, name: str, minimum: int, allow_none: bool = False) -> None:
    value = cfg.get(key) if isinstance(cfg, Mapping) else None
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        none = " (or null)" if allow_none else ""
        raise SettingError(f"{name} must be an int >= {minimum}{none}, got {value!r}.")


def _number(cfg: Mapping[str, Any], key: str, name: str, lo: float, hi: float, lo_open: bool = False) -> None:
    value = cfg.get(key)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and (lo < value if lo_open else lo <= value)
    if not ok or not value <= hi:
        interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise SettingError(f"{name} must be a number in {interval}, got {value!r}.")


def _choice(value: Any, name: str, allowed: tuple) -> None:
    if value not in allowed:
        raise SettingError(f"{name} must be one of {list(allowed)}, got {value!r}.")


def _section(cfg: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    value = cfg.get(key)
    if not isinstance(value, Mapping):
        raise SettingError(f"{key} must be a section (a mapping of settings), got {value!r}.")
    return value


def _names(value: Any, name: str, known: Mapping[str, Any], what: str) -> None:
    if isinstance(value, str) or not isinstance(value, (list, tuple)) or not value:
        raise SettingError(f"{name} must be a non-empty list of {what}, got {value!r}.")
    unknown = [v for v in value if v not in known]
    if unknown:
        raise SettingError(f"{name}: unknown {what} {unknown}; defined: {sorted(known)}.")


def _seeds(value: Any) -> None:
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        if value < 1:
            raise SettingError(f"seeds must be a count >= 1 or a list of ints >= 0, got {value!r}.")
        return
    if not isinstance(value, (list, tuple)) or not value or not all(
        isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 0 for s in value
    ):
        raise SettingError(f"seeds must be a count >= 1 or a non-empty list of ints >= 0, got {value!r}.")
    if len(set(value)) != len(value):
        raise SettingError(f"seeds must not repeat a seed, got {list(value)}.")


def _sweep(cfg: Mapping[str, Any], prefix: str = "") -> None:
    _choice(cfg.get("backend", "serial"), f"{prefix}backend", ("serial", "local", "ray"))
    _int(cfg, "num_workers", f"{prefix}num_workers", 1, allow_none=True)


def check_gridworld_settings(cfg: Mapping[str, Any]) -> None:
    """Checks every setting of a GridWorld recipe (a plain nested mapping) before anything runs.

    Raises:
        SettingError: (a ``ValueError``) naming the first bad setting, e.g. ``episodes must be an int >= 1, got -5.``

    Examples:
        >>> check_gridworld_settings({"episodes": -5})
        Traceback (most recent call last):
        ...
        torchrl_options.experiments.validation.SettingError: episodes must be an int >= 1, got -5.
    """
    _int(cfg, "episodes", "episodes", 1)
    _seeds(cfg.get("seeds"))
    _int(cfg, "num_envs", "num_envs", 1)
    _int(cfg, "checkpoint_every", "checkpoint_every", 1)
    _int(cfg, "stop_after_cells", "stop_after_cells", 0, allow_none=True)
    _sweep(cfg)
    if not cfg.get("out_dir"):
        raise SettingError(f"out_dir must be a folder name, got {cfg.get('out_dir')!r}.")
    settings, conditions = _section(cfg, "settings"), _section(cfg, "conditions")
    _names(cfg.get("settings_to_run"), "settings_to_run", settings, "settings")
    _names(cfg.get("conditions_to_run"), "conditions_to_run", conditions, "conditions")
    algorithm = cfg.get("algorithm", "dqn")
    _choice(algorithm, "algorithm", ("dqn", "ppo"))
    for name in cfg["settings_to_run"]:
        setting = _section(settings, name)
        if algorithm == "ppo" and isinstance(setting, Mapping) and setting.get("source") == "greedy":
            raise SettingError(
                f"settings_to_run: {name!r} pre-trains a DQN agent (source: greedy); algorithm=ppo runs supervised "
                "settings only."
            )
        _choice(setting.get("source"), f"settings.{name}.source", ("supervisor", "greedy"))
        if setting["source"] == "greedy":
            _int(setting, "pretrain_episodes", f"settings.{name}.pretrain_episodes", 1)
            greedy = _section(setting, "greedy")
            _int(greedy, "num", f"settings.{name}.greedy.num", 1)
            _int(greedy, "length", f"settings.{name}.greedy.length", 1)
            if greedy.get("epsilon", 0.0) != "agent":
                _number({"epsilon": greedy.get("epsilon", 0.0)}, "epsilon", f"settings.{name}.greedy.epsilon (or 'agent')", 0, 1)
            _choice(greedy.get("keep", "all"), f"settings.{name}.greedy.keep", ("all", "rewarded"))
    discovery = _section(cfg, "discovery")
    _int(discovery, "num_options", "discovery.num_options", 1)
    _choice(discovery.get("preset", "paper"), "discovery.preset", ("paper", "defaults"))
    _int(discovery, "num_iterations", "discovery.num_iterations", 0, allow_none=True)
    _int(discovery, "m_steps", "discovery.m_steps", 1, allow_none=True)
    _int(discovery, "restarts", "discovery.restarts", 1, allow_none=True)
    _int(discovery, "upper_level_iterations", "discovery.upper_level_iterations", 0, allow_none=True)
    _int(discovery, "batch_size", "discovery.batch_size", 1, allow_none=True)
    if discovery.get("lr") is not None:
        _number(discovery, "lr", "discovery.lr", 0, float("inf"), lo_open=True)
    if discovery.get("tol") is not None:
        _number(discovery, "tol", "discovery.tol", 0, float("inf"))
    _choice(discovery.get("init") or "random", "discovery.init", ("random", "kmeans", "segments", "auto"))
    from torchrl_options.modules._features import activation_class

    try:
        activation_class(discovery.get("activation") or "tanh")
    except (ValueError, TypeError) as err:
        raise SettingError(f"discovery.{err}") from None
    cells = discovery.get("num_cells") or 2
    if not (isinstance(cells, int) and not isinstance(cells, bool) and cells >= 1) and not (
        isinstance(cells, (list, tuple)) and all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in cells)
    ):
        raise SettingError(f"discovery.num_cells must be an int >= 1 or a list of them, got {cells!r}.")
    for name in cfg["conditions_to_run"]:
        condition = _section(conditions, name)
        _choice(condition.get("mode"), f"conditions.{name}.mode", ("actions", "options", "both"))
        _choice(condition.get("meta_control", "uniform"), f"conditions.{name}.meta_control", ("uniform", "learned"))
        _int(condition, "num_options", f"conditions.{name}.num_options", 1, allow_none=True)
        _int(condition, "levels", f"conditions.{name}.levels", 1, allow_none=True)
        _int(condition, "episodes", f"conditions.{name}.episodes", 1, allow_none=True)
    demos = cfg.get("demos")
    if demos is not None:
        _int(demos, "num", "demos.num", 1)
        _int(demos, "length", "demos.length", 1)
    summary = cfg.get("summary") or {}
    for key in ("final_window", "smooth_window", "curve_window", "reach_window"):
        _int(summary, key, f"summary.{key}", 1, allow_none=True)
    pictures = cfg.get("pictures") or {}
    for key in ("num_starts", "max_length"):
        _int(pictures, key, f"pictures.{key}", 1, allow_none=True)
    _check_env(cfg)
    if cfg.get("algorithm", "dqn") == "ppo":
        _check_ppo(cfg)
    else:
        _check_dqn(cfg)


def _check_env(cfg: Mapping[str, Any]) -> None:
    """Builds one env of the recipe's ``env`` section (and the demonstrations' overrides): the env's own checks
    name the bad argument."""
    from torchrl_options.experiments.gridworld import make_env

    env_cfg = _section(cfg, "env")
    _int(env_cfg, "max_steps", "env.max_steps", 1, allow_none=True)
    if "noise" in env_cfg:
        _number(env_cfg, "noise", "env.noise", 0.0, 1.0)
    for name, section in (("env", env_cfg), ("demos.env", {**dict(env_cfg), **dict((cfg.get("demos") or {}).get("env") or {})})):
        try:
            make_env(section, 1, 0).close()
        except (ValueError, TypeError, KeyError) as err:
            raise SettingError(f"{name}: {err}") from None


def _check_dqn(cfg: Mapping[str, Any]) -> None:
    from torchrl_options.agents.dqn import OptionsDQNConfig

    dqn = dict(_section(cfg, "dqn"))
    dqn["hidden_sizes"] = tuple(dqn.get("hidden_sizes", (2,))) if isinstance(dqn.get("hidden_sizes", (2,)), (list, tuple)) else dqn["hidden_sizes"]
    try:
        OptionsDQNConfig(**dqn)
    except TypeError as err:
        if "unexpected keyword" in str(err):
            raise SettingError(f"dqn: unknown setting ({str(err).split('argument')[-1].strip()}).") from None
        raise SettingError(f"dqn.{err}") from None
    except ValueError as err:
        raise SettingError(f"dqn.{err}") from None
    _check_frames_per_batch(cfg, "dqn")


def _check_ppo(cfg: Mapping[str, Any]) -> None:
    from torchrl_options.agents.ppo import OptionsPPOConfig

    ppo = dict(_section(cfg, "ppo"))
    if isinstance(ppo.get("hidden_sizes"), (list, tuple)):
        ppo["hidden_sizes"] = tuple(ppo["hidden_sizes"])
    try:
        OptionsPPOConfig(**ppo)
    except TypeError as err:
        if "unexpected keyword" in str(err):
            raise SettingError(f"ppo: unknown setting ({str(err).split('argument')[-1].strip()}).") from None
        raise SettingError(f"ppo.{err}") from None
    except ValueError as err:
        raise SettingError(f"ppo.{err}") from None
    _check_frames_per_batch(cfg, "ppo")


def _check_frames_per_batch(cfg: Mapping[str, Any], section: str) -> None:
    """The recipes run ``num_envs`` grids in one batched env: a collector batch must be whole steps of all of them
    (the agents refuse it too, but only once a cell starts)."""
    frames, num_envs = cfg[section].get("frames_per_batch"), cfg.get("num_envs")
    if isinstance(frames, int) and isinstance(num_envs, int) and num_envs >= 1 and frames % num_envs:
        raise SettingError(
            f"{section}.frames_per_batch must be a multiple of num_envs ({num_envs}), got {frames}: a batch holds whole "
            "steps of every env."
        )


def check_atari_recipe_settings(cfg: Mapping[str, Any]) -> None:
    """The Atari recipe's own keys (its ``atari`` section is :class:`~torchrl_options.experiments.atari.AtariConfig`'s).

    Raises:
        SettingError: naming the first bad setting.
    """
    from torchrl_options.experiments.atari import AtariConfig, CONDITIONS

    from torchrl_options.envs.atari import ATARI_GAMES

    games = [cfg["game"]] if cfg.get("game") else cfg.get("games")
    if isinstance(games, str) or not isinstance(games, (list, tuple)) or not games:
        raise SettingError(f"games must be a non-empty list of games (or set game=...), got {games!r}.")
    for game in games:
        if not isinstance(game, str) or not game:
            raise SettingError(f"games: {game!r} is not a game name (e.g. one of {list(ATARI_GAMES)}).")
    _seeds(cfg.get("seeds"))
    conditions = cfg.get("conditions") or ["A", "H1"]
    for c in conditions:
        _choice(c, "conditions", tuple(CONDITIONS))
    for key in ("smooth_window", "final_window"):
        _int(cfg, key, key, 1, allow_none=True)
    _sweep(dict(cfg.get("sweep") or {}), "sweep.")
    _int(dict(cfg.get("sweep") or {}), "threads_per_worker", "sweep.threads_per_worker", 1, allow_none=True)
    try:
        config = AtariConfig.from_dict(dict(cfg.get("atari") or {}))
    except TypeError as err:
        raise SettingError(f"atari.{err}") from None
    except ValueError as err:
        raise SettingError(f"atari.{err}" if not str(err).startswith("unknown") else str(err)) from None
    suffixes = [c for c in conditions if c.startswith("H1") and "s" in c[2:]]
    if suffixes and config.discount_per != "step":
        raise SettingError(
            f"conditions {suffixes} learn option values from option suffixes, discounted per primitive step: they "
            f"need atari.discount_per=step, got {config.discount_per!r}."
        )


def check_segment_settings(cfg: Mapping[str, Any]) -> None:
    """The segmentation recipe's settings (``recipes/config/segment.yaml``).

    Raises:
        SettingError: naming the first bad setting.

    Examples:
        >>> check_segment_settings({"data": {"source": "continuous", "num_trajectories": 0}})
        Traceback (most recent call last):
        ...
        torchrl_options.experiments.validation.SettingError: data.num_trajectories must be an int >= 1, got 0.
    """
    data = _section(cfg, "data")
    _choice(data.get("source"), "data.source", ("continuous", "gridworld", "file"))
    _choice(data.get("format", "auto"), "data.format", ("auto", "npz", "hdf5", "tensordict"))
    if data["source"] == "file" and not data.get("path"):
        raise SettingError("data.source=file needs data.path=<file or directory>.")
    if data["source"] != "file":
        _int(data, "num_trajectories", "data.num_trajectories", 1)
        _int(data, "length", "data.length", 1, allow_none=True)
    _int(data, "seed", "data.seed", 0, allow_none=True)
    d = _section(cfg, "discovery")
    _int(d, "num_options", "discovery.num_options", 1, allow_none=True)
    _choice(d.get("action_space", "auto"), "discovery.action_space", ("auto", "categorical", "continuous"))
    _choice(d.get("meta_control", "uniform"), "discovery.meta_control", ("uniform", "learned"))
    _choice(d.get("init", "random"), "discovery.init", ("random", "kmeans"))
    cells = d.get("num_cells")
    if not isinstance(cells, (list, tuple)) or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in cells):
        raise SettingError(f"discovery.num_cells must be a list of ints >= 1, got {cells!r}.")
    _int(d, "num_iterations", "discovery.num_iterations", 0)
    _number(d, "lr", "discovery.lr", 0, float("inf"), lo_open=True)
    if d.get("init_scale") is not None:
        _number(d, "init_scale", "discovery.init_scale", 0, float("inf"), lo_open=True)
    _int(d, "batch_size", "discovery.batch_size", 1, allow_none=True)
    _int(d, "seed", "discovery.seed", 0, allow_none=True)
    s = _section(cfg, "segmentation")
    _choice(s.get("method"), "segmentation.method", ("viterbi", "posterior"))
    _choice(s.get("boundary"), "segmentation.boundary", ("change", "switch"))
    _int(s, "window", "segmentation.window", 0, allow_none=True)
    _int(s, "baseline_samples", "segmentation.baseline_samples", 1)
    _int(dict(cfg.get("plot") or {}), "max_trajectories", "plot.max_trajectories", 1)
    if not cfg.get("output_dir"):
        raise SettingError(f"output_dir must be a folder name, got {cfg.get('output_dir')!r}.")
