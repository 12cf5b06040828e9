"""Where each start's networks come from (:class:`Networks`): the default modules (:func:`default_options`), one
module given by the caller, or factories of fresh modules; and the checks of what a run's settings ask of them
(:func:`check_networks`)."""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_choice
from torchrl_options.discovery.batch import DiscoveryBatch, infer_in_features, MASK_KEY
from torchrl_options.discovery.settings import (
    ACTION_SPACES,
    check_init_scale,
    default_restarts,
    DiscoverySettings,
    obs_key_list,
)
from torchrl_options.discovery.split_merge import check_split_merge_options
from torchrl_options.discovery.validation import check_factories, check_meta_control_module, check_options_module
from torchrl_options.modules import GaussianOptionsMLP, hidden_sizes, MetaControlMLP, OptionsMLP

__all__ = ["Networks", "check_networks", "check_width_choice", "default_options", "resolve_settings"]

OptimizerArg = torch.optim.Optimizer | Callable[..., torch.optim.Optimizer] | None


def default_options(
    data: TensorDictBase,
    num_options: int,
    *,
    action_space: str = "categorical",
    num_actions: int | None = None,
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] = 8,
    termination_cells: int | Sequence[int] | None = None,
    activation: str = "tanh",
    architecture: str = "separate",
    init_scale: float | None = None,
) -> TensorDictModuleBase:
    """The fresh options :func:`discover_options` trains when none are given (weights from the global RNG).

    Discrete actions get an :class:`OptionsMLP`; continuous ones a :class:`GaussianOptionsMLP` whose options all
    start at the demonstrations' own action spread (the mean per-dimension standard deviation of the valid
    actions, clipped to ``[0.01, 1]``) unless ``init_scale`` is given: a start at 1.0 can dwarf the spread and
    leave every option alike, a symmetric start the likelihood cannot leave. Unless ``termination_cells`` is given, a Gaussian option's
    termination network has two hidden layers of twice the widest of ``num_cells``: one layer of tanh units
    draws half-planes, and a termination that fires within a region of a continuous state space (the planted
    suite's Gaussian options stop near their goal) is their intersection, which a second layer forms and one layer
    approaches only slowly (measured in ``docs/experiments/planted_suite.md``).

    Args:
        data (TensorDictBase): ``[B, T]`` trajectories with the ``("collector", "mask")`` of valid steps.
        num_options (int): K.

    Keyword Args:
        action_space (str): ``"categorical"`` (default) or ``"continuous"``.
        num_actions (int, optional): A, for discrete actions. Defaults to ``max(action) + 1`` over valid steps.
        obs_keys, action_key, num_cells, termination_cells, activation, architecture, init_scale: as in
            :func:`discover_options`.

    Examples:
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(num_trajectories=4, length=10, seed=0)
        >>> type(default_options(data, 2)).__name__
        'OptionsMLP'
    """
    check_choice(action_space, "action_space", ACTION_SPACES)
    check_init_scale(init_scale, action_space)
    obs_keys = obs_key_list(obs_keys)
    mask = data.get(MASK_KEY) if MASK_KEY in data.keys(include_nested=True) else torch.ones(data.batch_size, dtype=torch.bool)
    in_features = infer_in_features(data, obs_keys)
    if action_space == "categorical":
        if num_actions is None:
            num_actions = int(data.get(action_key)[mask].max()) + 1
        return OptionsMLP(
            in_features, num_actions, num_options, num_cells=num_cells, termination_cells=termination_cells,
            activation=activation, architecture=architecture, in_keys=obs_keys,
        )
    if termination_cells is None:
        width = 2 * max(hidden_sizes(num_cells))
        termination_cells = [width, width]
    actions = data.get(action_key)[mask]
    action_dim = actions.shape[-1]
    if init_scale is None:
        spread = float(actions.float().std(0).mean()) if actions.shape[0] > 1 else 1.0
        init_scale = min(max(spread, 1e-2), 1.0) if spread == spread else 1.0
    return GaussianOptionsMLP(
        in_features, action_dim, num_options, num_cells=num_cells, termination_cells=termination_cells,
        activation=activation, in_keys=obs_keys, init_scale=init_scale, min_scale=min(1e-3, init_scale / 10),
    )


@dataclass
class Networks:
    """What a discovery run trains and how, beyond its plain settings: the code that
    :func:`~torchrl_options.discover_options` takes as arguments.

    Attributes:
        options (TensorDictModuleBase, optional): one options module, trained from one start as it comes.
        options_factory (callable, optional): ``options_factory()`` makes a fresh options module per start
            (``options_factory(num_cells=width)`` when the width is chosen). Neither: :func:`default_options`.
        meta_control (TensorDictModuleBase, optional): a meta-control module (in place of
            :attr:`DiscoverySettings.meta_control <torchrl_options.discovery.settings.DiscoverySettings>`).
        meta_control_factory (callable, optional): makes each start's learned meta-control
            (``meta_control="learned"``); default: a :class:`~torchrl_options.MetaControlMLP`.
        optimizer: an optimizer instance over the given modules' parameters, or a factory
            ``optimizer(params, lr=lr)``; ``None``: Adam.
        lr_scheduler (callable, optional): ``lr_scheduler(optimizer)`` makes a scheduler stepped once per iteration.

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> Networks(options_factory=lambda: OptionsMLP(2, 3, 4)).fresh
        True
        >>> Networks(options=OptionsMLP(2, 3, 4)).fresh
        False
    """

    options: TensorDictModuleBase | None = None
    options_factory: Callable[..., TensorDictModuleBase] | None = None
    meta_control: TensorDictModuleBase | None = None
    meta_control_factory: Callable[..., TensorDictModuleBase] | None = None
    optimizer: OptimizerArg = None
    lr_scheduler: Callable[[torch.optim.Optimizer], Any] | None = None

    def __post_init__(self) -> None:
        if self.options is not None and not isinstance(self.options, TensorDictModuleBase):
            raise TypeError(f"options must be None or a TensorDictModuleBase, got {type(self.options).__name__}.")
        if self.meta_control is not None and not isinstance(self.meta_control, TensorDictModuleBase):
            raise TypeError(f"meta_control must be 'uniform', 'learned' or a module, got {type(self.meta_control).__name__}.")
        if self.lr_scheduler is not None and not callable(self.lr_scheduler):
            raise ValueError(
                f"lr_scheduler must be a callable making a scheduler from the optimizer, got {self.lr_scheduler!r}."
            )

    @property
    def fresh(self) -> bool:
        """Whether every start can draw new modules: no options module and no optimizer instance given."""
        return (
            self.options is None and self.meta_control is None
            and not isinstance(self.optimizer, torch.optim.Optimizer)
        )  # fmt: skip

    def with_width(self, width: int) -> Networks:
        """The factories called with ``num_cells=width`` (a width fit of ``num_cells="auto"``)."""

        def fixed(factory: Callable[..., TensorDictModuleBase] | None) -> Callable[..., TensorDictModuleBase] | None:
            return None if factory is None else functools.partial(factory, num_cells=width)

        return replace(self, options_factory=fixed(self.options_factory),
                       meta_control_factory=fixed(self.meta_control_factory))  # fmt: skip

    def trained(self, options: TensorDictModuleBase, meta_control: TensorDictModuleBase | None = None) -> Networks:
        """Given modules to train on (a width's chosen fit, a split-and-merge candidate), with the same optimizer
        factory and scheduler."""
        return Networks(options=options, meta_control=meta_control, optimizer=self.optimizer,
                        lr_scheduler=self.lr_scheduler)  # fmt: skip

    def new_options(self, batch: DiscoveryBatch, settings: DiscoverySettings, *, check: bool = False) -> TensorDictModuleBase:
        """The options of a new start: the given module, the factory's next one (checked on the data with
        ``check``), or fresh default modules (drawn from the global RNG)."""
        if self.options is not None:
            return self.options
        if self.options_factory is None:
            return default_options(
                batch.data, settings.num_options, action_space=settings.action_space, num_actions=batch.num_actions,
                obs_keys=settings.obs_key_list, action_key=settings.action_key, num_cells=settings.num_cells,
                termination_cells=settings.termination_cells, activation=settings.activation,
                architecture=settings.architecture, init_scale=settings.init_scale,
            )  # fmt: skip
        options = self.options_factory()
        if not isinstance(options, TensorDictModuleBase):
            raise TypeError(f"options_factory must return a TensorDictModuleBase, got {type(options).__name__}.")
        if check:  # the first module made is checked against the data, before any training
            check_options_module(options, batch.data, settings.num_options, num_actions=batch.num_actions,
                                 action_space=settings.action_space, name="options_factory's")  # fmt: skip
            if settings.split_merge:
                check_split_merge_options(options, settings.num_options)
        return options

    def new_meta_control(
        self, batch: DiscoveryBatch, settings: DiscoverySettings, *, check: bool = False
    ) -> TensorDictModuleBase | None:
        """The meta-control of a new start: the given module, ``None`` (uniform), or a fresh learned one."""
        if self.meta_control is not None:
            return self.meta_control
        if settings.meta_control == "uniform":
            return None
        if self.meta_control_factory is None:
            obs_keys = settings.obs_key_list
            return MetaControlMLP(infer_in_features(batch.data, obs_keys), settings.num_options,
                                  num_cells=settings.num_cells, activation=settings.activation, in_keys=obs_keys)  # fmt: skip
        meta = self.meta_control_factory()
        if check:
            check_meta_control_module(meta, batch.data, settings.num_options, name="meta_control_factory's")
        return meta


def check_networks(settings: DiscoverySettings, networks: Networks, *, from_buffer: bool = False) -> None:
    """Refuses what a run's settings ask of its networks and cannot have, before any data is read: factories that
    cannot serve, ``init_scale`` with given options, and the needs of ``split_merge`` (``num_options >= 2``,
    ``meta_control="uniform"``, per-option parameters, an optimizer factory, tensordicts rather than a replay
    buffer) and of ``usage_floor`` (tensordicts) and of restarts (fresh modules, ``restart_iterations`` within ``num_iterations``)."""
    meta = networks.meta_control if networks.meta_control is not None else settings.meta_control
    check_factories(networks.options, networks.options_factory, meta, networks.meta_control_factory,
                    init_scale=settings.init_scale, num_cells=settings.num_cells)  # fmt: skip
    if settings.split_merge:
        _check_split_merge(settings, networks, from_buffer)
    if settings.usage_floor is not None and from_buffer:
        raise ValueError(
            f"usage_floor={settings.usage_floor!r} projects the E-step of trajectories held in memory: give the "
            "trajectories as tensordicts (not a replay buffer) and distributed=False."
        )
    restarts = settings.restarts
    if restarts is not None and restarts > 1:
        if not isinstance(settings.restart_iterations, int) or not 1 <= settings.restart_iterations <= settings.num_iterations:
            raise ValueError(
                f"restart_iterations must be an int in [1, num_iterations={settings.num_iterations}] when restarts > 1, "
                f"got {settings.restart_iterations!r}."
            )
        if not networks.fresh:
            raise ValueError(
                f"restarts={restarts} draws fresh modules for each start: it needs options=None (the default modules or "
                "an options_factory), meta_control 'uniform' or 'learned', and an optimizer factory rather than an "
                "optimizer instance."
            )


def _check_split_merge(settings: DiscoverySettings, networks: Networks, from_buffer: bool) -> None:
    num_options = settings.num_options
    if num_options < 2:
        raise ValueError(
            f"split_merge copies one option into another's slot: it needs num_options >= 2, got {num_options}."
        )
    if networks.meta_control is not None or settings.meta_control != "uniform":
        given = settings.meta_control if networks.meta_control is None else type(networks.meta_control).__name__
        raise ValueError(
            "split_merge supports only meta_control='uniform' (a learned meta-control's choice of the copied option "
            f"is not copied), got meta_control={given!r}."
        )
    if networks.options is None and networks.options_factory is None and settings.architecture != "separate":
        raise ValueError(
            "split_merge copies one option's own parameters into another's: it needs architecture='separate' "
            f"(no parameters shared between options), got architecture={settings.architecture!r}."
        )
    if networks.options is not None:
        check_split_merge_options(networks.options, num_options)
    if isinstance(networks.optimizer, torch.optim.Optimizer):
        raise ValueError(
            "split_merge re-trains each move with a fresh optimizer: give an optimizer factory (or None), not an "
            f"optimizer instance, got {type(networks.optimizer).__name__}."
        )
    if from_buffer:
        raise ValueError(
            "split_merge compares the training log-likelihood of the whole data before and after each move: give "
            "the trajectories as tensordicts, not a replay buffer."
        )


def check_width_choice(settings: DiscoverySettings, networks: Networks, batch: DiscoveryBatch) -> None:
    """``num_cells="auto"`` fits fresh modules of each width on 80% of at least 5 trajectories given as tensordicts."""
    if not isinstance(settings.num_cells, str):
        return
    if not networks.fresh or batch.buffer is not None or batch.num_trajectories < 5:
        raise ValueError(
            "num_cells='auto' fits fresh modules of each width in AUTO_WIDTHS on 80% of the trajectories and keeps "
            "the width with the best likelihood on the rest: it needs options=None (the default modules or an "
            "options_factory taking num_cells), meta_control 'uniform' or 'learned', no optimizer instance, and at "
            f"least 5 trajectories given as tensordicts (not a replay buffer); got {batch.num_trajectories} "
            "trajectories" + (" from a replay buffer" if batch.buffer is not None else "") + "."
        )


def resolve_settings(settings: DiscoverySettings, networks: Networks) -> DiscoverySettings:
    """The settings with ``patience`` and ``restarts`` chosen where left at ``None``: the stopping rule's window of
    the action space, and several short starts whenever fresh modules can be drawn for each
    (:func:`~torchrl_options.discovery.settings.default_restarts`)."""
    restarts = settings.restarts
    if restarts is None:
        restarts = default_restarts(settings.init, settings.num_iterations, settings.restart_iterations, networks.fresh)
    return settings.replace(patience=settings.stopping_patience, restarts=restarts)
