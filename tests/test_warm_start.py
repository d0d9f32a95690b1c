"""init=RUN_DIR starts the solve from a finished run's density."""

import json

import numpy as np
import pytest

from flamerecon.run.pipeline import reconstruct
from tests.helpers import tiny_config


def first_objective(run_dir) -> float:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    return acc.Scalars("solve/objective")[0].value


@pytest.mark.slow
def test_warm_start_from_a_finished_run_starts_lower(tmp_path):
    cold = tmp_path / "cold"
    reconstruct(tiny_config("log.eval_every=0"), cold)
    warm = tmp_path / "warm"
    reconstruct(tiny_config("log.eval_every=0", f"init={cold}"), warm)
    # the warm solve starts where the cold one ended, not where the cold one started
    cold_final = json.loads((cold / "metrics.json").read_text())["solver"]["objective"]
    assert first_objective(warm) <= cold_final * (1 + 1e-3)
    assert first_objective(warm) < 0.9 * first_objective(cold)
    a = np.load(cold / "density.npz")["density"]
    b = np.load(warm / "density.npz")["density"]
    assert np.linalg.norm(a - b) < 0.2 * np.linalg.norm(a)
    assert json.loads((warm / "metrics.json").read_text())["solver"]["iterations"] > 0


@pytest.mark.slow
def test_warm_start_refuses_a_different_box(tmp_path):
    cold = tmp_path / "cold"
    reconstruct(tiny_config("log.eval_every=0", "solver.max_iters=5"), cold)
    with pytest.raises(ValueError, match="init: .* same box"):
        reconstruct(tiny_config("grid.bbox=[[-1,0,-1],[1,2,1]]", f"init={cold}"), tmp_path / "w")


@pytest.mark.slow
@pytest.mark.e2e
def test_evaluate_script_reports_a_missing_run_folder_in_one_line(tmp_path):
    import subprocess
    import sys

    from tests.helpers import REPO, repo_env

    proc = subprocess.run([sys.executable, "scripts/evaluate.py", str(tmp_path / "none")],
                          check=False, cwd=REPO, capture_output=True, text=True, env=repo_env())
    assert proc.returncode == 2
    assert "flamerecon: error:" in proc.stderr and "config.yaml: not found" in proc.stderr
    assert "Traceback" not in proc.stderr
