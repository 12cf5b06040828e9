"""One segmentation measurement: the bot's demonstrations on a level, DDO, ``segment``, and the scores against the
bot's subgoals and skills next to the trivial baselines (:mod:`~torchrl_options.experiments.minigrid.scoring`).

A *method* is a dict of :func:`~torchrl_options.discover_options` keyword arguments plus ``network``: ``"mlp"``
(the default :class:`~torchrl_options.OptionsMLP` that ``discover_options`` builds), ``"mlp-module"`` (an
:class:`~torchrl_options.OptionsMLP` built here) or ``"conv"`` (a :class:`~torchrl_options.modules.GridConvOptions`).
For ``"mlp-module"`` and ``"conv"`` the modules are made by :func:`option_factory` and given to
``discover_options(options_factory=...)``, so they get the default modules' starts (segment starts, restarts):
``starts="factory"``, the default. ``starts="given"`` passes one module made from the seed as ``options=``
instead, trained from its random weights in one start: how rounds 1-4 of ``docs/experiments/minigrid.md`` ran
(their records have no ``starts`` entry).

Seed ``s`` uses the layouts ``1000 s, 1000 s + 1, ...`` (seed 0: the layouts of issue 50's probe) and seeds DDO
with ``s``.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable

import torch

from torchrl_options.checkpoints import scoped_seed

__all__ = ["NETWORKS", "option_factory", "segmentation_cell", "LAYOUTS_PER_SEED", "STARTS"]

logger = logging.getLogger(__name__)

NETWORKS = ("mlp", "mlp-module", "conv")
#: how a module of :func:`option_factory` starts: ``"factory"`` (``discover_options(options_factory=...)``, every
#: start a fresh module) or ``"given"`` (one module passed as ``options=``, one random start)
STARTS = ("factory", "given")
#: seed ``s`` draws its demonstrations from the layouts ``LAYOUTS_PER_SEED * s + i``
LAYOUTS_PER_SEED = 1000


def option_factory(network: str, num_options: int, *, num_actions: int = 7, in_features: int = 984,
                   num_cells=8, conv: dict | None = None, extra_features: int | None = None,
                   ) -> Callable[[], torch.nn.Module] | None:
    """A callable making fresh options modules of ``network`` (``None`` for ``"mlp"``: ``discover_options`` builds
    its default modules itself). For ``"conv"``, the observation is the one-hot view then ``extra_features``
    features (default: the direction's 4; with :func:`~torchrl_options.experiments.minigrid.with_previous_action`,
    4 + the number of actions).

    Examples:
        >>> make = option_factory("conv", 3)
        >>> type(make()).__name__, make().num_options
        ('GridConvOptions', 3)
        >>> option_factory("mlp", 3) is None
        True
    """
    from torchrl_options.checks import check_choice

    check_choice(network, "network", NETWORKS)
    if network == "mlp":
        return None
    if network == "mlp-module":
        from torchrl_options.modules import OptionsMLP

        return lambda: OptionsMLP(in_features, num_actions, num_options, num_cells=num_cells)
    from torchrl_options.envs.minigrid import DIRECTIONS, VIEW_CHANNELS
    from torchrl_options.modules import GridConvOptions

    extra = DIRECTIONS if extra_features is None else int(extra_features)
    view = int(round(((in_features - extra) / VIEW_CHANNELS) ** 0.5))
    if VIEW_CHANNELS * view * view + extra != in_features:
        raise ValueError(f"in_features must be {VIEW_CHANNELS} x view x view + extra_features ({extra}), "
                         f"got {in_features}.")
    return lambda: GridConvOptions(num_actions, num_options, channels=VIEW_CHANNELS, view_size=view,
                                   extra_features=extra, **(conv or {}))  # fmt: skip


def segmentation_cell(
    level: str,
    seed: int,
    *,
    method: dict | None = None,
    num_demonstrations: int = 100,
    demonstrations=None,
    return_options: bool = False,
) -> dict | tuple[dict, torch.nn.Module]:
    """Demonstrations of the bot on ``level`` (or ``demonstrations``), DDO with ``method``, ``segment``, scores.

    Args:
        level (str): a BabyAI level.
        seed (int): the seed (layouts and DDO; see the module docstring).

    Keyword Args:
        method (dict, optional): ``network`` (:data:`NETWORKS`, default ``"mlp"``), ``num_options`` (default 5),
            ``conv`` (keyword arguments of :class:`~torchrl_options.modules.GridConvOptions`), ``starts``
            (:data:`STARTS`, default ``"factory"``; not for ``"mlp"``), ``previous_action`` (bool, default
            ``False``: the options see the demonstrations of
            :func:`~torchrl_options.experiments.minigrid.with_previous_action`; the scores use the bot's own) and
            any other :func:`~torchrl_options.discover_options` keyword argument. ``{}``: issue 50's probe
            (``discover_options(data, num_options=5)`` with the defaults).
        num_demonstrations (int): bot episodes. Defaults to 100.
        demonstrations (TensorDict, optional): use these instead of generating them.
        return_options (bool): also return the discovered options module, as ``(record, options)``.

    Returns:
        A dict of plain data: ``level``, ``seed``, ``method``, ``num_steps``, ``fit`` (the log-likelihood per step,
        iterations, CPU seconds, DDO's warnings and option usage), ``labels`` (the Viterbi option of every valid
        step, one list per trajectory), ``action_agreement`` (the label accuracy of the options against the bot's
        actions, best matching: 1 when the options are the actions renamed), ``information`` (what the options track:
        :func:`~torchrl_options.experiments.minigrid.scoring.option_information`), and per granularity (``subgoal``,
        ``skill``) the scores of ``ddo`` and of the baselines, and ``composition`` (what each option holds, against
        the subgoal types and the skills).
    """
    from torchrl_options import discover_options, segment
    from torchrl_options.checks import check_choice
    from torchrl_options.envs.minigrid import DIRECTIONS, MINIGRID_ACTIONS
    from torchrl_options.experiments.minigrid.demonstrations import (
        bot_demonstrations,
        SKILLS,
        SUBGOAL_TYPES,
        with_previous_action,
    )
    from torchrl_options.experiments.minigrid.scoring import (
        baseline_scores,
        GRANULARITIES,
        option_composition,
        option_information,
        segmentation_scores,
    )

    method = dict(method or {})
    network = method.pop("network", "mlp")
    num_options = int(method.pop("num_options", 5))
    conv = method.pop("conv", None)
    starts = method.pop("starts", None)
    previous_action = method.pop("previous_action", False)
    if not isinstance(previous_action, bool):
        raise TypeError(f"method: previous_action must be a bool, got {previous_action!r}.")
    check_choice(network, "network", NETWORKS)
    if network == "mlp" and starts is not None:
        raise ValueError("method: starts is for the modules of option_factory (network 'mlp-module' or 'conv'); "
                         "the default 'mlp' modules always get discover_options' starts.")
    starts = "factory" if starts is None and network != "mlp" else starts
    if starts is not None:
        check_choice(starts, "starts", STARTS)
    if demonstrations is None:
        demonstrations = bot_demonstrations(level, num_demonstrations, first_seed=LAYOUTS_PER_SEED * seed).data
    labelled = demonstrations  # the bot's observations, for the scores
    data = with_previous_action(labelled) if previous_action else labelled
    factory = option_factory(network, num_options, in_features=int(data["observation"].shape[-1]),
                             num_cells=method.get("num_cells", 8), conv=conv,
                             extra_features=DIRECTIONS + len(MINIGRID_ACTIONS) if previous_action else None)  # fmt: skip
    modules: dict = {}
    if starts == "factory":
        modules["options_factory"] = factory  # called after discover_options seeds: the weights come from seed
        # the modules have all of MiniGrid's actions (the bot never takes "done"): tell DDO, not the record
        modules.setdefault("num_actions", method.pop("num_actions", int(factory().num_actions)))
    elif starts == "given":
        with scoped_seed(seed):  # the module's initial weights come from the seed
            modules["options"] = factory()
    # the factory's width (recorded); discover_options' num_cells describes its own default modules only
    num_cells = method.pop("num_cells", None) if factory is not None else None
    t0 = time.process_time()
    result = discover_options(data, num_options, seed=seed, progress=False, return_info=True, **modules, **method)
    seconds = time.process_time() - t0
    seg = segment(data, result)
    out = {
        "level": level,
        "seed": seed,
        "method": {"network": network, "num_options": num_options, **({"conv": conv} if conv else {}),
                   **({"starts": starts} if starts is not None else {}),
                   **({"previous_action": True} if previous_action else {}), **method,
                   **({"num_cells": num_cells} if num_cells is not None else {})},
        "num_steps": int(data["collector", "mask"].sum()),
        "fit": {
            "log_likelihood_per_step": result.final_log_likelihood_per_step,  # the last training record
            "model_log_likelihood_per_step": result.log_likelihood_per_step,  # the returned options' own
            "iterations": len(result.history),
            "cpu_seconds": seconds,
            "warnings": list(result.warnings),
            "option_usage": [float(u) for u in result.option_usage],
        },
    }
    mask = data["collector", "mask"]
    # the Viterbi labels of the valid steps, per trajectory, for analyses after the fact
    out["labels"] = [seg.options[i, : int(mask[i].sum())].tolist() for i in range(mask.shape[0])]
    actions = data["action"].reshape(mask.shape)
    out["action_agreement"] = segmentation_scores(seg.options, data.clone(False).set("action_label", actions),
                                                  label_key="action_label", switch_key="true_switch")["label_accuracy"]
    out["information"] = option_information(seg.options, labelled)
    for name, (label_key, switch_key) in GRANULARITIES.items():
        scores = {"ddo": segmentation_scores(seg.options, data, label_key=label_key, switch_key=switch_key)}
        scores.update(baseline_scores(data, label_key=label_key, switch_key=switch_key, seed=seed))
        names = SUBGOAL_TYPES if name == "subgoal" else SKILLS
        scores["composition"] = option_composition(seg.options, data, label_key=label_key, names=names,
                                                   num_options=num_options)  # fmt: skip
        out[name] = scores
    logger.info("%s seed %d %s: %s", level, seed, out["method"], {k: round(v, 3) for k, v in out["subgoal"]["ddo"].items()})
    return (out, result.options) if return_options else out
