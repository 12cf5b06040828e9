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

import torch
from tensordict.utils import NestedKey, unravel_key

__all__ = [
    "check_bool",
    "check_callable",
    "check_choice",
    "check_distinct_keys",
    "check_int",
    "check_nested_key",
    "check_number",
    "check_numbers",
    "check_positive_number",
    "check_same_device",
    "check_tensor",
    "with_article",
]


def with_article(phrase: str) -> str:
    """``phrase`` after "a" or "an", as its first letter asks ("an OptionsPPO checkpoint", "a bool tensor").

    Examples:
        >>> with_article("OptionsPPO checkpoint"), with_article("hierarchy"), with_article("integer tensor")
        ('an OptionsPPO checkpoint', 'a hierarchy', 'an integer tensor')
    """
    return f"{'an' if phrase[:1].lower() in 'aeiou' else 'a'} {phrase}"


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


def check_numbers(
    values: Any,
    name: str,
    *,
    lo: float = -math.inf,
    hi: float = math.inf,
    allow_empty: bool = True,
    allow_nan: bool = False,
) -> list[float]:
    """Returns ``values`` (a sequence of real numbers, or a 1-D tensor / array of them) as a list of floats; refuses
    another type (``TypeError``) and an entry that is NaN (unless ``allow_nan``) or outside ``[lo, hi]``
    (``ValueError`` naming its index).

    Examples:
        >>> check_numbers([0.5, 0.5], "usage", lo=0, hi=1)
        [0.5, 0.5]
        >>> check_numbers([0.5, float("nan"), 0.5], "usage", lo=0, hi=1)
        Traceback (most recent call last):
        ...
        ValueError: usage[1] must be a number in [0, 1], got nan.
        >>> check_numbers("0.5", "usage")
        Traceback (most recent call last):
        ...
        TypeError: usage must be a sequence of numbers, got '0.5' (str).
    """
    if isinstance(values, torch.Tensor):
        if values.ndim != 1 or values.is_complex():
            raise TypeError(f"{name} must be a sequence of numbers (1-D), got a tensor of shape {tuple(values.shape)}.")
        values = values.tolist()
    elif hasattr(values, "tolist") and getattr(values, "ndim", None) == 1:  # a 1-D numpy array
        values = values.tolist()
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
        raise TypeError(f"{name} must be a sequence of numbers, got {values!r} ({type(values).__name__}).")
    if not allow_empty and len(values) == 0:
        raise ValueError(f"{name} must not be empty.")
    out = []
    for i, v in enumerate(values):
        if not (allow_nan and isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isnan(v)):
            check_number(v, f"{name}[{i}]", lo=lo, hi=hi)
        out.append(float(v))
    return out


def check_callable(value: Any, name: str, *, allow_none: bool = False, what: str = "a callable") -> None:
    """Refuses what cannot be called (``TypeError``).

    Examples:
        >>> check_callable(print, "callback")
        >>> check_callable(3, "callback", allow_none=True)
        Traceback (most recent call last):
        ...
        TypeError: callback must be a callable or None, got 3 (int).
    """
    if value is None and allow_none:
        return
    if not callable(value):
        raise TypeError(f"{name} must be {what}{' or None' if allow_none else ''}, got {value!r} ({type(value).__name__}).")


_KINDS = {
    "floating": (lambda t: t.is_floating_point(), "floating point"),
    "integer": (lambda t: not t.is_floating_point() and not t.is_complex() and t.dtype != torch.bool, "integer"),
    "bool": (lambda t: t.dtype == torch.bool, "bool"),
}


def check_tensor(
    value: Any,
    name: str,
    *,
    ndim: int | Sequence[int] | None = None,
    shape: Sequence[int | None] | None = None,
    dtype: str | Sequence[str] | None = None,
    nonempty: bool = False,
    owner: str | None = None,
) -> torch.Tensor:
    """Returns ``value`` if it is a ``torch.Tensor`` of the given number of dimensions, shape (``None``: any size in
    that dimension), kind of dtype (``"floating"``, ``"integer"``, ``"bool"`` or a tuple of them) and, with
    ``nonempty``, at least one element; refuses anything else, naming the argument (``TypeError`` for a non-tensor,
    ``ValueError`` otherwise).

    Examples:
        >>> check_tensor(torch.zeros(2, 3), "u", ndim=2, dtype="floating").shape
        torch.Size([2, 3])
        >>> check_tensor(torch.zeros(2, 3), "u", ndim=3)
        Traceback (most recent call last):
        ...
        ValueError: u must be a 3-dimensional tensor, got shape [2, 3].
        >>> check_tensor(torch.zeros(2, 3), "mask", shape=(2, 4), dtype="bool")
        Traceback (most recent call last):
        ...
        ValueError: mask must have shape [2, 4], got shape [2, 3].
    """
    where = f"{owner}: " if owner else ""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{where}{name} must be a torch.Tensor, got {type(value).__name__}.")
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if value.ndim not in allowed:
            dims = " or ".join(str(d) for d in allowed)
            raise ValueError(f"{where}{name} must be {with_article(dims + '-dimensional tensor')}, got shape {list(value.shape)}.")
    if shape is not None:
        if value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
            want = ", ".join("*" if s is None else str(s) for s in shape)
            raise ValueError(f"{where}{name} must have shape [{want}], got shape {list(value.shape)}.")
    if dtype is not None:
        kinds = (dtype,) if isinstance(dtype, str) else tuple(dtype)
        if not any(_KINDS[k][0](value) for k in kinds):
            names = " or ".join(_KINDS[k][1] for k in kinds)
            raise ValueError(f"{where}{name} must be {with_article(names + ' tensor')}, got dtype {value.dtype}.")
    if nonempty and value.numel() == 0:
        raise ValueError(f"{where}{name} must not be empty, got shape {list(value.shape)}.")
    return value


def check_same_device(tensors: Mapping[str, Any], owner: str | None = None) -> None:
    """Refuses tensors (``{argument name: tensor or None}``) that are not all on one device (``ValueError`` naming
    two of them); ``None`` entries are skipped.

    Examples:
        >>> check_same_device({"u": torch.zeros(1), "mask": torch.zeros(1, device="meta")}, "most_likely_options")
        Traceback (most recent call last):
        ...
        ValueError: most_likely_options: mask is on device meta but u is on device cpu; put them on one device.
    """
    first = None
    for name, t in tensors.items():
        if t is None:
            continue
        if first is None:
            first = (name, t.device)
        elif t.device != first[1]:
            where = f"{owner}: " if owner else ""
            raise ValueError(
                f"{where}{name} is on device {t.device} but {first[0]} is on device {first[1]}; put them on one device."
            )
