"""Where the checkout is, and the environment for a subprocess that imports it."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def repo_env() -> dict[str, str]:
    """The environment for a subprocess that imports flamerecon from this checkout: the repo
    put in front of PYTHONPATH (kept, where the packages may come from)."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p))


#: a tiny synthetic scene and options, as Python source for a subprocess (``s`` and ``o``)
TINY_API_SETUP = ("s = fr.load_scene({'name': 'synthetic', 'width': 24, 'height': 18, 'n_cameras': 3, "
                  "'phantom_resolution': 16}); "
                  "o = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=8), device='cpu', "
                  "solver=fr.SolverOptions(params={'max_iters': 5}))")


def python_stdout(code: str) -> str:
    """What ``python -c code`` prints, run from the checkout (a failure shows its stderr)."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", code], check=False, cwd=REPO, env=repo_env(), capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout
