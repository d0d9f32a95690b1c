"""A multirun where one job fails still runs the others, marks the failure and lists it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from flamerecon.run.runner import FAILED_FILE
from tests.helpers import FAST, REPO, TINY, repo_env


@pytest.mark.slow
@pytest.mark.e2e
def test_failed_job_does_not_stop_the_sweep(tmp_path):
    env = repo_env()
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), "--multirun", *TINY, *FAST, "solver.max_iters=5",
         "holdout=[cam99],[cam01]", f"hydra.sweep.dir={tmp_path}"],
        capture_output=True, text=True, env=env, timeout=300, check=False,
    )
    assert proc.returncode == 2, proc.stderr
    bad, good = tmp_path / "0", tmp_path / "1"
    assert "holdout: unknown view 'cam99'" in (bad / FAILED_FILE).read_text()
    assert not (bad / "density.npz").exists()
    assert (good / "metrics.json").is_file() and not (good / FAILED_FILE).exists()
    assert "flamerecon: 1 of 2 jobs failed:" in proc.stderr
    assert f"{bad}: holdout: unknown view 'cam99'" in proc.stderr
    assert "Traceback" not in proc.stderr
