"""The one typed reader of calibration values: every field a loader reads from a file (or from
its ``scene`` config, named ``config``) goes through one of these, which returns it as the
Python or numpy value the loader needs or raises :class:`SceneError` with one line naming the
file, the field, what it holds and what it must be::

    calibration.yaml: cameras[1].width: got the string '40'; write a number (an integer >= 1) without quotes
    info.json: train_videos[0].camera_hw: got [32.5, 40]; must be [H, W] of integers >= 1

A number given as a string is refused as such (never parsed, as a CLI value is not), a
non-integer where an integer belongs is refused (never truncated), and a name list given as
one string is one name (never split into its characters).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np

from flamerecon.rules import Check, integer, number, quoted_number
from flamerecon.scenes.base import SceneError

#: checks by what they read
POSITIVE = number(0, lo_open=True)
NONNEGATIVE = number(0)
FINITE = number()
FIELD_OF_VIEW = number(0, math.pi, lo_open=True, hi_open=True)  # radians


def refuse(value, file, field: str, want: str) -> SceneError:
    """The error for ``value`` at ``file: field`` that must be ``want``."""
    if quoted_number(value):
        return SceneError(f"{file}: {field}: got the string '{value}'; write a number ({want}) without quotes")
    want = f"a number {want}" if want[:1] in "<>" else want  # a bound alone: "> 0"
    if value is None:
        return SceneError(f"{file}: {field}: missing; it must be {want}")
    text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return SceneError(f"{file}: {field}: got {text}; it must be {want}")


def read(value, file, field: str, check: Check):
    """``value`` when ``check`` passes, else :func:`refuse`."""
    want = check(value) if value is not None else check(object())
    if value is None or want is not None:
        raise refuse(value, file, field, want)
    return value


def read_int(value, file, field: str, lo: int = 1) -> int:
    """An integer >= ``lo`` (an integral float such as ``32.0`` too; ``32.5`` is refused)."""
    return int(read(value, file, field, integer(lo)))


def read_float(value, file, field: str, check: Check = FINITE) -> float:
    """A finite float (``check``: e.g. :data:`POSITIVE`)."""
    return float(read(value, file, field, check))


def read_text(value, file, field: str) -> str:
    """A non-empty string of printable characters (a number, as an unquoted YAML name is, as its
    digits): a name or path holding NUL, a newline or another control character is refused by
    its field (no file name can hold NUL; the others would break the outputs' names)."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return str(value)
    if not isinstance(value, str) or not value:
        raise refuse(value, file, field, "a non-empty string")
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in value):
        raise SceneError(f"{file}: {field}: {value!r} holds a control character (NUL, newline, tab, ...); write it "
                         "with printable characters only")
    return value


def read_names(value, file, field: str) -> list[str]:
    """A list of names: None is none, one string is one name (an XML sequence of one, as
    cv2.FileStorage writes it, reads back as one string), a list of strings is itself."""
    if value is None:
        return []
    items = [value] if isinstance(value, (str, numbers.Integral)) and not isinstance(value, bool) else value
    if not _is_list(items):
        raise refuse(value, file, field, "a list of names")
    return [read_text(item, file, f"{field}[{i}]") for i, item in enumerate(items)]


def read_array(value, file, field: str) -> np.ndarray:
    """A finite float64 array of any shape from nested lists of numbers (or an array)."""
    if value is None:
        raise refuse(value, file, field, "an array of numbers")
    flat = value.reshape(-1).tolist() if isinstance(value, np.ndarray) else list(_leaves(value))
    for i, item in enumerate(flat):
        if isinstance(item, str) or not (isinstance(item, numbers.Real) and not isinstance(item, bool)):
            where = f"{field} (item {i})" if _is_list(value) or isinstance(value, np.ndarray) else field
            raise refuse(item, file, where, "a number")
    try:
        arr = np.asarray(_as_lists(value), dtype=np.float64)
    except ValueError:  # rows of different lengths
        raise refuse(value, file, field, "an array of numbers with rows of one length") from None
    if not np.isfinite(arr).all():
        raise SceneError(f"{file}: {field}: holds NaN or Inf")
    return arr


def read_matrix(value, shape: tuple[int, ...], file, field: str) -> np.ndarray:
    """A finite float64 array of ``shape`` (a vector may be given as a row or a column)."""
    arr = read_array(value, file, field)
    vector = len(shape) == 1 and sum(n > 1 for n in arr.shape) <= 1  # (3,), (3, 1), (1, 3)
    if arr.size == int(np.prod(shape)) and arr.shape != shape and (arr.ndim <= 1 or vector):
        arr = arr.reshape(shape)
    if arr.shape != shape:
        raise SceneError(f"{file}: {field}: expected shape {shape}, got {arr.shape}")
    return arr


def read_size(value, file, field: str, what: str) -> tuple[int, ...]:
    """A list of image sizes (``what``: ``[H, W]`` or ``[W, H]``), each an integer >= 1."""
    sizes = read_matrix(value, (len(what.split(",")),), file, field)
    if not all(n >= 1 and n == int(n) for n in sizes):
        raise refuse(sizes.tolist(), file, field, f"{what} of integers >= 1")
    return tuple(int(n) for n in sizes)


def _is_list(value) -> bool:
    """A list, a tuple or a config's list (any sequence but a string)."""
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))


def _leaves(value):
    if _is_list(value):
        for item in value:
            yield from _leaves(item)
    else:
        yield value


def _as_lists(value):
    """Nested sequences (a config's lists too) as nested lists, for numpy."""
    return [_as_lists(v) for v in value] if _is_list(value) else value
