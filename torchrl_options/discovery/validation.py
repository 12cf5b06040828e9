"""Input checks of the discovery entry points (:func:`~torchrl_options.discover_options`,
:func:`~torchrl_options.as_trajectory_batch`, :func:`~torchrl_options.discover_hierarchy`,
:func:`~torchrl_options.segment`): every bad input is refused at the door with a ``ValueError`` (``TypeError`` for
a wrong type) that names the argument or key, what was expected and what came.

The checks read shapes and dtypes, plus one pass over the valid steps' values (non-finite observations, action
range) and one forward of the options module on a single step: cheap next to one E-step.
"""
from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

__all__ = [
    "check_factories",
    "check_meta_control_module",
    "check_options_module",
    "check_step_data",
    "check_trajectories",
]

_MASK = ("collector", "mask")


def _steps(td: TensorDictBase) -> int:
    # TensorDict.numel() is never below 1 (a [0] tensordict has numel() == 1): count from the batch size
    return int(math.prod(td.batch_size))


def check_trajectories(trajectories: Any, *, trajectory_key: NestedKey | None = None, mask_key: NestedKey = _MASK) -> None:
    """Checks what :func:`~torchrl_options.as_trajectory_batch` accepts, before it pads or splits anything."""
    if isinstance(trajectories, TensorDictBase):
        td = trajectories
        if _steps(td) == 0:
            raise ValueError(f"trajectories is empty (batch_size {list(td.batch_size)}): discovery needs at least one step.")
        if td.ndim not in (1, 2):
            raise ValueError(f"trajectories must be [B, T] (or one [T] trajectory), got batch_size {list(td.batch_size)}.")
        if trajectory_key is not None and td.ndim == 1 and trajectory_key not in td.keys(include_nested=True):
            raise ValueError(f"the sample has no {trajectory_key!r} entry (trajectory_key).")
        mask = td.get(mask_key, None)
        if mask is not None:
            _check_mask(mask, td.batch_size, mask_key)
        return
    if isinstance(trajectories, (str, bytes)) or not isinstance(trajectories, Sequence):
        raise TypeError(
            "trajectories must be a TensorDict ([B, T] or [T]) or a list of [T_i] TensorDicts, got "
            f"{type(trajectories).__name__}."
        )
    if len(trajectories) == 0:
        raise ValueError("trajectories is an empty list: discovery needs at least one trajectory.")
    keys0 = None
    for i, t in enumerate(trajectories):
        if not isinstance(t, TensorDictBase):
            raise TypeError(f"trajectories[{i}] must be a [T] TensorDict, got {type(t).__name__}.")
        if t.ndim != 1:
            raise ValueError(f"trajectories[{i}] must be a [T] TensorDict (one trajectory), got batch_size {list(t.batch_size)}.")
        if _steps(t) == 0:
            raise ValueError(f"trajectories[{i}] is empty (0 steps): every trajectory needs at least one step.")
        keys = set(t.keys(include_nested=True, leaves_only=True))
        if keys0 is None:
            keys0 = keys
        elif keys != keys0:
            raise ValueError(
                f"trajectories[{i}] has other entries than trajectories[0]: missing {sorted(map(str, keys0 - keys))}, "
                f"extra {sorted(map(str, keys - keys0))}."
            )
        mask = t.get(mask_key, None)
        if mask is not None:
            _check_mask(mask, t.batch_size, f"trajectories[{i}] {mask_key!r}")


def _check_mask(mask: torch.Tensor, batch_size: torch.Size, name: Any) -> None:
    if mask.dtype != torch.bool:
        raise ValueError(f"the mask {name!r} must be bool (True at valid steps), got dtype {mask.dtype}.")
    shape = tuple(mask.shape)
    if shape not in (tuple(batch_size), (*batch_size, 1)):
        raise ValueError(f"the mask {name!r} must have shape {list(batch_size)}, got {list(shape)}.")


def check_step_data(
    data: TensorDictBase,
    *,
    obs_keys: Sequence[NestedKey],
    action_key: NestedKey,
    action_space: str = "categorical",
    num_actions: int | None = None,
    mask_key: NestedKey = _MASK,
    terminal_key: NestedKey = ("next", "terminated"),
) -> None:
    """Checks a ``[B, T]`` batch (after :func:`~torchrl_options.as_trajectory_batch`): entries present, shapes that
    agree, bool mask with a valid step per row, finite observations, actions in range."""
    B, T = data.batch_size
    keys = set(data.keys(include_nested=True, leaves_only=True))
    mask = data.get(mask_key)
    _check_mask(mask, data.batch_size, mask_key)
    mask = mask.reshape(B, T)
    empty = (~mask.any(1)).nonzero()
    if empty.numel():
        raise ValueError(f"trajectory {int(empty[0])} has no valid step (its {mask_key!r} is all False).")
    if action_key not in keys:
        raise ValueError(f"the trajectories have no {action_key!r} entry (action_key); entries: {sorted(map(str, keys))}.")
    for key in obs_keys:
        if key not in data.keys(include_nested=True):
            raise ValueError(f"the trajectories have no {key!r} entry (obs_keys); entries: {sorted(map(str, keys))}.")
        obs = data.get(key)
        nxt_key = ("next", *((key,) if isinstance(key, str) else key))
        nxt = data.get(nxt_key, None)
        if nxt is None:
            raise ValueError(
                f"the trajectories have no {nxt_key!r} entry: an option's termination is evaluated at the next "
                f"observation, so every obs_keys entry {key!r} needs its {nxt_key!r} (TorchRL's rollouts and "
                "collectors write it)."
            )
        if nxt.shape != obs.shape:
            raise ValueError(
                f"{nxt_key!r} must have the shape of {key!r}, {list(obs.shape)}, got {list(nxt.shape)}."
            )
        if obs.is_floating_point():
            bad = ~torch.isfinite(obs.reshape(B, T, -1)).all(-1) & mask
            if bad.any():
                b, t = (int(i) for i in bad.nonzero()[0])
                raise ValueError(f"{key!r} holds NaN or inf at trajectory {b}, step {t} (a valid step).")
    term = data.get(terminal_key, None)
    if term is not None and tuple(term.shape) not in ((B, T), (B, T, 1)):
        raise ValueError(f"{terminal_key!r} must have shape [B, T] or [B, T, 1] = {[B, T]}, got {list(term.shape)}.")
    action = data.get(action_key)
    if tuple(action.shape[:2]) != (B, T):
        raise ValueError(f"{action_key!r} must be [B, T, ...] = {[B, T]}, got {list(action.shape)}.")
    if action_space == "categorical" and action.ndim == 2 or (action.ndim == 3 and action.shape[-1] == 1 and action_space == "categorical"):
        valid = action.reshape(B, T)[mask]
        if valid.is_floating_point() and not torch.equal(valid, valid.round()):
            raise ValueError(
                f"{action_key!r} holds non-integer values ({action.dtype}) but action_space='categorical': pass integer "
                "actions, or action_space='continuous'."
            )
        if (valid < 0).any():
            raise ValueError(f"{action_key!r} holds negative actions ({int(valid.min())}): actions are 0 .. A-1.")
        if num_actions is not None and (valid >= num_actions).any():
            raise ValueError(f"{action_key!r} holds action {int(valid.max())}, outside [0, num_actions={num_actions}).")
    if action_space == "continuous" and not action.is_floating_point():
        raise ValueError(f"action_space='continuous' needs float actions, {action_key!r} has dtype {action.dtype}.")
    if action_space == "continuous" and action.ndim == 2:
        raise ValueError(
            f"action_space='continuous' needs {action_key!r} of shape [B, T, D] (D the action dimension), got "
            f"{list(action.shape)}: for one-dimensional actions add the trailing dimension (action.unsqueeze(-1))."
        )


def _one_step_output(module: Any, data: TensorDictBase, name: str, key: str) -> tuple[TensorDictBase, torch.Tensor]:
    """``module``'s output on the first step of a ``[B, T]`` batch (no gradients) and its ``key`` entry ``[..., K]``;
    a module that cannot read the batch is refused with the per-step shapes of the entries it reads."""
    if not isinstance(module, TensorDictModuleBase):
        raise TypeError(f"{name} must be a TensorDictModuleBase, got {type(module).__name__}.")
    step = data[:1, :1].clone(False)
    try:
        with torch.no_grad():
            out = module(step.to(next(iter(module.parameters()), torch.empty(0)).device))
    except (RuntimeError, KeyError, ValueError, IndexError) as err:
        detail = " ".join(str(err).split())[:200]
        shapes = {str(k): list(step.get(k).shape[2:]) for k in getattr(module, "in_keys", []) if k in step.keys(True)}
        raise ValueError(
            f"the {name} module cannot read the trajectories (per-step entry shapes {shapes}; another observation "
            f"size than it was built for?): {type(err).__name__}: {detail}"
        ) from None
    entry = out.get(key, None)
    if entry is None:
        raise ValueError(f"the {name} module must write {key!r} [..., K]; it wrote {sorted(map(str, out.keys(True)))}.")
    return out, entry


def check_options_module(
    options: TensorDictModuleBase,
    data: TensorDictBase,
    num_options: int | None,
    *,
    num_actions: int | None = None,
    action_space: str = "categorical",
    name: str = "options",
) -> int:
    """Runs ``options`` on one step of ``data`` and checks what it writes against ``num_options`` (and
    ``num_actions``): a module of another K, or one that cannot read the observations, is refused here. Returns the
    module's number of options K."""
    out, term = _one_step_output(options, data, name, "termination_logits")
    if num_options is not None and int(term.shape[-1]) != num_options:
        raise ValueError(f"num_options={num_options} but the {name} module has K={int(term.shape[-1])} options.")
    logits = out.get("option_logits", None)
    if action_space == "categorical" and logits is not None and num_actions is not None and logits.shape[-1] != num_actions:
        raise ValueError(f"num_actions={num_actions} but the {name} module has A={int(logits.shape[-1])} actions.")
    return int(term.shape[-1])


def _takes_keyword(factory: Callable[..., Any], name: str) -> bool:
    try:
        parameters = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # a builtin without a signature: let the call tell
        return True
    return any(p.kind is p.VAR_KEYWORD or (p.name == name and p.kind is not p.POSITIONAL_ONLY) for p in parameters)


def check_factories(
    options: Any,
    options_factory: Any,
    meta_control: Any,
    meta_control_factory: Any,
    *,
    init_scale: Any = None,
    num_cells: Any = 8,
) -> None:
    """Checks :func:`~torchrl_options.discover_options`' ``options_factory`` and ``meta_control_factory``: callables
    (not module instances: those go to ``options`` / ``meta_control``), not both an options module and a factory,
    a meta-control factory only with ``meta_control="learned"``, ``init_scale`` only for the default modules, and
    factories that take ``num_cells`` with ``num_cells="auto"``.

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> check_factories(None, lambda: OptionsMLP(2, 3, 4), "uniform", None)
        >>> check_factories(OptionsMLP(2, 3, 4), None, "uniform", None, init_scale=0.3)
        Traceback (most recent call last):
        ...
        ValueError: init_scale sets the starting standard deviation of the default Gaussian options; the options given (options=OptionsMLP) are built by the caller: give init_scale to the module (GaussianOptionsMLP(..., init_scale=...)) or leave it None.
    """
    for name, factory, instead in (("options_factory", options_factory, "options"),
                                   ("meta_control_factory", meta_control_factory, "meta_control")):  # fmt: skip
        if factory is None:
            continue
        if isinstance(factory, TensorDictModuleBase):
            raise TypeError(
                f"{name} must be a callable that builds a fresh module on each call, got a module instance "
                f"({type(factory).__name__}): pass it as {instead}= to train that one module."
            )
        if not callable(factory):
            raise TypeError(f"{name} must be a callable returning a fresh module, got {type(factory).__name__}.")
        if isinstance(num_cells, str) and not _takes_keyword(factory, "num_cells"):
            raise ValueError(
                f"num_cells='auto' fits modules of each width in AUTO_WIDTHS: {name} must take a num_cells keyword "
                f"(called as {name}(num_cells=width)); {getattr(factory, '__name__', type(factory).__name__)} does not."
            )
    if options is not None and options_factory is not None:
        raise ValueError(
            "give options (one module, trained once) or options_factory (a fresh module per start), not both."
        )
    if meta_control_factory is not None and not (isinstance(meta_control, str) and meta_control == "learned"):
        raise ValueError(
            "meta_control_factory builds the learned meta-control of each start: it needs meta_control='learned', "
            f"got meta_control={meta_control if isinstance(meta_control, str) else type(meta_control).__name__!r}."
        )
    if init_scale is not None and (options is not None or options_factory is not None):
        given = f"options={type(options).__name__}" if options is not None else "options_factory"
        raise ValueError(
            "init_scale sets the starting standard deviation of the default Gaussian options; the options given "
            f"({given}) are built by the caller: give init_scale to the module (GaussianOptionsMLP(..., "
            "init_scale=...)) or leave it None."
        )


def check_meta_control_module(
    meta_control: Any, data: TensorDictBase, num_options: int, *, name: str = "meta_control"
) -> None:
    """Runs a meta-control module on one step of ``data`` and checks that it writes ``meta_logits`` ``[..., K]``."""
    _, logits = _one_step_output(meta_control, data, name, "meta_logits")
    if logits.shape[-1] != num_options:
        raise ValueError(f"num_options={num_options} but the {name} module writes {logits.shape[-1]} meta_logits.")
