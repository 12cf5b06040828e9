"""OptionHierarchy: the options of every level, their action spaces, and saving/loading the whole hierarchy."""
from __future__ import annotations

import os
from collections.abc import Sequence

from tensordict.nn import TensorDictModuleBase
from torch import nn

from torchrl_options.checkpoints import load_file
from torchrl_options.discovery.serialization import check_metadata, describe_payload, module_from_dict, module_to_dict, write_payload

__all__ = ["OptionHierarchy", "load_hierarchy", "save_hierarchy"]

_FORMAT = "torchrl_options/hierarchy-v1"


class OptionHierarchy(nn.Module):
    """The options of a multi-level hierarchy, level 1 (over primitive actions) first.

    Level ``j``'s options choose among ``A + K_1 + ... + K_{j-1}`` actions: the primitive actions, then the
    options of every lower level (Fox et al., 2017, section 4.3: "augment action space A <- A U H_d"). This is
    the layout of nested :class:`~torchrl_options.transforms.OptionExecutor` transforms: the level-``j``
    executor, appended above the level-``(j-1)`` one, sees that space as its primitive actions and exposes
    ``A + K_1 + ... + K_j`` to the policy above, so index ``A + K_1 + ... + K_{i-1} + k`` is option ``k`` of
    level ``i``.

    Args:
        num_actions (int): A, the number of primitive actions.
        levels (sequence of TensorDictModuleBase, optional): the options of levels 1, 2, ... Each writes
            ``option_logits`` ``[..., K_j, N_j]`` and ``termination_logits`` ``[..., K_j]``.

    Keyword Args:
        meta_controls (sequence, optional): the meta-control used when discovering each level (``None`` for
            uniform), kept for reference and saved with the hierarchy; execution does not use them.
        num_options (sequence of int, optional): ``K_j`` for modules without a ``num_options`` attribute.

    Raises:
        ValueError: when a level's module does not choose among ``A + K_1 + ... + K_{j-1}`` actions (checked
            through its ``num_actions`` attribute when it has one).

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.hierarchy import OptionHierarchy
        >>> h = OptionHierarchy(4, [OptionsMLP(2, 4, 3), OptionsMLP(2, 4 + 3, 2)])
        >>> h.num_levels, h.num_options, h.action_space_sizes
        (2, [3, 2], [4, 7, 9])
        >>> h.options(2).num_actions  # what the level-2 executor's options choose among
        7
    """

    def __init__(
        self,
        num_actions: int,
        levels: Sequence[TensorDictModuleBase] = (),
        *,
        meta_controls: Sequence[TensorDictModuleBase | None] | None = None,
        num_options: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        if isinstance(num_actions, bool) or not isinstance(num_actions, int) or num_actions < 1:
            raise ValueError(f"num_actions must be a positive int, got {num_actions!r}.")
        if isinstance(levels, (str, bytes, TensorDictModuleBase)) or not isinstance(levels, Sequence):
            raise TypeError(f"levels must be a sequence of options modules (level 1 first), got {type(levels).__name__}.")
        levels = list(levels)
        for name, seq in (("meta_controls", meta_controls), ("num_options", num_options)):
            if seq is not None and (isinstance(seq, (str, bytes)) or not isinstance(seq, Sequence)):
                raise TypeError(f"{name} must be None or a sequence with one entry per level, got {type(seq).__name__}.")
        if meta_controls is not None and len(meta_controls) != len(levels):
            raise ValueError(f"meta_controls has {len(meta_controls)} entries for {len(levels)} levels.")
        if num_options is not None and len(num_options) != len(levels):
            raise ValueError(f"num_options has {len(num_options)} entries for {len(levels)} levels.")
        self.num_actions = num_actions
        self.levels = nn.ModuleList()
        self.meta_controls = nn.ModuleList()
        self._num_options: list[int] = []
        for j, module in enumerate(levels):
            self.append(
                module,
                meta_control=None if meta_controls is None else meta_controls[j],
                num_options=None if num_options is None else num_options[j],
            )

    def append(
        self,
        options: TensorDictModuleBase,
        *,
        meta_control: TensorDictModuleBase | None = None,
        num_options: int | None = None,
    ) -> OptionHierarchy:
        """Adds a level on top: ``options`` must choose among :attr:`action_space_sizes` ``[-1]`` actions."""
        level = self.num_levels + 1
        expected = self.action_space_sizes[-1]
        if not isinstance(options, TensorDictModuleBase):
            raise TypeError(
                f"level {level}: the options must be a TensorDictModuleBase (writing option_logits and "
                f"termination_logits), got {type(options).__name__}."
            )
        if meta_control is not None and not isinstance(meta_control, TensorDictModuleBase):
            raise TypeError(
                f"level {level}: meta_control must be None or a TensorDictModuleBase, got {type(meta_control).__name__}."
            )
        k = num_options if num_options is not None else getattr(options, "num_options", None)
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(
                f"level {level}: cannot tell how many options the module has; pass num_options (got {k!r})."
            )
        n = getattr(options, "num_actions", None)
        if n is not None and n != expected:
            raise ValueError(f"level {level} options have num_actions={n}, but level-{level} options choose among "
                             f"{self._space_formula(level)} = {expected} actions.")
        k_meta = getattr(meta_control, "num_options", None)
        if k_meta is not None and k_meta != k:
            raise ValueError(f"level {level}: meta_control has num_options={k_meta}, the options have {k}.")
        self.levels.append(options)
        self.meta_controls.append(meta_control if meta_control is not None else _NoMetaControl())
        self._num_options.append(k)
        return self

    def _space_formula(self, level: int) -> str:
        return " + ".join(["A"] + [f"K{i}" for i in range(1, level)])

    @property
    def num_levels(self) -> int:
        """D, the number of levels."""
        return len(self.levels)

    @property
    def num_options(self) -> list[int]:
        """``[K_1, ..., K_D]``."""
        return list(self._num_options)

    @property
    def action_space_sizes(self) -> list[int]:
        """``[A, A + K_1, ..., A + K_1 + ... + K_D]``: entry ``j - 1`` is the space level-``j`` options choose
        among; the last one is the space a policy sees over the whole hierarchy (the top executor's)."""
        sizes = [self.num_actions]
        for k in self._num_options:
            sizes.append(sizes[-1] + k)
        return sizes

    def _check_level(self, level: int) -> None:
        if isinstance(level, bool) or not isinstance(level, int):
            raise TypeError(f"level must be an int (1-based), got {level!r} ({type(level).__name__}).")
        if not 1 <= level <= self.num_levels:
            if not self.num_levels:
                raise ValueError(f"the hierarchy has no level yet, got level {level}.")
            raise ValueError(f"level must be in [1, {self.num_levels}] (the hierarchy's levels), got {level}.")

    def options(self, level: int) -> TensorDictModuleBase:
        """The options module of ``level`` (1-based); its ``option_logits`` are over ``action_space_sizes[level-1]``."""
        self._check_level(level)
        return self.levels[level - 1]

    def meta_control(self, level: int) -> TensorDictModuleBase | None:
        """The meta-control used when discovering ``level`` (``None``: uniform)."""
        self._check_level(level)
        m = self.meta_controls[level - 1]
        return None if isinstance(m, _NoMetaControl) else m

    def option_index(self, level: int, option: int) -> int:
        """The action index of ``option`` of ``level`` in the augmented spaces above it.

        Examples:
            >>> from torchrl_options import OptionsMLP
            >>> OptionHierarchy(4, [OptionsMLP(2, 4, 3), OptionsMLP(2, 7, 2)]).option_index(2, 1)
            8
        """
        self._check_level(level)
        if isinstance(option, bool) or not isinstance(option, int):
            raise TypeError(f"option must be an int, got {option!r} ({type(option).__name__}).")
        if not 0 <= option < self.num_options[level - 1]:
            raise ValueError(
                f"level {level} has {self.num_options[level - 1]} options (0 .. {self.num_options[level - 1] - 1}), "
                f"got option {option}."
            )
        return self.action_space_sizes[level - 1] + option

    def executors(self, **kwargs) -> list:
        """One :class:`~torchrl_options.transforms.OptionExecutor` per level, to append to an env in this order
        (level 1 first). ``kwargs`` go to every executor (``greedy=True``, say)."""
        from torchrl_options.transforms import OptionExecutor

        return [
            OptionExecutor(self.options(j), num_options=self.num_options[j - 1], level=j, **kwargs)
            for j in range(1, self.num_levels + 1)
        ]

    def forward(self, *args, **kwargs):
        raise NotImplementedError(
            "OptionHierarchy is a container: run level j with hierarchy.options(j), or the whole hierarchy in an "
            "env with hierarchy.executors()."
        )

    def extra_repr(self) -> str:
        return f"num_actions={self.num_actions}, num_options={self.num_options}"

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike, *, metadata: dict | None = None) -> None:
        """Saves the whole hierarchy (configurations and weights of every level) to ``path``; see :func:`save_hierarchy`."""
        save_hierarchy(self, path, metadata=metadata)

    @classmethod
    def load(cls, path: str | os.PathLike, *, map_location=None) -> OptionHierarchy:
        """Loads a hierarchy written by :meth:`save`."""
        return load_hierarchy(path, map_location=map_location)


class _NoMetaControl(nn.Module):
    """Placeholder for a uniform meta-control in the ``meta_controls`` list."""


def save_hierarchy(hierarchy: OptionHierarchy, path: str | os.PathLike, *, metadata: dict | None = None) -> None:
    """Saves an :class:`OptionHierarchy` as plain data (loads with ``weights_only=True``).

    Every level must be one of this package's modules (rebuilt from its configuration).

    Examples:
        >>> import os, tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options import OptionsMLP
        >>> from torchrl_options.hierarchy import OptionHierarchy, load_hierarchy, save_hierarchy
        >>> h = OptionHierarchy(4, [OptionsMLP(2, 4, 3), OptionsMLP(2, 7, 2)])
        >>> path = os.path.join(tempfile.mkdtemp(), "hierarchy.pt")
        >>> save_hierarchy(h, path)
        >>> loaded = load_hierarchy(path)
        >>> td = TensorDict({"observation": torch.randn(5, 2)}, [5])
        >>> torch.equal(h.options(2)(td.clone())["option_logits"], loaded.options(2)(td.clone())["option_logits"])
        True
    """
    if not isinstance(hierarchy, OptionHierarchy):
        raise TypeError(f"save_hierarchy: hierarchy must be an OptionHierarchy, got {type(hierarchy).__name__}.")
    payload = {
        "format": _FORMAT,
        "num_actions": hierarchy.num_actions,
        "num_options": hierarchy.num_options,
        "levels": [module_to_dict(m) for m in hierarchy.levels],
        "meta_controls": [
            None if (m := hierarchy.meta_control(j)) is None else module_to_dict(m)
            for j in range(1, hierarchy.num_levels + 1)
        ],
        "metadata": check_metadata(metadata),
    }
    write_payload(payload, path, "hierarchy")


def load_hierarchy(path: str | os.PathLike, *, map_location=None, with_metadata: bool = False):
    """Loads a hierarchy saved by :func:`save_hierarchy` (``(hierarchy, metadata)`` with ``with_metadata``).

    Raises:
        ValueError: naming the file, if it is missing (also a ``FileNotFoundError``), empty, truncated or
            corrupt, needs pickle, is not a hierarchy file of this package, or its stored configurations disagree
            with its weights or with each other. Loads with ``weights_only=True``.

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import OptionsMLP
        >>> path = os.path.join(tempfile.mkdtemp(), "h.pt")
        >>> save_hierarchy(OptionHierarchy(4, [OptionsMLP(2, 4, 3)]), path, metadata={"seed": 0})
        >>> hierarchy, metadata = load_hierarchy(path, with_metadata=True)
        >>> hierarchy.num_options, metadata
        ([3], {'seed': 0})
    """
    payload = load_file(path, what="hierarchy", map_location=map_location)
    source = os.fspath(path)
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise ValueError(
            f"{source}: not a hierarchy file written by torchrl_options save_hierarchy (expected format {_FORMAT!r}, "
            f"got {describe_payload(payload)})."
        )
    missing = [k for k in ("num_actions", "num_options", "levels", "meta_controls") if k not in payload]
    if missing:
        raise ValueError(f"{source}: the hierarchy file lacks {missing}.")
    if not isinstance(payload["levels"], list) or not isinstance(payload["meta_controls"], list):
        raise ValueError(f"{source}: 'levels' and 'meta_controls' must be lists.")
    levels = [module_from_dict(e, source) for e in payload["levels"]]
    metas = [None if e is None else module_from_dict(e, source) for e in payload["meta_controls"]]
    try:
        hierarchy = OptionHierarchy(
            payload["num_actions"], levels, meta_controls=metas, num_options=payload["num_options"]
        )
    except (ValueError, TypeError) as err:
        raise ValueError(f"{source}: the stored hierarchy is inconsistent: {err}") from None
    if with_metadata:
        return hierarchy, payload.get("metadata", {})
    return hierarchy
