"""THE tiny configuration every end-to-end test starts from, and ``python train.py`` run on it."""

from __future__ import annotations

import subprocess
import sys

from hydra import compose, initialize_config_dir

from .paths import REPO, repo_env

#: the real config shrunk to seconds: 5 cameras at 48x36, a 32-cell phantom, a 16-cell grid,
#: solved by the paper's method (fista; the default is pqn_smooth): a test of another solver
#: names it.
TINY = [
    "solver=fista", "scene.width=48", "scene.height=36", "scene.n_cameras=5", "scene.phantom_resolution=32",
    "grid.resolution=16", "solver.max_iters=30", "log.eval_every=10", "log.eval_share=null",
    "device=cpu",
]
#: a shorter solve without held-out pictures, for runs that only have to get somewhere.
FAST = ["solver.max_iters=10", "log.eval_every=0"]
#: smaller still, for runs that only have to start (bad input) or compare two backends.
SMALLER = ["scene.width=24", "scene.height=18", "scene.phantom_resolution=16", "grid.resolution=8"]
VIEWS = [f"cam{i:02d}" for i in range(5)]
HELDOUT, TRAIN = ["cam04"], VIEWS[:4]  # the scene's default holdout: the last camera


def tiny_config(*overrides: str):
    """The tiny config composed by Hydra, with ``overrides`` after :data:`TINY`."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=[*TINY, *overrides])


class CliRun:
    """``python train.py TINY... overrides... hydra.run.dir=RUN_DIR`` from the repo root, as a
    user types it, in a subprocess."""

    def __init__(self, run_dir, *overrides: str):
        self.run_dir = run_dir
        env = repo_env()
        self.args = [sys.executable, "train.py", *TINY, *overrides, f"hydra.run.dir={run_dir}"]
        self.proc = subprocess.Popen(self.args, cwd=REPO, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self._done: subprocess.CompletedProcess | None = None

    def result(self) -> subprocess.CompletedProcess:
        if self._done is None:
            out, err = self.proc.communicate(timeout=300)
            self._done = subprocess.CompletedProcess(self.args, self.proc.returncode, out, err)
        return self._done

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def refused_line(args: list[str], cwd, status: int = 2) -> str:
    """The one line ``python train.py args`` prints when it refuses the command (run from
    ``cwd``): it must exit with ``status`` and print nothing else, on stdout or stderr (no config,
    no log line, no traceback before or after it)."""
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *args], cwd=cwd, capture_output=True,
                          text=True, env=repo_env(), timeout=300, check=False)
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert proc.returncode == status, proc.stdout + proc.stderr
    assert len(lines) == 1 and proc.stderr.startswith("flamerecon: error: "), proc.stdout + proc.stderr
    return lines[0]
