"""Entry names shared by the option transforms, and the done entries they follow.

An env's done entries may be nested and several (TorchRL's multi-agent and multi-task envs: a root ``"done"``
of shape ``[*B, 1]`` beside an ``("agents", "done")`` of shape ``[*B, n_agents, 1]``), each with its partial-reset
flag ``"_reset"`` next to it. :func:`done_keys_for` finds them the way TorchRL's
:class:`~torchrl.envs.transforms.StepCounter` does (a leaf name placed next to each of the env's reset keys), and
:class:`FlagToState` maps such a flag, whatever its nesting level, onto a transform's state entry of another
shape.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Composite

__all__ = [
    "FlagToState",
    "done_key_arguments",
    "done_keys_for",
    "followed_done_entries",
    "level_key",
    "reset_key",
    "sibling_key",
]


def level_key(name: str, level: int) -> str:
    """The name of an executor's entry at ``level``: ``name`` at level 1, ``name_L`` at level ``L > 1``.

    Examples:
        >>> level_key("option", 1), level_key("option", 2)
        ('option', 'option_2')
    """
    return name if level == 1 else f"{name}_{level}"


def sibling_key(key: NestedKey, name: str) -> NestedKey:
    """``name`` next to ``key``: ``"_reset"`` for ``"done"``, ``(..., "_reset")`` for ``(..., "done")``.

    Examples:
        >>> sibling_key("done", "truncated"), sibling_key(("agents", "done"), "_reset")
        ('truncated', ('agents', '_reset'))
    """
    key = unravel_key(key)
    return name if isinstance(key, str) else (*key[:-1], name)


def reset_key(done_key: NestedKey) -> NestedKey:
    """The partial-reset flag of a done entry (TorchRL's ``"_reset"`` next to it).

    Examples:
        >>> reset_key("done"), reset_key(("agent", "done"))
        ('_reset', ('agent', '_reset'))
    """
    return sibling_key(done_key, "_reset")


def done_key_arguments(done_key: NestedKey | Sequence[NestedKey], owner: str) -> dict[str, NestedKey]:
    """A transform's ``done_key`` argument by name, for its key checks: ``{"done_key": key}``, or
    ``{"done_key[i]": key}`` for a list.

    Raises:
        ValueError: an empty list.

    Examples:
        >>> done_key_arguments("done", "X"), done_key_arguments(["done", ("agents", "done")], "X")
        ({'done_key': 'done'}, {'done_key[0]': 'done', 'done_key[1]': ('agents', 'done')})
    """
    if not isinstance(done_key, list):
        return {"done_key": done_key}
    if not done_key:
        raise ValueError(f"{owner}: done_key must name at least one done entry, got [].")
    return {f"done_key[{i}]": key for i, key in enumerate(done_key)}


def done_keys_for(
    done_key: NestedKey | Sequence[NestedKey],
    done_spec_keys: Sequence[NestedKey],
    reset_keys: Sequence[NestedKey],
    owner: str,
) -> list[NestedKey]:
    """The done entries named by ``done_key`` in an env with the done entries ``done_spec_keys``.

    A string is a leaf name, placed next to each of the env's ``reset_keys`` (``env.reset_keys``) as TorchRL's
    ``StepCounter`` places its ``truncated_key``: ``"done"`` names the root ``"done"`` and every nested
    ``(..., "done")`` of the env. A tuple of strings names one nested entry. A list names exactly the entries it
    holds (a string in it is a root entry). Every entry named must be in the done spec.

    Raises:
        ValueError: a key naming no done entry of the env.

    Examples:
        >>> done_keys_for("done", ["done", "terminated", ("agents", "done")], ["_reset", ("agents", "_reset")], "X")
        ['done', ('agents', 'done')]
        >>> done_keys_for(["done"], ["done", "terminated", ("agents", "done")], ["_reset", ("agents", "_reset")], "X")
        ['done']
    """
    nested = isinstance(done_key, tuple) and all(isinstance(part, str) for part in done_key)
    leaf_name = isinstance(done_key, str)
    names = [done_key] if leaf_name or nested else list(done_key)
    available = [unravel_key(k) for k in done_spec_keys]
    found: list[NestedKey] = []
    for name in names:
        name = unravel_key(name)
        if leaf_name:
            candidates = [name if isinstance(r, str) else (*r[:-1], name) for r in map(unravel_key, reset_keys)]
            candidates = [c for c in candidates if c in available] or ([name] if name in available else [])
        else:
            candidates = [name] if name in available else []
        if not candidates:
            raise ValueError(
                f"{owner}: done_key {name!r} names no entry of the env's done spec ({available})."
            )
        found.extend(c for c in candidates if c not in found)
    return found


def _without_trailing_one(shape: torch.Size) -> torch.Size:
    return shape[:-1] if len(shape) and shape[-1] == 1 else shape


def followed_done_entries(
    transform: Any, done_key: NestedKey | Sequence[NestedKey], owner: str
) -> tuple[list[NestedKey], Composite]:
    """The done entries a transform follows in the env it is appended to (``done_key`` read by
    :func:`done_keys_for` against that env's done spec and reset keys), and that done spec.

    Raises:
        RuntimeError: a transform not appended to an env.
        ValueError: a ``done_key`` naming no done entry of the env.
    """
    parent = transform.parent
    if parent is None:
        raise RuntimeError(f"{owner} must be appended to an environment.")
    done_spec = parent.full_done_spec
    return done_keys_for(done_key, list(done_spec.keys(True, True)), parent.reset_keys, owner), done_spec


class FlagToState:
    """Maps a boolean flag of one shape (a done or ``"_reset"`` entry) onto a state entry of another shape.

    The flag has the shape ``flag_shape`` of its done spec (usually ``[*B, 1]``, or ``[*B, n_agents, 1]`` for an
    agent-level one), the state the shape ``state_shape`` (a transform's entry, e.g. the shape of the action).
    Flags with as many elements are reshaped; a coarser flag (its dims, a trailing ``1`` dropped, a prefix of the
    state's: a root done for a per-agent state) is broadcast over the state's extra dims; a finer one (the
    state's dims a prefix of its own: a per-agent done for a root state) is reduced with ``any`` over its extra
    dims, as TorchRL reduces a finer ``"_reset"`` when it merges a partial reset.

    Raises:
        ValueError: shapes that relate in none of these ways.

    Examples:
        >>> import torch
        >>> root = FlagToState((2, 1), (2, 3), "done", "X")  # a root done for 3 agents
        >>> root(torch.tensor([[True], [False]]))
        tensor([[ True,  True,  True],
                [False, False, False]])
        >>> agents = FlagToState((2, 3, 1), (2,), ("agents", "done"), "X")  # per-agent dones for a root state
        >>> agents(torch.tensor([[[False], [True], [False]], [[False], [False], [False]]]))
        tensor([ True, False])
    """

    def __init__(self, flag_shape: Sequence[int], state_shape: Sequence[int], key: NestedKey, owner: str):
        flag_shape, state_shape = torch.Size(flag_shape), torch.Size(state_shape)
        self.state_shape = state_shape
        core, state_core = _without_trailing_one(flag_shape), _without_trailing_one(state_shape)
        if flag_shape == state_shape:
            self.mode = "same"
        elif flag_shape.numel() == state_shape.numel():
            self.mode = "reshape"
        elif len(core) < len(state_core) and state_core[: len(core)] == core:
            self.mode = "broadcast"
            self.view = torch.Size((*core, *(1,) * (len(state_shape) - len(core))))
        elif len(core) > len(state_core) and core[: len(state_core)] == state_core:
            self.mode = "any"
            self.core, self.kept = core, len(state_core)
        else:
            raise ValueError(
                f"{owner}: the done entry {key!r} has shape {tuple(flag_shape)}, which does not match the "
                f"shape {tuple(state_shape)} of the state it should reset (neither the same elements, nor a "
                "prefix of it, nor extending it)."
            )

    def __call__(self, flag: torch.Tensor) -> torch.Tensor:
        if flag.shape == self.state_shape:
            return flag
        mode = self.mode
        if mode == "broadcast":
            return flag.reshape(self.view).expand(self.state_shape)
        if mode == "any":
            return flag.reshape(self.core).flatten(self.kept).any(-1).reshape(self.state_shape)
        return flag.reshape(self.state_shape)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(mode={self.mode!r}, state_shape={tuple(self.state_shape)})"
