"""The table format of the bad-input tests (issues 26 and 53): one row per case.

A row is ``(api, case, call, error, phrase)``: ``api`` the public name the case tries (a function, a class, or
``Class.method``), ``case`` what is wrong, ``call`` a function of no argument (or of ``tmp_path`` in the file
tables) that makes the call, ``error`` the exception type it must raise and ``phrase`` a part of its message. A
*control* (an input that must be accepted, often the nearest good neighbour of a bad one) has ``error=None`` and
``phrase=None``. Case names starting with ``"issue:"`` are the cases listed in issue 53.
"""
from __future__ import annotations

import pytest

OK = None  # the error of a control: the call must succeed


def ids(rows) -> list[str]:
    return [f"{r[0]}: {r[1]}" for r in rows]


def check(call, error, phrase, *args) -> None:
    """Runs one row: a control must return, a bad input must raise ``error`` with ``phrase`` in its message."""
    if error is None:
        call(*args)
        return
    with pytest.raises(error) as info:
        call(*args)
    assert phrase in str(info.value), f"message {str(info.value)!r} lacks {phrase!r}"
