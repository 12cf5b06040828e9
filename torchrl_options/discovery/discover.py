"""One-call option discovery: DDO (Fox et al., 2017) trained with :class:`~torchrl_options.DDOLoss`.

:func:`discover_options` is the front door: it gathers its keyword arguments into a
:class:`~torchrl_options.discovery.settings.DiscoverySettings` (the plain values) and
:class:`~torchrl_options.discovery.networks.Networks` (the code), and :func:`discover` checks them and the
trajectories once and runs the stages of :mod:`~torchrl_options.discovery.stages`.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

from torchrl_options.discovery.batch import discovery_batch
from torchrl_options.discovery.networks import check_networks, check_width_choice, Networks, resolve_settings
from torchrl_options.discovery.settings import DiscoverySettings
from torchrl_options.discovery.stages import DiscoveryResult, run_discovery, seeded

__all__ = ["discover", "discover_options"]

logger = logging.getLogger(__name__)


def discover(
    trajectories: TensorDictBase | Sequence[TensorDictBase] | ReplayBuffer,
    settings: DiscoverySettings,
    networks: Networks | None = None,
) -> DiscoveryResult:
    """Discovers options with the settings of a :class:`~torchrl_options.discovery.settings.DiscoverySettings` (as
    a Hydra config gives them) and the networks of a :class:`~torchrl_options.discovery.networks.Networks`:
    :func:`discover_options` with its keyword arguments gathered.

    The door: the settings are resolved (``patience``, ``restarts``) and checked against the networks, the global
    RNG is seeded (``settings.seed``; every global random state is put back on return), the trajectories are
    checked and batched once (:func:`~torchrl_options.discovery.batch.discovery_batch`), and the stages run
    (:func:`~torchrl_options.discovery.stages.run_discovery`).

    Examples:
        >>> from torchrl_options.discovery.settings import DiscoverySettings
        >>> from torchrl_options.testing import planted_corridor_demonstrations
        >>> data = planted_corridor_demonstrations(8, 30, seed=0)
        >>> result = discover(data, DiscoverySettings(2, num_iterations=30, seed=0, progress=False))
        >>> len(result.option_usage)
        2
    """
    networks = Networks() if networks is None else networks
    settings = resolve_settings(settings, networks)
    check_networks(settings, networks, from_buffer=isinstance(trajectories, ReplayBuffer) or settings.distributed)
    with seeded(settings.seed) as generator:
        batch = discovery_batch(trajectories, settings, options=networks.options, meta_control=networks.meta_control,
                                infer_num_actions=networks.options is None)  # fmt: skip
        check_width_choice(settings, networks, batch)
        return run_discovery(batch, settings, networks, generator)


def discover_options(
    trajectories: TensorDictBase | Sequence[TensorDictBase] | ReplayBuffer,
    num_options: int,
    *,
    options: TensorDictModuleBase | None = None,
    meta_control: str | TensorDictModuleBase = "uniform",
    num_actions: int | None = None,
    action_space: str = "categorical",
    obs_keys: NestedKey | Sequence[NestedKey] = "observation",
    action_key: NestedKey = "action",
    num_cells: int | Sequence[int] | str = 8,
    termination_cells: int | Sequence[int] | None = None,
    activation: str = "tanh",
    architecture: str = "separate",
    init_scale: float | None = None,
    init: str = "auto",
    num_iterations: int = 1000,
    m_steps: int = 5,
    tol: float | None = 1e-4,
    patience: int | None = None,
    restarts: int | None = None,
    restart_iterations: int = 40,
    batch_size: int | None = None,
    optimizer: torch.optim.Optimizer | Callable[..., torch.optim.Optimizer] | None = None,
    lr: float = 0.03,
    lr_scheduler: Callable[[torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler] | None = None,
    device: torch.device | str | None = None,
    seed: int | None = None,
    progress: bool = True,
    trajectory_key: NestedKey = ("collector", "traj_ids"),
    return_info: bool = False,
    log_every: int = 50,
    desc: str = "DDO",
    split_merge: int = 0,
    split_merge_iterations: int = 300,
    options_factory: Callable[..., TensorDictModuleBase] | None = None,
    meta_control_factory: Callable[..., TensorDictModuleBase] | None = None,
    chunk_trajectories: int | None = None,
    eval_trajectories: int = 64,
    distributed: bool = False,
    usage_floor: float | None = None,
) -> TensorDictModuleBase | DiscoveryResult:
    """Discovers ``num_options`` options from demonstration trajectories with DDO.

    Hierarchical behavioural cloning by Expectation-Gradient (Fox, Krishnan, Stoica, Goldberg, "Multi-Level
    Discovery of Deep Options", 2017, section 4): the options' control policies, termination conditions and
    (optionally) meta-control policy are trained jointly to maximise the likelihood of the demonstrations, on
    minibatches of trajectories, under the model of :class:`~torchrl_options.DDOLoss`.

    Each iteration is an E-step (the exact posterior of the batch, :func:`~torchrl_options.forward_backward`)
    followed by ``m_steps`` optimizer steps (G-steps) on the expected complete-data log-likelihood, whose gradient
    at the E-step's parameters is the gradient of the log-likelihood: ``m_steps=1`` is the paper's
    Expectation-Gradient, ``m_steps > 1`` (default 5) a generalised EM that gets more out of each (costly) E-step. The networks
    are evaluated once per distinct state and state-action pair of the batch (:class:`~torchrl_options.discovery.TabulatedDDO`), which makes
    an iteration much cheaper when states repeat (grid worlds); results equal :class:`~torchrl_options.DDOLoss`'s
    to float rounding.

    On the paper's four rooms (50 x 1000 steps, K = 4, 2 tanh units; 1851 distinct states), ``m_steps=10,
    lr=0.1, tol=1e-3, patience=20`` converges in about 190 iterations, 25 s of CPU time on one core, where plain
    Expectation-Gradient (``m_steps=1``) is still improving after 400 (``benchmarks/bench_discovery.py``).

    The defaults were chosen on a suite of planted problems whose truth is known
    (:data:`~torchrl_options.testing.PLANTED_SUITE`, ``benchmarks/bench_planted_suite.py``): 8 tanh units, 5 G-steps
    per E-step at learning rate 0.03, 6 segment starts (``init="auto"``) of 40 iterations selected by likelihood,
    then up to 1000 iterations with the stopping rule ``tol=1e-4`` (over 20 iterations, 100 for Gaussian options),
    ending at the best iteration. Wider networks fit small data sets better than the truth does with other labels;
    the paper's 2 units, one start and plain Expectation-Gradient stop in local optima on several problems, and
    random starts miss the optimum next to the truth when options share moves.
    :data:`~torchrl_options.discovery.PAPER_SETTINGS` gives the paper's settings (``discover_options(data, K, **PAPER_SETTINGS)``). The result
    (``return_info=True``) reports each start's likelihood, each option's usage and duplicated options, and a
    warning is logged when they suggest a local optimum (:func:`~torchrl_options.discovery.option_diagnostics`).

    Args:
        trajectories: a ``[B, T]`` tensordict with ``("collector", "mask")`` (missing: all valid), one ``[T]``
            trajectory, a list of ``[T_i]`` trajectories, or a TorchRL replay buffer over a ``TensorStorage``
            (``LazyMemmapStorage`` on disk: :func:`~torchrl_options.data.demonstration_buffer`) holding whole
            trajectories, which is *streamed*: each iteration reads its trajectories (whole ones, never a window:
            the buffer's sampler is not used), so that memory is bounded by ``batch_size`` (or
            ``chunk_trajectories``) trajectories, not the data set. The buffer holds steps with their trajectory
            ids at ``trajectory_key`` (what a collector with ``replay_buffer=`` and ``trajs_per_batch`` writes, and
            :func:`~torchrl_options.data.write_demonstrations`) or ``[T]`` trajectories with their mask; see
            :mod:`~torchrl_options.discovery.streaming` for what is read when, and which likelihood the stopping
            rule and the choice among starts read then (the evaluation set's, with minibatches).
        num_options (int): K.

    Keyword Args:
        options (TensorDictModuleBase, optional): one options module to train (any module writing the option
            entries, modified in place), trained from one start as it comes (``init="auto"`` then means
            ``"random"``, and there are no restarts or width choice: those need fresh modules, see
            ``options_factory``). Default: an :class:`~torchrl_options.OptionsMLP` (or :class:`~torchrl_options.GaussianOptionsMLP`) built from the
            data.
        options_factory (callable, optional): your own networks with every start strategy: called as
            ``options_factory()``, it returns a fresh options module each time (any ``TensorDictModuleBase`` writing
            ``option_logits`` ``[..., K, A]`` (or ``option_loc`` / ``option_scale`` ``[..., K, D]``) and
            ``termination_logits`` ``[..., K]`` from its ``in_keys`` on any leading dims, a function of the step's
            entries as DDO's model assumes: a conv net on pixels, an MLP of your own,
            :class:`~torchrl_options.modules.OneHotByteOptions`).
            It is called once per start, after the seeding (its weights come from ``seed``), so ``init`` (segment
            and k-means starts clone the factory's modules), ``restarts`` and ``split_merge`` work as with the
            default modules; the first module made is checked against the data before any training. With
            ``num_cells="auto"`` it is called as ``options_factory(num_cells=width)`` for each candidate width and
            must take that keyword. As TorchRL's collectors take ``policy_factory`` next to ``policy``: give
            ``options`` or ``options_factory``, not both. ``num_cells``, ``termination_cells``, ``activation``,
            ``architecture`` and ``init_scale`` describe the default modules only (``init_scale`` is refused with
            either).
        meta_control (str or module): ``"uniform"`` (H1u, default), ``"learned"`` (an :class:`~torchrl_options.MetaControlMLP`,
            H1s, or ``meta_control_factory``'s module) or a module writing ``meta_logits``.
        meta_control_factory (callable, optional): with ``meta_control="learned"``, builds each start's learned
            meta-control instead of the default :class:`~torchrl_options.MetaControlMLP` (a module writing ``meta_logits``
            ``[..., K]``), called as ``options_factory`` is (``meta_control_factory(num_cells=width)`` with
            ``num_cells="auto"``).
        num_actions (int, optional): A for discrete actions; default: ``max(action) + 1`` over the data.
        action_space (str): ``"categorical"`` (default) or ``"continuous"``.
        obs_keys (NestedKey or list): observation entries the default modules read. Defaults to ``"observation"``.
        action_key (NestedKey): the action entry. Defaults to ``"action"``.
        num_cells, activation, architecture: for the default modules. Defaults: 8 tanh units, one hidden layer,
            separate networks per option (the paper's four rooms: 2 tanh units). ``num_cells="auto"`` chooses the
            width among :data:`~torchrl_options.discovery.width.AUTO_WIDTHS` (4 and 8) by the log-likelihood of
            20% of the trajectories held out while each width is fitted on the rest (with the restarts), then
            trains the chosen fit on all the trajectories; about twice the CPU time of one width on the planted
            suite. The result's ``num_cells`` and ``width_log_likelihoods`` say what was chosen and why, and its
            ``history`` holds the chosen width's iterations on the training share followed by those on all the
            trajectories.
        termination_cells (int or sequence of int, optional): hidden sizes of the default modules' termination
            networks. Defaults to ``num_cells`` for discrete actions and, for continuous ones, to two layers of twice
            the widest of ``num_cells`` (``[16, 16]`` with the default width; see :func:`~torchrl_options.discovery.default_options`).
        init_scale (float, optional): for continuous actions, the standard deviation every fresh Gaussian option
            starts at. Defaults to the demonstrations' action spread (see :func:`~torchrl_options.discovery.default_options`); ``1.0`` was the
            default until 2026-12-05.
        init (str): how each start's options are drawn before DDO: ``"random"``, ``"kmeans"`` (pre-clustering of
            state-action pairs, appendix B), ``"segments"`` (the demonstrations cut where the actions change regime,
            the segments clustered by where they end, each option cloned from a cluster:
            :func:`~torchrl_options.discovery.pretrain_on_segments`; every start draws its own clusters), or
            ``"auto"`` (default): for fresh modules (the default ones or ``options_factory``'s) given tensordicts,
            segment starts, two of every three clustered by where the segments end and the third by their actions
            (``features="actions"``), :data:`~torchrl_options.discovery.AUTO_RESTARTS` of them unless ``restarts`` is set; ``"random"`` (the
            modules as they come) when ``options`` are given or the trajectories come from a replay buffer.
        num_iterations (int): the most iterations (E-steps). Defaults to 1000 (the stopping rule usually ends
            training sooner).
        m_steps (int): optimizer steps per E-step (G-steps); 1 is the paper's Expectation-Gradient. Defaults to 5.
        tol (float, optional): stopping rule: stop once the log-likelihood per step has gained less than ``tol``
            nats over the last ``patience`` iterations (see :func:`~torchrl_options.discovery.converged_at`; meant for full-batch training,
            minibatch estimates are noisy). Defaults to 1e-4; ``None`` runs all ``num_iterations``. With ``tol`` on
            the full batch, the last training (the chosen start's, continued) ends at its iteration with the
            highest log-likelihood per step (``fit_ddo(keep_best=True)``), not at its last one; a start that meets
            the stopping rule within ``restart_iterations`` is returned as it stopped.
        patience (int, optional): the stopping rule's window, in iterations. Defaults to 20 for discrete actions and
            to :data:`~torchrl_options.discovery.CONTINUOUS_PATIENCE` (100) for continuous ones: a Gaussian fit's likelihood pauses for tens of
            iterations and then climbs again (measured in ``docs/experiments/planted_suite.md``).
        restarts (int): starts from ``restarts`` initialisations (as ``init`` draws them), each trained for
            at most ``restart_iterations`` iterations; the one with the highest training log-likelihood (a
            label-free model selection) is then trained for the rest of ``num_iterations``. The likelihood has
            local optima (two options merged, one unused), which restarts avoid. More than 1 needs fresh modules
            for each start (the default ``options`` or an ``options_factory``, a meta-control given by name) and an
            optimizer factory (not an instance). ``None`` (default): n starts
            when fresh modules can be drawn and ``num_iterations >= n * restart_iterations``, else 1, with n
            :data:`~torchrl_options.discovery.AUTO_RESTARTS` (6) for ``init="auto"`` and :data:`~torchrl_options.discovery.DEFAULT_RESTARTS` (4) otherwise.
        restart_iterations (int): the iterations given to each start when ``restarts > 1``. Defaults to 40.
        batch_size (int, optional): trajectories per minibatch; ``None`` uses all of them every iteration.
        chunk_trajectories (int, optional): streamed only: trajectories per E-step when an iteration reads more
            (the full batch of a large buffer); the chunks' gradients are summed before the step, so an iteration
            is the full-batch one with the memory of a chunk. Needs ``m_steps=1`` when it cuts an iteration's
            trajectories. ``None`` (default): all at once.
        eval_trajectories (int): streamed with minibatches: the size of the fixed evaluation set whose
            log-likelihood the stopping rule, the choice among starts and ``keep_best`` read (also the sample the
            data checks, the default modules and the segment starts are taken from). Defaults to 64.
        distributed (bool): data-parallel over the initialised ``torch.distributed`` process group (``torchrun``;
            gloo on CPU, NCCL on GPU): each process streams its shard (trajectories ``rank, rank + world_size,
            ...``) and the gradients are all-reduced (:mod:`~torchrl_options.discovery.distributed`); every process
            returns the same modules. ``batch_size`` is then the global minibatch. Tensordicts given with it are
            streamed in place. Defaults to ``False``.
        optimizer: an optimizer instance over the modules' parameters, or a factory called as
            ``optimizer(params, lr=lr)``. Defaults to Adam (``fused=True`` on CPU and CUDA, else ``foreach=True``).
        lr (float): learning rate for the default or factory-made optimizer. Defaults to 0.03.
        lr_scheduler (callable, optional): ``lr_scheduler(optimizer)`` makes a learning-rate scheduler of the
            optimizer (given or made), stepped once per iteration, e.g.
            ``lambda opt: torch.optim.lr_scheduler.CosineAnnealingLR(opt, num_iterations)``. Defaults to none.
        device: where to train. Defaults to the data's device.
        seed (int, optional): seeds module initialisation, minibatch order and clustering; the global random
            states are restored on return, so the caller's random numbers do not change.
        progress (bool): show a tqdm progress bar. Defaults to ``True``.
        trajectory_key (NestedKey): trajectory ids used to split replay-buffer samples.
        return_info (bool): return a :class:`~torchrl_options.discovery.DiscoveryResult` (options, meta-control, history).
        log_every (int): log the diagnostics every this many iterations.
        desc (str): the progress bar's label, e.g. which run it fits (``"DDO supervised seed 0, K=4, uniform"``).
            Defaults to ``"DDO"``.
        split_merge (int): after the main fit, propose this many split-and-merge moves
            (:mod:`~torchrl_options.discovery.split_merge`; Ueda et al., 2000): a little-used or duplicated option
            is overwritten with a noisy copy of a busy one, the model re-trained for ``split_merge_iterations``
            iterations from there (one start, the same ``lr``, ``m_steps``, ``tol``, ``patience``, ``batch_size``,
            optimizer factory and scheduler), and the move kept only if the training log-likelihood per step rises
            by more than 1e-4; so the final likelihood is never below the main fit's. Each move costs up to
            ``split_merge_iterations`` iterations. It needs options whose every parameter has the option index as
            leading dimension (the default modules with ``architecture="separate"``), ``meta_control="uniform"``,
            ``num_options >= 2``, trajectories given as tensordicts (not a replay buffer) and no optimizer
            instance. With ``num_cells="auto"`` the moves follow the final fit on all the trajectories. Defaults
            to 0 (off). On the planted ``landmarks-8`` problem, 8 moves raise the share of correctly labelled
            steps from the main fit's local optimum (``docs/experiments/planted_suite.md``).
        split_merge_iterations (int): the most iterations of each move's re-fit. Defaults to 300.
        usage_floor (float, optional): keep every option in use during the fit: each E-step's posterior is
            projected onto "every option active on at least ``usage_floor / K`` of the steps" (posterior
            regularisation, :mod:`~torchrl_options.discovery.usage_floor`), a share of the uniform usage in
            ``(0, 1)``. Against the collapse to one option that maximum likelihood allows when one option can copy
            a demonstrator. The history's ``log_likelihood_per_step`` is then the penalised objective (a lower
            bound of the likelihood, equal to it when no floor binds); the result's ``option_usage`` is the
            trained model's own. Needs trajectories as tensordicts. Defaults to ``None`` (off).

    Returns:
        The trained options module, or a :class:`~torchrl_options.discovery.DiscoveryResult` with ``return_info=True``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import discover_options
        >>> B, T = 8, 30
        >>> obs = torch.randn(B, T + 1, 2)
        >>> data = TensorDict({"observation": obs[:, :-1], "action": (obs[:, :-1, 0] > 0).long(),
        ...                    "next": {"observation": obs[:, 1:]}}, [B, T])
        >>> options = discover_options(data, num_options=2, num_iterations=20, seed=0, progress=False)
        >>> options(data[0].clone())["option_logits"].shape
        torch.Size([30, 2, 2])
    """
    networks = Networks(
        options=options, options_factory=options_factory,
        meta_control=None if isinstance(meta_control, str) else meta_control,
        meta_control_factory=meta_control_factory, optimizer=optimizer, lr_scheduler=lr_scheduler,
    )  # fmt: skip
    settings = DiscoverySettings(
        num_options, meta_control=meta_control if isinstance(meta_control, str) else "uniform",
        num_actions=num_actions, action_space=action_space, obs_keys=obs_keys, action_key=action_key,
        num_cells=num_cells, termination_cells=termination_cells, activation=activation, architecture=architecture,
        init_scale=init_scale, init=init, num_iterations=num_iterations, m_steps=m_steps, tol=tol, patience=patience,
        restarts=restarts, restart_iterations=restart_iterations, batch_size=batch_size, lr=lr, device=device,
        seed=seed, progress=progress, trajectory_key=trajectory_key, log_every=log_every, desc=desc,
        split_merge=split_merge, split_merge_iterations=split_merge_iterations,
        chunk_trajectories=chunk_trajectories, eval_trajectories=eval_trajectories, distributed=distributed,
        usage_floor=usage_floor,
    )  # fmt: skip
    result = discover(trajectories, settings, networks)
    return result if return_info else result.options
