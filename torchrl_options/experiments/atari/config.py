"""The settings of one Atari RAM cell (:class:`AtariConfig`), checked when they are read, the recipe's Hydra
schema (:func:`store_atari_config`) and the check of its own keys (:func:`check_atari_recipe_settings`)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar

from torchrl_options.agents.dqn import DQNHyperParameters
from torchrl_options.checks import check_choice, check_int
from torchrl_options.experiments.atari.conditions import CONDITIONS
from torchrl_options.experiments.recipe_config import check_seeds, check_sweep

__all__ = ["AtariConfig", "check_atari_recipe_settings", "store_atari_config"]


@dataclass
class AtariConfig(DQNHyperParameters):
    """Settings of one Atari RAM cell: the schema of the ``atari`` section of ``recipes/config/atari_ram.yaml``
    (:func:`store_atari_config`). The DQN settings (``lr``, ``gamma``, ``batch_size``, ...) are the fields of
    :class:`~torchrl_options.agents.DQNHyperParameters`, which the agent's
    :class:`~torchrl_options.agents.OptionsDQNConfig` derives from too: declared and checked once, with the paper's
    defaults here; the other fields are the cell's own.

    Env: ``env_semantics="project"`` (default) builds the game from ``frame_skip``, ``repeat_action_probability``,
    ``noop_max``, ``episodic_life``, ``clip_rewards``, ``max_episode_steps`` (see
    :func:`~torchrl_options.envs.atari.make_atari_ram_env`); ``env_semantics="paper"`` ignores the first five and
    reproduces the authors' gym ``<Game>-ram-v0`` (:data:`~torchrl_options.envs.atari.PAPER_ENV_SETTINGS`: sticky
    actions 0.25, a frame skip drawn uniformly in 2-4 at every step, raw rewards, no no-op starts), with episodes
    cut at ``max_episode_steps`` steps, ``None`` giving the paper's 10,000 (a smaller cap: a shorter budget). ``ram_encoding`` is the Q-network's input layer: ``"one_hot"`` (the paper's 128 x 256) or
    ``"bytes"``. ``option_encoding`` the options networks': ``"one_hot"`` (default, the paper's:
    :class:`~torchrl_options.modules.OneHotByteOptions`, each byte one-hot, ``options_num_cells`` the widths after
    it) or ``"bytes"`` (an :class:`~torchrl_options.OptionsMLP` on ``bytes / 255``).

    Phases: ``phase1_episodes`` (DQN, actions), ``num_demonstrations`` greedy trajectories of at most
    ``demo_max_steps`` steps, DDO with ``num_options`` (``None``: the paper's count for the game) for
    ``ddo_iterations`` iterations of ``ddo_m_steps`` optimizer steps each (1: the paper's Expectation-Gradient;
    more: a generalised EM that fits the demonstrations much more closely for the same E-steps, see
    :func:`~torchrl_options.discover_options`), then ``phase3_episodes`` for each condition. The demonstrations'
    quality gate: ``demo_random_episodes`` episodes of a uniformly random policy on the same game (0: none); when the
    greedy demonstrations' mean return is no better than theirs, the demonstrator is recorded as degenerate
    (``phase2.json`` and ``summary.md``) and a warning is logged; the protocol runs on regardless, as the paper's.
    ``ddo_starts``: ``"one"`` (default; the paper's protocol and every kept run: one start from the options network
    drawn from the seed, every iteration run) or ``"defaults"``: the options network comes from a factory, a fresh one
    per start, and DDO gets :func:`~torchrl_options.discover_options`' default starts (``init="auto"``: 6 segment
    starts of 40 iterations selected by likelihood, when ``ddo_iterations >= 240``), still without the stopping
    rule. ``ddo_usage_floor``: ``None`` (default, every kept run) or a share of the uniform usage in ``(0, 1)``,
    :func:`~torchrl_options.discover_options`' ``usage_floor``: every option kept active on at least that share
    of ``1 / K`` of the demonstrations' steps during the fit (against the collapse to one option that copies the
    demonstrator).

    ``discount_per``: ``"step"`` (default, the SMDP target ``R + gamma^k max Q`` with rewards discounted inside an
    option) or ``"decision"`` (the authors' HDQN: an option's rewards summed undiscounted, one ``gamma`` per
    decision); see :class:`~torchrl_options.agents.DQNHyperParameters`.

    DQN (paper: epsilon 0.05, gamma 0.85, three dense tanh layers): the fields of
    :class:`~torchrl_options.agents.DQNHyperParameters` (``hidden_sizes``, ``gamma``, ``eps_init``, ``eps_end``,
    ``eps_annealing_frames``, ``lr``, ``batch_size``, ``buffer_size``, ``learning_starts``, ``frames_per_batch``,
    ``updates_per_batch``, ``hard_update_interval``, ``double_dqn``, ``device``), ``num_envs`` games
    batched in a ``SerialEnv`` (``ParallelEnv`` with ``parallel``; one gymnasium ``SyncVectorEnv`` with
    ``vector_env``, the fastest on few cores: see :func:`~torchrl_options.envs.atari.make_atari_ram_env`; the
    greedy demonstrations stay one game at a time), ``fused_adam`` (Adam as one fused kernel: the
    same algorithm, several times faster per update on the one-hot network; ``benchmarks/bench_dqn_update.py``).

    Greedy evaluation (off by default; the paper plots the mean return of rollouts of the learned policy): each
    time a cell's episode count passes a multiple of ``eval_every``, ``eval_episodes`` episodes of the greedy
    policy (options run as in training) on freshly seeded games, the same games for every condition and every
    time (:meth:`~torchrl_options.agents.OptionsDQN.record_evaluation`); the cell's json file keeps them and
    ``summary.md`` compares the conditions on them.

    ``torch_threads``: torch's thread count for the cells, set by the recipe (in a serial sweep's process, else in
    each pool or Ray worker instead of ``sweep.threads_per_worker``); ``None``: left as it is. The library itself
    sets no thread count.

    With batched games, episodes end several at a time and a phase stops at the first collector batch that
    completes its count: phase 1 may then have run up to ``num_envs - 1`` episodes more than
    ``phase1_episodes``. They are part of ``A``'s continuation (the same agent), so ``A``'s first phase-3 episodes
    may come from phase 1's last batch; the other conditions start new agents.
    """

    # env
    env_semantics: str = "project"
    frame_skip: int = 4
    repeat_action_probability: float = 0.0
    noop_max: int = 30
    episodic_life: bool = False
    clip_rewards: bool = True
    max_episode_steps: int | None = None
    ram_encoding: str = "one_hot"
    option_encoding: str = "one_hot"
    # phases
    phase1_episodes: int = 1000
    phase3_episodes: int = 4000
    num_demonstrations: int = 100
    demo_max_steps: int = 2000
    num_options: int | None = None
    options_num_cells: tuple[int, ...] = (64, 64, 64)
    ddo_iterations: int = 500
    ddo_batch_size: int | None = 20
    ddo_lr: float = 1e-3
    ddo_m_steps: int = 1
    ddo_starts: str = "one"
    ddo_usage_floor: float | None = None
    demo_random_episodes: int = 10
    # DQN: the fields of DQNHyperParameters, the paper's defaults where they differ from the agent's
    hidden_sizes: tuple[int, ...] = (64, 64, 64)
    gamma: float = 0.85
    eps_init: float = 0.05
    eps_annealing_frames: int = 1
    lr: float = 1e-4
    learning_starts: int = 1000
    hard_update_interval: int = 1000
    # the cell's own DQN settings
    vector_env: bool = False
    fused_adam: bool = False
    # greedy evaluation (the paper's measure): every eval_every episodes of a cell (0: off)
    eval_every: int = 0
    eval_episodes: int = 8
    # outputs
    checkpoint_every: int = 100
    checkpoint_buffer: bool = True
    option_frames: bool = True
    option_frames_max_steps: int = 400
    torch_threads: int | None = None

    #: (minimum, allowed None) of every int setting, and [low, high] of every number: checked when the settings
    #: are read, before any work starts
    _INTS: ClassVar[dict[str, tuple[int, bool]]] = {
        "frame_skip": (1, False), "noop_max": (0, False), "max_episode_steps": (1, True), "phase1_episodes": (1, False),
        "phase3_episodes": (1, False), "num_demonstrations": (1, False), "demo_max_steps": (1, False),
        "num_options": (1, True), "ddo_iterations": (0, False), "ddo_batch_size": (1, True), "eval_every": (0, False),
        "eval_episodes": (1, False), "checkpoint_every": (0, False), "option_frames_max_steps": (1, False),
        "torch_threads": (1, True), "demo_random_episodes": (0, False),
    }  # fmt: skip
    _NUMBERS: ClassVar[dict[str, tuple[float, float]]] = {"repeat_action_probability": (0.0, 1.0)}

    def __post_init__(self) -> None:
        from torchrl_options.checks import check_choice, check_int
        from torchrl_options.discovery import check_usage_floor

        super().__post_init__()  # the DQN settings
        check_int(self.ddo_m_steps, "ddo_m_steps", minimum=1)  # refused when the settings are read, not after phase 1
        check_choice(self.ddo_starts, "ddo_starts", ("one", "defaults"))
        check_usage_floor(self.ddo_usage_floor, "ddo_usage_floor")
        for name, (minimum, allow_none) in self._INTS.items():
            check_int(getattr(self, name), name, minimum=minimum, allow_none=allow_none)
        for name, (lo, hi) in self._NUMBERS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
                raise ValueError(f"{name} must be a number in [{lo}, {hi}], got {value!r}.")
        if isinstance(self.ddo_lr, bool) or not isinstance(self.ddo_lr, (int, float)) or not 0 < self.ddo_lr < float("inf"):
            raise ValueError(f"ddo_lr must be a number > 0, got {self.ddo_lr!r}.")
        for name, choices in (("ram_encoding", ("one_hot", "bytes")), ("option_encoding", ("one_hot", "bytes")),
                              ("env_semantics", ("project", "paper"))):
            if getattr(self, name) not in choices:
                raise ValueError(f"{name} must be one of {choices}, got {getattr(self, name)!r}.")
        for name in ("hidden_sizes", "options_num_cells"):
            sizes = getattr(self, name)
            if not isinstance(sizes, (tuple, list)) or not sizes or not all(
                isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in sizes
            ):
                raise ValueError(f"{name} must be a non-empty list of ints >= 1, got {sizes!r}.")
        from torchrl_options.checks import check_bool

        for name in ("episodic_life", "clip_rewards", "vector_env", "fused_adam", "checkpoint_buffer", "option_frames"):
            check_bool(getattr(self, name), name)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AtariConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown Atari settings: {sorted(unknown)}")
        d = dict(d)
        for key in ("options_num_cells", "hidden_sizes"):
            if key in d and d[key] is not None:
                d[key] = tuple(d[key])
        return cls(**d)

    #: fields that change how a cell runs (device, threads, pictures, greedy evaluation, which leaves training's
    #: random numbers untouched, fused Adam, the same algorithm), not the episodes it records. ``checkpoint_every``
    #: is not one of them: training restarts its episodes at each checkpoint (what makes resuming exact)
    RUN_ONLY_FIELDS: ClassVar[tuple[str, ...]] = (
        "device", "parallel", "torch_threads", "fused_adam", "checkpoint_buffer", "eval_every",
        "eval_episodes", "option_frames", "option_frames_max_steps",
    )  # fmt: skip

    def cell_settings(self) -> dict[str, Any]:
        """The settings that define what a cell computes: every field but :attr:`RUN_ONLY_FIELDS`. The recipe records
        them in its ``out_dir`` and refuses to resume it with others
        (:func:`~torchrl_options.experiments.run_settings.check_run_settings`).

        Examples:
            >>> settings = AtariConfig(device="cuda").cell_settings()
            >>> settings["phase1_episodes"], "device" in settings
            (1000, False)
        """
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.RUN_ONLY_FIELDS}

    def env_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~torchrl_options.envs.atari.make_atari_ram_env` that make the game: the
        env fields, or :data:`~torchrl_options.envs.atari.PAPER_ENV_SETTINGS` with ``env_semantics="paper"``.

        Examples:
            >>> paper = AtariConfig(env_semantics="paper", frame_skip=3).env_kwargs()
            >>> paper["frame_skip"], paper["clip_rewards"], paper["max_episode_steps"]
            ((2, 5), False, 10000)
            >>> AtariConfig(env_semantics="paper", max_episode_steps=200).env_kwargs()["max_episode_steps"]
            200
            >>> AtariConfig(frame_skip=3).env_kwargs()["frame_skip"]
            3
        """
        if self.env_semantics == "paper":
            from torchrl_options.envs.atari import PAPER_ENV_SETTINGS

            settings = dict(PAPER_ENV_SETTINGS)
            if self.max_episode_steps is not None:
                settings["max_episode_steps"] = self.max_episode_steps
            return settings
        return dict(
            frame_skip=self.frame_skip,
            repeat_action_probability=self.repeat_action_probability,
            noop_max=self.noop_max,
            episodic_life=self.episodic_life,
            clip_rewards=self.clip_rewards,
            max_episode_steps=self.max_episode_steps,
        )

    def dqn_settings(self) -> dict[str, Any]:
        """The :class:`~torchrl_options.agents.DQNHyperParameters` fields (``lr``, ``gamma``, ``batch_size``, ...),
        which the agent's :class:`~torchrl_options.agents.OptionsDQNConfig` has too: the agent's config is built
        from them.

        Examples:
            >>> settings = AtariConfig(lr=0.01).dqn_settings()
            >>> settings["lr"], "phase1_episodes" in settings
            (0.01, False)
        """
        return {f.name: getattr(self, f.name) for f in fields(DQNHyperParameters)}

    def options_for(self, game: str) -> int:
        from torchrl_options.envs.atari import PAPER_NUM_OPTIONS

        if self.num_options is not None:
            return int(self.num_options)
        return PAPER_NUM_OPTIONS.get(game, 4)


def store_atari_config(group: str = "atari", name: str = "schema") -> None:
    """Registers :class:`AtariConfig` in Hydra's ``ConfigStore`` as ``<group>/<name>``: the one schema of the
    Atari recipe's ``atari`` section (its defaults and types), which ``recipes/config/atari_ram.yaml`` names in its
    ``defaults`` and its presets only override. Needs ``hydra-core`` (the ``recipes`` extra).

    Examples:
        >>> from hydra.core.config_store import ConfigStore
        >>> store_atari_config()
        >>> ConfigStore.instance().load("atari/schema.yaml").node.phase1_episodes
        1000
    """
    for arg, value in (("group", group), ("name", name)):
        if not isinstance(value, str) or not value:
            raise TypeError(f"store_atari_config: {arg} must be a non-empty str, got {value!r}.")
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group=group, name=name, node=AtariConfig)


def check_atari_recipe_settings(cfg: Mapping[str, Any]) -> AtariConfig:
    """Checks the Atari recipe's own keys (``games``/``game``, ``seeds``, ``conditions``, the windows, ``sweep``)
    and its ``atari`` section (:class:`AtariConfig`), before any work; returns the cell settings.

    Raises:
        ValueError: naming the first bad setting.

    Examples:
        >>> check_atari_recipe_settings({"games": ["Pooyan"], "seeds": 1, "atari": {"phase1_episodes": 5}}).phase1_episodes
        5
        >>> check_atari_recipe_settings({"games": ["Pooyan"], "seeds": 1, "sweep": {"backend": "slurm"}})
        Traceback (most recent call last):
        ...
        ValueError: sweep.backend must be one of ('serial', 'local', 'ray'), got 'slurm'.
    """
    from torchrl_options.envs.atari import ATARI_GAMES

    games = [cfg["game"]] if cfg.get("game") else cfg.get("games")
    if isinstance(games, str) or not isinstance(games, (list, tuple)) or not games:
        raise ValueError(f"games must be a non-empty list of games (or set game=...), got {games!r}.")
    for game in games:
        if not isinstance(game, str) or not game:
            raise ValueError(f"games: {game!r} is not a game name (e.g. one of {list(ATARI_GAMES)}).")
    check_seeds(cfg.get("seeds"))
    conditions = cfg.get("conditions") or ["A", "H1"]
    for c in conditions:
        check_choice(c, "conditions", tuple(CONDITIONS))
    for key in ("smooth_window", "final_window"):
        check_int(cfg.get(key), key, minimum=1, allow_none=True)
    sweep = dict(cfg.get("sweep") or {})
    check_sweep(sweep.get("backend", "serial"), sweep.get("num_workers"), "sweep.")
    check_int(sweep.get("threads_per_worker"), "sweep.threads_per_worker", minimum=1, allow_none=True)
    try:
        config = AtariConfig.from_dict(dict(cfg.get("atari") or {}))
    except (TypeError, ValueError) as err:
        raise ValueError(str(err) if str(err).startswith("unknown") else f"atari.{err}") from None
    suffixes = [c for c in conditions if c.startswith("H1") and "s" in c[2:]]
    if suffixes and config.discount_per != "step":
        raise ValueError(
            f"conditions {suffixes} learn option values from option suffixes, discounted per primitive step: they "
            f"need atari.discount_per=step, got {config.discount_per!r}."
        )
    return config
