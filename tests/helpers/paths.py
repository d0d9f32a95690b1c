"""Where the checkout is, and the environment for a subprocess that imports it."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def repo_env() -> dict[str, str]:
    """The environment for a subprocess that imports flamerecon from this checkout: the repo
    put in front of PYTHONPATH (kept, where the packages may come from)."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p))
