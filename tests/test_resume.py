"""An interrupted run resumes to the same result as an uninterrupted one; a diverging solve
stops, keeps its last good iterate and says so."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from flamerecon.errors import Interrupted, SolveDiverged
from flamerecon.run.pipeline import reconstruct
from flamerecon.run.runner import FAILED_FILE, run_task
from flamerecon.solvers import SOLVERS, Solver, SolveResult, register
from tests.helpers import FAST, REPO, TINY, interrupt_at, repo_env, tiny_cfg

SOLVE = ["grid.resolution=12", "solver.tol=0", "checkpoint.every=10"]

# The child runs train.py with a pause at every solver check, so that the parent's SIGINT
# lands mid-solve however fast the machine is.
_CHILD = textwrap.dedent(
    """
    import sys, time
    from flamerecon.run import hook as run_hook
    original = run_hook.Monitor.__call__
    def slow(self, it, x, info):
        original(self, it, x, info)
        time.sleep(0.05)
    run_hook.Monitor.__call__ = slow
    import runpy
    sys.argv = [sys.argv[1], *sys.argv[2:]]
    runpy.run_path(sys.argv[0], run_name="__main__")
    """
)


def solve_cfg(*overrides: str):
    return tiny_cfg(*SOLVE, *overrides)


def _density(run: Path) -> np.ndarray:
    with np.load(run / "density.npz") as f:
        return f["density"]


@pytest.mark.slow
@pytest.mark.e2e
def test_sigint_then_resume_matches_uninterrupted_run(tmp_path):
    overrides = ["solver=fista", "solver.max_iters=100", "solver.check_every=5"]
    run = tmp_path / "run"
    env = repo_env()
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(REPO / "train.py"), *TINY, *FAST, *SOLVE, *overrides,
         f"hydra.run.dir={run}"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    deadline = time.monotonic() + 120
    while not (run / "checkpoint.pt").exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    child.send_signal(signal.SIGINT)
    _, err = child.communicate(timeout=120)
    assert child.returncode == 130, err
    assert "the state is saved in checkpoint.pt; continue with: python train.py resume=" in err
    assert not (run / "density.npz").exists()
    stopped_at = torch.load(run / "checkpoint.pt", weights_only=True)["state"]["iteration"]
    assert 10 <= stopped_at < 100

    resumed = run_task(OmegaConf.create({"resume": str(run)}), tmp_path / "resume_invocation")
    assert resumed is not None
    assert not (run / "checkpoint.pt").exists() and not (run / FAILED_FILE).exists()
    reference = tmp_path / "reference"
    reconstruct(solve_cfg(*overrides), reference)
    np.testing.assert_allclose(_density(run), _density(reference), rtol=1e-5, atol=1e-7)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["solver"]["iterations"] == 100 and metrics["solver"]["status"] == "finished"


@pytest.mark.slow
def test_adam_resumes_exactly_from_its_optimizer_state(tmp_path, monkeypatch):
    overrides = ["solver=adam", "solver.max_iters=30", "solver.check_every=5"]
    run = tmp_path / "run"
    cfg = solve_cfg(*overrides)
    with pytest.raises(Interrupted, match="SIGINT received at iteration 15"):
        reconstruct(cfg, run, watch=interrupt_at(15))  # the run's handler: checkpoint, then stop
    reconstruct(cfg, run, resume=True)
    reference = tmp_path / "reference"
    reconstruct(cfg, reference)
    np.testing.assert_allclose(_density(run), _density(reference), rtol=1e-5, atol=1e-7)


@register("test_blows_up")
class _BlowsUp(Solver):
    """A gradient step that works for a while, then turns to NaN at iteration ``nan_at``."""

    def __init__(self, nan_at: int = 25, **budget):
        super().__init__(**budget)
        self.nan_at = nan_at

    def _run(self, problem, x, callback):
        A, b = problem.A, problem.b
        for it in range(1, self.max_iters + 1):
            x = (x - 1e-3 * A.adjoint(A.forward(x) - b)).clamp_min(0)
            if it >= self.nan_at:
                x = x * float("nan")
            if it % 10 == 0 and callback is not None:
                callback(it, x, {"objective": problem.objective(x)})
        return SolveResult(x, self.max_iters, 0.0, problem.objective(x), False)


@pytest.mark.slow
def test_nan_stops_the_solve_and_keeps_the_last_good_iterate(tmp_path):
    assert "test_blows_up" in SOLVERS
    run = tmp_path / "run"
    cfg = solve_cfg("solver.name=test_blows_up", "solver.max_iters=40", "checkpoint.every=0")
    with pytest.raises(SolveDiverged, match=r"diverged at iteration 30: .*NaN/Inf.*last good iterate "
                                            r"\(iteration 20\)") as info:
        reconstruct(cfg, run)
    assert info.value.exit_code == 3
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["solver"]["status"] == "diverged"
    assert metrics["solver"]["iterations"] == 20
    assert metrics["solver"]["stopped"]["iteration"] == 30
    density = _density(run)
    assert np.isfinite(density).all() and density.max() > 0
    with pytest.raises(SystemExit) as exit_info:
        run_task(cfg, tmp_path / "run2")
    assert exit_info.value.code == 3
    assert "NaN/Inf" in (tmp_path / "run2" / FAILED_FILE).read_text()


def test_objective_growth_counts_as_divergence(tmp_path):
    cfg = solve_cfg("solver.name=test_blows_up", "+solver.nan_at=1000", "solver.max_iters=20",
                   "checkpoint.divergence_factor=1e-9")
    with pytest.raises(SolveDiverged, match=r"exceeds 1e-09 times its starting value"):
        reconstruct(cfg, tmp_path / "run")
