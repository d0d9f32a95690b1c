"""Config values as plain Python: what a Hydra node, a dataclass dict or a user's nested
mapping becomes before it is stored, compared or hashed; and JSON text read into it."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence


def json_value(text: str):
    """``json.loads(text)``; a document nested so deeply that the parser runs out of stack
    (a RecursionError) is refused like any invalid JSON, as a ``ValueError`` that says so."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("nested too deeply to read (thousands of levels of [ or {)") from None


def plain(value):
    """``value`` with sequences (tuples, config lists; not strings) as lists and mappings as
    dicts, all the way down."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain(v) for v in value]
    return value
