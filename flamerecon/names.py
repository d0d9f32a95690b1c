"""View names as file names: a name becomes ``renders/<name>.png`` and the like, so a NeRF view
named by its relative path (``train/r_0``) must not reach into another folder."""

from __future__ import annotations

import re

_UNSAFE = re.compile(r"[^A-Za-z0-9._+=@,-]+")


def file_stem(name: str) -> str:
    """``name`` with path separators and other characters unsafe in file names replaced by
    ``_`` (``train/r_0`` -> ``train_r_0``), without leading dots; never empty."""
    stem = _UNSAFE.sub("_", str(name)).lstrip(".")
    return stem or "_"
