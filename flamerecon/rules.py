"""What a value may be: the checks every rule is made of.

A :data:`Check` takes a value and returns None when it is fine, else what the value must be
(``"an integer >= 1"``); its ``types`` say which Python types it takes at all, so a caller can
tell a value of the wrong type (``TypeError``) from one out of range (``ValueError``). The
CLI's option table (:mod:`flamerecon.fit.option_rules`), the front door's argument checks
(:mod:`flamerecon.arguments`) and the calibration file reader
(:mod:`flamerecon.scenes.values`) are all made of these.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Callable

Check = Callable[[object], str | None]  # value -> what is wrong with it, or None


def takes(*types: type) -> Callable[[Check], Check]:
    """Mark a check with the Python types it takes (bool only where named)."""

    def mark(check: Check) -> Check:
        check.types = types
        return check

    return mark


def of_type(value, check: Check) -> bool:
    """Whether ``value`` has a type ``check`` takes (True for a check that does not say)."""
    types = getattr(check, "types", None)
    if types is None:
        return True
    if isinstance(value, bool) and bool not in types:
        return False
    return isinstance(value, types)


def is_number(value) -> bool:
    """An int or float (numpy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def quoted_number(value) -> bool:
    """A string that reads as a number (``'1e-4'``: quoted on a command line or in a file)."""
    if not isinstance(value, str):
        return False
    try:
        float(value)
    except ValueError:
        return False
    return True


def integer(lo: int | None = None, hi: int | None = None) -> Check:
    """An int (or an integral float, as ``1e3`` parses) in [lo, hi]."""
    want = ("an integer" + (f" >= {lo}" if lo is not None else "")
            + (f" <= {hi}" if hi is not None else ""))

    @takes(numbers.Real)
    def check(value):
        if not is_number(value) or not math.isfinite(value) or int(value) != value:
            return want
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            return want
        return None

    return check


def number(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           hi_open: bool = False) -> Check:
    """A finite int or float in the interval from lo to hi (open ends where asked)."""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    want = " and ".join(parts) if parts else "a finite number"

    @takes(numbers.Real)
    def check(value):
        if not is_number(value) or not math.isfinite(value):
            return want
        if lo is not None and (value <= lo if lo_open else value < lo):
            return want
        if hi is not None and (value >= hi if hi_open else value > hi):
            return want
        return None

    return check


@takes(bool)
def boolean(value) -> str | None:
    return None if isinstance(value, bool) else "true or false"


@takes(str)
def text(value) -> str | None:
    return None if isinstance(value, str) and value != "" else "a non-empty string"


def choice(*values) -> Check:
    want = "one of " + ", ".join(str(v) for v in values)

    @takes(*dict.fromkeys(type(v) for v in values))
    def check(value):
        return None if value in values and not isinstance(value, bool) else want

    check.choices = values
    return check


def either(*checks: Check) -> Check:
    """Any one of ``checks`` (the message lists them all)."""

    @takes(*dict.fromkeys(t for c in checks for t in getattr(c, "types", (object,))))
    def check(value):
        wrong = [c(value) for c in checks]
        return None if None in wrong else " or ".join(dict.fromkeys(wrong))

    return check


def list_of(item: Check, length: int | None = None, what: str = "") -> Check:
    want = what or f"a list{f' of {length}' if length else ''}"

    @takes(list, tuple)
    def check(value):
        if not isinstance(value, (list, tuple)) or (length is not None and len(value) != length):
            return want
        return None if all(item(v) is None for v in value) else want

    return check


def pattern(regex: str, what: str) -> Check:
    @takes(str)
    def check(value):
        return None if isinstance(value, str) and re.fullmatch(regex, value) else what

    return check
