"""The conditions of the Atari RAM experiment: their names (a small grammar), what each means, and a sweep's cells.

``"A"`` is the paper's baseline (phase 1's DQN continued with actions only), ``"A0"`` a control (actions only from a
reset Q-function), and ``"H1"`` followed by any of :data:`OPTION_FLAGS` (in that order) an options condition: see
:mod:`torchrl_options.experiments.atari`.
"""
from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

from torchrl_options.checks import check_int
from torchrl_options.experiments.sweep import Cell

__all__ = ["CONDITIONS", "OPTION_FLAGS", "atari_cells"]

#: what may follow ``"H1"`` in a condition's name, in this order: ``w`` options added to phase 1's DQN (no reset),
#: ``g`` options act greedily, ``i`` intra-option transitions for the primitive actions, ``s`` option suffixes
OPTION_FLAGS = ("w", "g", "i", "s")
CONDITIONS = ("A", "A0", "H1") + tuple(
    "H1" + "".join(letters)
    for n in range(1, len(OPTION_FLAGS) + 1)
    for letters in itertools.combinations(OPTION_FLAGS, n)
)


@dataclass(frozen=True)
class _OptionFlags:
    warm: bool
    greedy: bool
    intra: bool
    suffixes: bool


def _option_flags(condition: str) -> _OptionFlags | None:
    """The flags of an options condition (``"H1"`` then any of :data:`OPTION_FLAGS`, in order); ``None`` for ``A``
    and ``A0``."""
    if not condition.startswith("H1"):
        return None
    rest = condition[2:]
    return _OptionFlags(warm="w" in rest, greedy="g" in rest, intra="i" in rest, suffixes="s" in rest)


def _describe(condition: str) -> str:
    flags = _option_flags(condition)
    if flags is None:
        baselines = {"A": "the phase-1 DQN continued with actions only", "A0": "DQN over actions only from a reset Q-function"}
        return baselines[condition]
    text = "DQN over actions + DDO options" + (
        ", started from phase 1's DQN (output layer widened, replay kept)" if flags.warm else " from a reset Q-function"
    )
    if flags.greedy:
        text += ", each option acting with the argmax of its control policy"
    if flags.intra:
        text += ", the primitive actions' values also learned from the steps options take"
    if flags.suffixes:
        text += ", the options' values also learned from every step they run (option suffixes)"
    return text


def atari_cells(games: Sequence[str], seeds: Sequence[int] | int, conditions: Sequence[str] = ("A", "H1")) -> list[Cell]:
    """The cells of a sweep, conditions outermost: the first cells of a pool then run the phases 1 and 2 of
    different seeds in parallel, and the other condition's cells find them cached (rather than wait on a lock).

    Examples:
        >>> [c.name for c in atari_cells(["Pooyan"], 2)]
        ['Pooyan-A-seed0', 'Pooyan-A-seed1', 'Pooyan-H1-seed0', 'Pooyan-H1-seed1']

    Raises:
        ValueError: a condition not in :data:`CONDITIONS` (``A``, ``A0``, or ``H1`` followed by any of ``w``, ``g``,
            ``i``, ``s`` in that order), or none.
    """
    if isinstance(games, str) or not isinstance(games, Sequence) or not games:
        raise ValueError(f"games must be a non-empty list of game names (e.g. ['Pong']), got {games!r}.")
    if isinstance(conditions, str):
        raise ValueError(f"conditions must be a non-empty list of {CONDITIONS}, got the string {conditions!r}.")
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad or not conditions:
        raise ValueError(f"conditions must be a non-empty list of {CONDITIONS}, got {list(conditions)}.")
    if isinstance(seeds, int) and not isinstance(seeds, bool):
        check_int(seeds, "seeds", minimum=1)
    elif isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence) or not seeds:
        raise ValueError(f"seeds must be a count >= 1 or a non-empty list of seeds, got {seeds!r}.")
    seeds = range(seeds) if isinstance(seeds, int) else seeds
    return [Cell(g, c, int(s)) for c in conditions for g in games for s in seeds]
