"""The settings of one discovery run (:class:`DiscoverySettings`), checked when they are made, and their defaults.

Every setting of :func:`~torchrl_options.discover_options` that is a plain value (numbers, strings, keys) lives in
one dataclass that Hydra's ``ConfigStore`` can hold, so a recipe's YAML can name them; what is code (a module, a
factory of modules, an optimizer factory, a scheduler factory) is given next to it
(:class:`~torchrl_options.discovery.stages.Networks`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from torchrl_options.checks import (
    check_bool,
    check_choice,
    check_int,
    check_nested_key,
    check_number,
    check_positive_number,
)

from torchrl_options.discovery.usage_floor import check_usage_floor

__all__ = [
    "ACTION_SPACES",
    "AUTO_RESTARTS",
    "CONTINUOUS_PATIENCE",
    "DEFAULT_PATIENCE",
    "DEFAULT_RESTARTS",
    "DiscoverySettings",
    "INITS",
    "META_CONTROLS",
    "PAPER_SETTINGS",
    "check_init_scale",
    "check_stopping_rule",
    "default_restarts",
    "obs_key_list",
]

DEFAULT_RESTARTS = 4
"""Starts drawn by :func:`~torchrl_options.discover_options` when ``restarts`` is left at ``None`` (and fresh modules
can be drawn)."""

INITS = ("random", "kmeans", "segments", "auto")
"""The values of ``discover_options(init=...)``; ``"auto"`` (the default) starts fresh modules from segments."""

AUTO_RESTARTS = 6
"""Starts drawn with ``init="auto"`` when ``restarts`` is left at ``None``: of every three, two segment starts
clustered by where the segments end and one clustered by their actions."""

DEFAULT_PATIENCE = 20
"""The stopping rule's window (iterations) of :func:`~torchrl_options.discover_options` for discrete actions when
``patience`` is left at ``None``."""

CONTINUOUS_PATIENCE = 100
"""The stopping rule's window for continuous actions (Gaussian options) when ``patience`` is left at ``None``: with
a window of 20 the planted suite's Gaussian fits stopped on a pause of the likelihood, up to 0.015 nats per step
below the truth's, and climbed past it when trained on."""

ACTION_SPACES = ("categorical", "continuous")
META_CONTROLS = ("uniform", "learned")

PAPER_SETTINGS: dict = dict(
    num_cells=2, termination_cells=2, activation="tanh", num_iterations=500, m_steps=1, lr=1e-2, restarts=1, tol=None,
    init="random",
)
"""The settings of the paper's four-rooms experiment (one hidden layer of 2 tanh units, plain Expectation-Gradient,
one start), as ``discover_options`` keyword arguments: ``discover_options(data, K, **PAPER_SETTINGS)``. The
GridWorld recipes use them; the defaults of :func:`~torchrl_options.discover_options` are chosen on the planted
suite instead."""


def check_stopping_rule(tol: Any, patience: Any) -> None:
    """Refuses a ``tol`` that is not ``None`` or a number ``>= 0`` (nats per step) and a ``patience`` that is not an
    int ``>= 1`` (iterations): the stopping rule of :func:`~torchrl_options.discovery.fit.converged_at`.

    Examples:
        >>> check_stopping_rule(1e-4, 20)
        >>> check_stopping_rule(-1.0, 20)
        Traceback (most recent call last):
        ...
        ValueError: tol must be a number >= 0, got -1.
    """
    check_number(tol, "tol", lo=0.0, allow_none=True)
    check_int(patience, "patience", minimum=1)


def check_init_scale(init_scale: Any, action_space: str) -> None:
    """``init_scale`` is ``None``, or a positive finite number with ``action_space="continuous"``."""
    if init_scale is None:
        return
    if action_space != "continuous":
        raise ValueError(
            f"init_scale sets the starting standard deviation of Gaussian options: it needs "
            f"action_space='continuous', got action_space={action_space!r} with init_scale={init_scale!r}."
        )
    check_positive_number(init_scale, "init_scale")


def obs_key_list(obs_keys: Any) -> list:
    """``obs_keys`` as a list of keys: one key (a str, or a tuple of str) becomes a one-element list; a list (as YAML
    gives it) holds keys, its nested keys as tuples or lists.

    Examples:
        >>> obs_key_list("observation"), obs_key_list(("agent", "obs")), obs_key_list(["pixels", ["agent", "obs"]])
        (['observation'], [('agent', 'obs')], ['pixels', ('agent', 'obs')])
    """
    keys = [obs_keys] if isinstance(obs_keys, (str, tuple)) else list(obs_keys)
    return [tuple(k) if isinstance(k, list) else k for k in keys]


def default_restarts(init: str, num_iterations: int, restart_iterations: int, fresh_modules: bool) -> int:
    """The starts of ``restarts=None``: :data:`AUTO_RESTARTS` (``init="auto"``) or :data:`DEFAULT_RESTARTS` short
    starts when fresh modules can be drawn for each and ``num_iterations`` leaves room for them, else one.

    Examples:
        >>> default_restarts("auto", 1000, 40, True), default_restarts("random", 1000, 40, True)
        (6, 4)
        >>> default_restarts("auto", 100, 40, True), default_restarts("auto", 1000, 40, False)
        (1, 1)
    """
    starts = AUTO_RESTARTS if init == "auto" else DEFAULT_RESTARTS
    return starts if fresh_modules and num_iterations >= starts * restart_iterations else 1


@dataclass
class DiscoverySettings:
    """The plain-valued settings of :func:`~torchrl_options.discover_options`, with its defaults, checked when made.

    The fields are the function's keyword arguments of the same names (see there for each one's meaning);
    ``discover_options(data, K, **kwargs)`` builds one and hands it to the stages of
    :mod:`~torchrl_options.discovery.stages`. Keys may come as YAML lists: ``action_key`` and ``trajectory_key``
    are turned into tuples, ``obs_keys`` into a list of keys (:func:`obs_key_list`). ``meta_control`` is
    ``"uniform"`` or ``"learned"``; a meta-control module is given with the modules instead. ``chunk_trajectories``,
    ``eval_trajectories`` and ``distributed`` concern trajectories streamed from a replay buffer only
    (:mod:`~torchrl_options.discovery.streaming`).

    With Hydra, register it as a structured config and build the settings from a YAML section::

        ConfigStore.instance().store(group="ddo", name="schema", node=DiscoverySettings)

    Examples:
        >>> settings = DiscoverySettings(4, num_cells="auto", action_key=["agent", "action"])
        >>> settings.num_options, settings.action_key, settings.patience
        (4, ('agent', 'action'), None)
        >>> settings.stopping_patience
        20
        >>> DiscoverySettings(4, init="spectral")
        Traceback (most recent call last):
        ...
        ValueError: init must be one of 'random', 'kmeans', 'segments', 'auto', got 'spectral'.
    """

    num_options: int
    meta_control: str = "uniform"
    num_actions: int | None = None
    action_space: str = "categorical"
    obs_keys: Any = "observation"
    action_key: Any = "action"
    num_cells: Any = 8
    termination_cells: Any = None
    activation: str = "tanh"
    architecture: str = "separate"
    init_scale: float | None = None
    init: str = "auto"
    num_iterations: int = 1000
    m_steps: int = 5
    tol: float | None = 1e-4
    patience: int | None = None
    restarts: int | None = None
    restart_iterations: int = 40
    batch_size: int | None = None
    lr: float = 0.03
    device: Any = None
    seed: int | None = None
    progress: bool = True
    trajectory_key: Any = ("collector", "traj_ids")
    log_every: int = 50
    desc: str = "DDO"
    split_merge: int = 0
    split_merge_iterations: int = 300
    chunk_trajectories: int | None = None
    eval_trajectories: int = 64
    distributed: bool = False
    usage_floor: float | None = None

    def __post_init__(self) -> None:
        for name in ("action_key", "trajectory_key"):
            value = getattr(self, name)
            setattr(self, name, check_nested_key(tuple(value) if isinstance(value, list) else value, name))
        check_int(self.num_options, "num_options", minimum=1)
        check_int(self.num_actions, "num_actions", minimum=1, allow_none=True)
        check_int(self.num_iterations, "num_iterations", minimum=0)
        check_int(self.m_steps, "m_steps", minimum=1)
        check_stopping_rule(self.tol, self.stopping_patience)
        check_choice(self.action_space, "action_space", ACTION_SPACES)
        check_init_scale(self.init_scale, self.action_space)
        if isinstance(self.num_cells, str) and self.num_cells != "auto":
            raise ValueError(f"num_cells must be an int, a sequence of ints or 'auto', got {self.num_cells!r}.")
        check_int(self.split_merge, "split_merge", minimum=0)
        check_int(self.split_merge_iterations, "split_merge_iterations", minimum=1)
        check_int(self.restarts, "restarts", minimum=1, allow_none=True)
        if self.init not in INITS:
            raise ValueError(f"init must be one of {', '.join(map(repr, INITS))}, got {self.init!r}.")
        if self.meta_control not in META_CONTROLS:
            raise ValueError(f"meta_control must be 'uniform', 'learned' or a module, got {self.meta_control!r}.")
        check_int(self.batch_size, "batch_size", minimum=1, allow_none=True)
        check_int(self.log_every, "log_every", minimum=0)
        check_int(self.chunk_trajectories, "chunk_trajectories", minimum=1, allow_none=True)
        check_int(self.eval_trajectories, "eval_trajectories", minimum=1)
        check_bool(self.distributed, "distributed")
        check_usage_floor(self.usage_floor)

    @property
    def stopping_patience(self) -> int:
        """``patience``, or its default for the action space when ``None``."""
        if self.patience is not None:
            return self.patience
        return CONTINUOUS_PATIENCE if self.action_space == "continuous" else DEFAULT_PATIENCE

    @property
    def obs_key_list(self) -> list:
        """``obs_keys`` as a list of keys (:func:`obs_key_list`)."""
        return obs_key_list(self.obs_keys)

    def replace(self, **changes: Any) -> DiscoverySettings:
        """A copy with ``changes`` (checked again)."""
        return dataclasses.replace(self, **changes)
