"""Argument checks shared by every part of the package: the ground floor, importing nothing of the package.

Every public entry point refuses bad input at its door with a ``TypeError`` (wrong type) or ``ValueError`` (wrong
value) that names the argument, says what was expected and shows what came. These helpers write those messages
the same way everywhere; a subpackage imports them from here (never from another subpackage's private module).

Examples:
    >>> from torchrl_options.checks import check_int, check_number, check_distinct_keys
    >>> check_int(3, "num_options", minimum=1)
    >>> check_number(0.5, "gamma", lo=0.0, hi=1.0)
    >>> check_distinct_keys({"reward_key": ("next", "reward"), "steps_key": ("next", "reward")}, "SMDPTransitions")
    Traceback (most recent call last):
    ...
    ValueError: SMDPTransitions: reward_key and steps_key are both ('next', 'reward'); one would overwrite the other's entry. Give them different keys.
"""
from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from tensordict.utils import NestedKey, unravel_key

__all__ = [
    "check_bool",
    "check_choice",
    "check_distinct_keys",
    "check_int",
    "check_nested_key",
    "check_number",
    "check_positive_number",
]


def check_int(
    value: Any, name: str, *, minimum: int | None = None, maximum: int | None = None, allow_none: bool = False
) -> None:
    """Refuses a non-int (``TypeError``; ``bool`` and ``2.0`` are not ints) or one outside
    ``[minimum, maximum]`` (``ValueError``).

    Examples:
        >>> check_int(3, "num_options", minimum=1)
        >>> check_int(2.5, "num_options", minimum=1)
        Traceback (most recent call last):
        ...
        TypeError: num_options must be an int, got 2.5 (float).
        >>> check_int(-1, "victim", minimum=0, maximum=3)
        Traceback (most recent call last):
        ...
        ValueError: victim must be an int in [0, 3], got -1.
    """
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int{' or None' if allow_none else ''}, got {value!r} ({type(value).__name__}).")
    low = minimum is not None and value < minimum
    high = maximum is not None and value > maximum
    if low or high:
        if minimum is not None and maximum is not None:
            raise ValueError(f"{name} must be an int in [{minimum}, {maximum}], got {value}.")
        if minimum is not None:
            raise ValueError(f"{name} must be an int >= {minimum}, got {value}.")
        raise ValueError(f"{name} must be an int <= {maximum}, got {value}.")


def check_number(
    value: Any,
    name: str,
    *,
    lo: float = -math.inf,
    hi: float = math.inf,
    lo_open: bool = False,
    hi_open: bool = False,
    allow_none: bool = False,
) -> None:
    """Refuses a non-number (``TypeError``; ``bool`` and strings are not numbers), NaN, or a number outside the
    interval from ``lo`` to ``hi`` (closed ends unless ``lo_open`` / ``hi_open``) (``ValueError``).

    Examples:
        >>> check_number(0.9, "gamma", lo=0, hi=1)
        >>> check_number(float("nan"), "min_usage", lo=0, hi=1)
        Traceback (most recent call last):
        ...
        ValueError: min_usage must be a number in [0, 1], got nan.
        >>> check_number("0.1", "lr", lo=0, lo_open=True)
        Traceback (most recent call last):
        ...
        TypeError: lr must be a number, got '0.1' (str).
    """
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number{' or None' if allow_none else ''}, got {value!r} ({type(value).__name__}).")
    value = float(value)
    inside = (lo < value if lo_open else lo <= value) and (value < hi if hi_open else value <= hi)
    if math.isnan(value) or not inside:
        if lo == -math.inf and hi == math.inf:
            raise ValueError(f"{name} must be a number, got {value}.")
        if hi == math.inf:
            what = f"> {lo:g}" if lo_open else f">= {lo:g}"
        elif lo == -math.inf:
            what = f"< {hi:g}" if hi_open else f"<= {hi:g}"
        else:
            what = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise ValueError(f"{name} must be a number {what}, got {value:g}.")


def check_positive_number(value: Any, name: str) -> None:
    """Refuses anything but a finite number above 0 (``ValueError``; ``bool`` and strings are not numbers).

    Examples:
        >>> check_positive_number(0.03, "lr")
        >>> check_positive_number(float("nan"), "lr")
        Traceback (most recent call last):
        ...
        ValueError: lr must be a positive finite number, got nan.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 < float(value) < float("inf"):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}.")


def check_bool(value: Any, name: str) -> None:
    """Refuses anything but ``True`` / ``False`` (``TypeError``: ``1`` and ``"yes"`` are not flags).

    Examples:
        >>> check_bool(True, "progress")
        >>> check_bool("no", "progress")
        Traceback (most recent call last):
        ...
        TypeError: progress must be True or False, got 'no' (str).
    """
    if not isinstance(value, bool):
        raise TypeError(f"{name} must be True or False, got {value!r} ({type(value).__name__}).")


def check_choice(value: Any, name: str, allowed: Sequence[Any]) -> None:
    """Refuses a value not among ``allowed`` (``ValueError`` listing them).

    Examples:
        >>> check_choice("step", "discount_per", ("step", "decision"))
        >>> check_choice("option", "discount_per", ("step", "decision"))
        Traceback (most recent call last):
        ...
        ValueError: discount_per must be one of ('step', 'decision'), got 'option'.
    """
    try:
        ok = value in tuple(allowed)
    except TypeError:  # an unhashable / incomparable value
        ok = False
    if not ok or isinstance(value, bool) and not any(isinstance(a, bool) for a in allowed):
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}.")


def check_nested_key(key: Any, name: str, owner: str | None = None) -> NestedKey:
    """Returns ``key`` unravelled (``("a", ("b",))`` -> ``("a", "b")``, ``("a",)`` -> ``"a"``); refuses what is not
    a ``NestedKey`` (a non-empty str or a non-empty tuple of them) with a ``TypeError``.

    Examples:
        >>> check_nested_key(("next", ("reward",)), "reward_key")
        ('next', 'reward')
        >>> check_nested_key(3, "reward_key", "OnPolicyDecisions")
        Traceback (most recent call last):
        ...
        TypeError: OnPolicyDecisions: reward_key must be a NestedKey (a str or a tuple of str), got 3 (int).
    """
    where = f"{owner}: " if owner else ""
    bad = TypeError(f"{where}{name} must be a NestedKey (a str or a tuple of str), got {key!r} ({type(key).__name__}).")
    if not isinstance(key, (str, tuple)) or key in ("", ()):
        raise bad
    try:
        out = unravel_key(key)
    except (RuntimeError, TypeError, ValueError):
        raise bad from None
    parts = (out,) if isinstance(out, str) else out
    if not parts or any(not isinstance(p, str) or p == "" for p in parts):
        raise bad
    return out


def check_distinct_keys(keys: Mapping[str, Any], owner: str, *, allow_same: Iterable[tuple[str, str]] = ()) -> dict[str, NestedKey]:
    """Checks every key argument of a component (``{argument name: NestedKey}``) and refuses two that name the same
    entry: the component would write one over the other, or read what it wrote. Returns the unravelled keys.

    ``allow_same`` lists pairs of argument names that may share an entry by design.

    Examples:
        >>> check_distinct_keys({"steps_key": "steps", "reward_key": ("next", "reward")}, "SMDPTransitions")
        {'steps_key': 'steps', 'reward_key': ('next', 'reward')}
    """
    out = {name: check_nested_key(key, name, owner) for name, key in keys.items()}
    allowed = {frozenset(pair) for pair in allow_same}
    names = list(out)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if out[a] == out[b] and frozenset((a, b)) not in allowed:
                raise ValueError(
                    f"{owner}: {a} and {b} are both {out[a]!r}; one would overwrite the other's entry. "
                    "Give them different keys."
                )
    return out
