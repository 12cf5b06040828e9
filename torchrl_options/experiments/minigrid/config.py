"""The settings of the MiniGrid recipe (:class:`MiniGridConfig`), checked when they are read, and its Hydra schema
(:func:`store_minigrid_config`)."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

__all__ = ["ALGORITHMS", "MiniGridConfig", "OPTION_CONDITIONS", "store_minigrid_config"]

#: the RL algorithms of a condition's name (``"ppo-A"``, ``"dqn-H1"``, ...)
ALGORITHMS = ("ppo", "dqn")
#: ``A``: actions only; ``H1``: actions + options discovered on the RL level itself (same level); ``H1t``: actions
#: + options discovered on ``transfer_source`` (transfer)
OPTION_CONDITIONS = ("A", "H1", "H1t")


@dataclass
class MiniGridConfig:
    """Settings of the MiniGrid recipe: the schema of the ``minigrid`` section of ``recipes/config/minigrid.yaml``.

    **Segmentation** (stage "demonstrations -> discovery -> segmentation scores"): for every level of
    ``segmentation_levels`` and each of ``segmentation_seeds`` seeds, ``num_demonstrations`` BabyAI-bot
    demonstrations, DDO with ``num_options`` options of ``network`` (``"mlp"``: ``discover_options``'s defaults;
    ``"conv"``: :class:`~torchrl_options.modules.GridConvOptions`; see
    :mod:`~torchrl_options.experiments.minigrid.segmentation`) for at most ``ddo_iterations`` iterations, then the
    scores against the bot's subgoals and skills with the trivial baselines.

    **RL**: on ``rl_level`` (sparse reward: MiniGrid's ``1 - 0.9 t / T`` on success, 0 otherwise), each condition of
    ``conditions`` for ``rl_seeds`` seeds and ``rl_frames`` frames: ``"<algorithm>-<kind>"`` with the algorithm in
    :data:`ALGORITHMS` and the kind in :data:`OPTION_CONDITIONS`: ``A`` actions only, ``H1`` actions + the options
    discovered from the bot on ``rl_level`` itself (same level), ``H1t`` actions + those discovered on
    ``transfer_source`` (transfer: an easier level's skills on a harder level). ``max_episode_steps`` cuts the RL
    episodes (``None``: the level's own limit, e.g. 72 steps on ``BabyAI-UnlockPickup-v0``, 576 on
    ``BabyAI-UnlockLocal-v0``); a cell must end at least one episode in ``rl_frames`` frames. The options of a
    (level, seed) are those of its segmentation cell when it has one (cached in ``<out_dir>/options/``), else
    discovered from ``num_demonstrations`` demonstrations in the same way. PPO: :class:`~torchrl_options.agents.OptionsPPO` with
    ``num_envs`` envs, ``frames_per_batch``, ``ppo_epochs``, ``ppo_minibatch``, ``lr``, ``entropy_coeff``,
    ``gamma``, ``hidden_sizes``; DQN: :class:`~torchrl_options.agents.OptionsDQN` with the same envs, ``lr``,
    ``gamma`` and ``hidden_sizes``, and ``dqn_eps_frames`` of linear epsilon annealing from 1 to 0.05.
    A cell checkpoints every ``checkpoint_every`` frames and resumes from there (each chunk is a fresh ``train``,
    so a resumed cell is the uninterrupted one).

    ``success_target``: the success rate (share of episodes with a positive return, over ``success_window``
    episodes) whose first reach is reported as "frames to reach".
    """

    # segmentation
    segmentation_levels: list[str] = field(default_factory=lambda: ["BabyAI-UnlockPickup-v0"])
    segmentation_seeds: int = 2
    num_demonstrations: int = 100
    num_options: int = 5
    network: str = "mlp"
    ddo_iterations: int = 1000
    # RL
    rl_level: str = "BabyAI-UnlockPickup-v0"
    transfer_source: str = "BabyAI-UnlockLocal-v0"
    conditions: list[str] = field(default_factory=lambda: ["ppo-A", "ppo-H1", "ppo-H1t"])
    rl_seeds: int = 2
    rl_frames: int = 20_000
    max_episode_steps: int | None = None
    num_envs: int = 4
    parallel: bool = False
    frames_per_batch: int = 512
    ppo_epochs: int = 4
    ppo_minibatch: int = 128
    lr: float = 3e-4
    entropy_coeff: float = 0.01
    gamma: float = 0.99
    hidden_sizes: list[int] = field(default_factory=lambda: [64, 64])
    dqn_eps_frames: int = 20_000
    checkpoint_every: int = 10_240
    success_target: float = 0.5
    success_window: int = 50
    torch_threads: int | None = 1

    _INTS: ClassVar[dict[str, tuple[int, bool]]] = {
        "segmentation_seeds": (0, False), "num_demonstrations": (1, False), "num_options": (1, False),
        "ddo_iterations": (1, False), "rl_seeds": (0, False), "rl_frames": (1, False), "num_envs": (1, False),
        "frames_per_batch": (1, False), "ppo_epochs": (1, False), "ppo_minibatch": (1, False),
        "dqn_eps_frames": (0, False), "checkpoint_every": (1, False), "success_window": (1, False),
        "torch_threads": (1, True), "max_episode_steps": (1, True),
    }  # fmt: skip

    def __post_init__(self) -> None:
        from torchrl_options.checks import check_bool, check_choice, check_int, check_number

        for name, (minimum, allow_none) in self._INTS.items():
            check_int(getattr(self, name), name, minimum=minimum, allow_none=allow_none)
        check_choice(self.network, "network", ("mlp", "conv"))
        check_bool(self.parallel, "parallel")
        check_number(self.lr, "lr", lo=0, hi=1, lo_open=True)
        check_number(self.entropy_coeff, "entropy_coeff", lo=0)
        check_number(self.gamma, "gamma", lo=0, hi=1)
        check_number(self.success_target, "success_target", lo=0, hi=1)
        levels = self.segmentation_levels
        if not isinstance(levels, (list, tuple)) or not all(isinstance(lv, str) and lv.startswith("BabyAI-")
                                                            for lv in levels):  # fmt: skip
            raise ValueError(f"segmentation_levels must be a list of BabyAI levels (the bot's), got {levels!r}.")
        for name in ("rl_level", "transfer_source"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value.startswith(("BabyAI-", "MiniGrid-")):
                raise ValueError(f"{name} must be a MiniGrid or BabyAI level id, got {value!r}.")
        if not self.transfer_source.startswith("BabyAI-"):
            raise ValueError(
                f"transfer_source must be a BabyAI level (the bot demonstrates it), got {self.transfer_source!r}."
            )
        conditions = list(self.conditions)
        allowed = [f"{a}-{k}" for a in ALGORITHMS for k in OPTION_CONDITIONS]
        bad = [c for c in conditions if c not in allowed]
        if bad or not conditions:
            raise ValueError(f"conditions must be a non-empty list of {allowed}, got {conditions!r}.")
        if any(c.endswith("-H1") for c in conditions) and not self.rl_level.startswith("BabyAI-"):
            raise ValueError(
                "an H1 condition discovers options on rl_level with the bot: it needs a BabyAI level, got "
                f"{self.rl_level!r} (use H1t, options from transfer_source)."
            )
        sizes = self.hidden_sizes
        if not isinstance(sizes, (list, tuple)) or not sizes or not all(
            isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in sizes
        ):
            raise ValueError(f"hidden_sizes must be a non-empty list of ints >= 1, got {sizes!r}.")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MiniGridConfig:
        """Builds the settings from a plain dict (the composed Hydra section), refusing unknown names.

        Examples:
            >>> MiniGridConfig.from_dict({"rl_frames": 1000}).rl_frames
            1000
            >>> try:
            ...     MiniGridConfig.from_dict({"rl_frame": 1000})
            ... except ValueError as err:
            ...     print(str(err)[:40])
            unknown MiniGrid settings: ['rl_frame']
        """
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown MiniGrid settings: {unknown} (known: {sorted(names)}).")
        d = dict(d)
        for key in ("segmentation_levels", "conditions", "hidden_sizes"):
            if key in d and d[key] is not None:
                d[key] = list(d[key])
        return cls(**d)

    #: fields that change how a cell runs, not what it computes
    RUN_ONLY_FIELDS: ClassVar[tuple[str, ...]] = ("parallel", "torch_threads", "success_target", "success_window")

    def cell_settings(self) -> dict[str, Any]:
        """The settings that define what the cells compute (every field but :attr:`RUN_ONLY_FIELDS`): recorded in
        the ``out_dir``, which is refused with others.

        Examples:
            >>> "rl_frames" in MiniGridConfig().cell_settings(), "parallel" in MiniGridConfig().cell_settings()
            (True, False)
        """
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.RUN_ONLY_FIELDS}


def store_minigrid_config(group: str = "minigrid", name: str = "schema") -> None:
    """Registers :class:`MiniGridConfig` in Hydra's ``ConfigStore`` as ``<group>/<name>``: the schema that
    ``recipes/config/minigrid.yaml`` names in its ``defaults``. Needs ``hydra-core`` (the ``recipes`` extra).

    Examples:
        >>> from hydra.core.config_store import ConfigStore
        >>> store_minigrid_config()
        >>> ConfigStore.instance().load("minigrid/schema.yaml").node.rl_frames
        20000
    """
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group=group, name=name, node=MiniGridConfig)
