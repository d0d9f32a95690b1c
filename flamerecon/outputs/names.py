"""View names as file names: a name becomes ``renders/<name>.png`` and the like, so a NeRF view
named by its relative path (``train/r_0``) must not reach into another folder."""

from __future__ import annotations

import hashlib
import re

_UNSAFE = re.compile(r"[^A-Za-z0-9._+=@,-]+")
#: the longest file stem made of a view name (a suffix and the atomic writers' temporary prefix
#: and mark fit in the 255 bytes a file name may take)
MAX_STEM = 120


def file_stem(name: str) -> str:
    """``name`` with path separators and other characters unsafe in file names replaced by
    ``_`` (``train/r_0`` -> ``train_r_0``), without leading dots; never empty, and never
    longer than :data:`MAX_STEM` (a longer one keeps its start and a hash of the whole name:
    file systems refuse names of more than 255 bytes)."""
    stem = _UNSAFE.sub("_", str(name)).lstrip(".") or "_"
    if len(stem) > MAX_STEM:
        digest = hashlib.sha1(str(name).encode("utf-8", "surrogatepass")).hexdigest()[:10]
        stem = f"{stem[:MAX_STEM - 11]}-{digest}"
    return stem


def file_stems(names: list[str]) -> list[str]:
    """:func:`file_stem` of each name, made unique (``a/b`` and ``a_b``: ``a_b``, ``a_b-2``)."""
    out: list[str] = []
    for name in names:
        base = stem = file_stem(name)
        n = 1
        while stem in out:
            n += 1
            stem = f"{base}-{n}"
        out.append(stem)
    return out
