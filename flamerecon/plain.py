"""Config values as plain Python: what a Hydra node, a dataclass dict or a user's nested
mapping becomes before it is stored, compared or hashed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence


def plain(value):
    """``value`` with sequences (tuples, config lists; not strings) as lists and mappings as
    dicts, all the way down."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain(v) for v in value]
    return value
