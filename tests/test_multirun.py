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
    table = proc.stdout[proc.stdout.index(f"{tmp_path}: 2 jobs, differing in holdout"):].splitlines()
    assert table[1].split()[:3] == ["job", "holdout", "heldout"]
    assert table[2].split()[:3] == ["0", "[cam99]", "FAILED:"] and table[3].split()[-1] == "finished"
    assert (tmp_path / "sweep_summary.csv").is_file()


def fake_job(folder, overrides: list[str], metrics: dict | None, failed: str | None = None) -> None:
    """A job folder as Hydra and a run leave it: .hydra/overrides.yaml, metrics.json, FAILED."""
    import json

    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if metrics is not None:
        (folder / "metrics.json").write_text(json.dumps(metrics))
    if failed:
        (folder / FAILED_FILE).write_text(failed + "\n")


def test_a_sweeps_table_sets_its_jobs_side_by_side(tmp_path):
    from flamerecon.outputs.sweep import sweep_rows, sweep_table

    def metrics(psnr: float) -> dict:
        return {"heldout": {"a": {"psnr": psnr, "psnr_black": 20.0, "ssim": 0.9}, "b": {"psnr": psnr + 2}},
                "train": {"c": {"psnr": 40.0}}, "solver": {"iterations": 100, "seconds": 1.25}}

    for job, l1, m in (("0", "0", metrics(30.0)), ("1", "1e-3", metrics(31.0)), ("10", "1e-2", None)):
        fake_job(tmp_path / job, ["solver=fista", f"solver.l1_rel={l1}"], m, "diverged" if m is None else None)
    varying, rows = sweep_rows(tmp_path)
    assert varying == ["solver.l1_rel"]  # solver=fista is common to every job: not a column
    assert [r["job"] for r in rows] == ["0", "1", "10"]  # job order, not text order
    assert rows[1]["heldout PSNR dB"] == "32.00" and rows[1]["black dB"] == "20.00"  # means over views
    assert rows[0]["train PSNR dB"] == "40.00" and rows[0]["iterations"] == "100" and rows[0]["seconds"] == "1.2"
    assert rows[2]["status"] == "FAILED: diverged" and rows[2]["heldout PSNR dB"] == ""
    assert sweep_table(tmp_path).splitlines()[0] == f"{tmp_path}: 3 jobs, differing in solver.l1_rel"


def test_a_sweep_of_runs_fitting_every_camera_shows_their_leave_one_out_mean(tmp_path):
    """leave_one_out=true with no held-out camera: the table's held-out cells stay empty and a
    leave-one-out column (the mean over the cameras left out in turn) tells the jobs apart; a
    sweep without it has no such column."""
    from flamerecon.outputs.sweep import sweep_rows, sweep_table

    for job, l1, loo in (("0", "1e-3", 30.0), ("1", "1e-2", 31.5)):
        fake_job(tmp_path / job, [f"solver.l1_rel={l1}", "holdout=[]", "leave_one_out=true"], {
            "heldout": {}, "train": {"a": {"psnr": 40.0}}, "solver": {"iterations": 10, "seconds": 1.0},
            "leave_one_out": {"mean": {"psnr": loo}, "views": {"a": {"psnr": loo - 1}, "b": {"psnr": loo + 1}}}})
    _, rows = sweep_rows(tmp_path)
    assert [r["leave-one-out PSNR dB"] for r in rows] == ["30.00", "31.50"] and rows[0]["heldout PSNR dB"] == ""
    assert "leave-one-out PSNR dB" in sweep_table(tmp_path).splitlines()[1]
    other = tmp_path / "plain"
    fake_job(other / "0", ["solver.l1_rel=0"], {"heldout": {"a": {"psnr": 30.0}}})
    assert "leave-one-out" not in sweep_table(other)


@pytest.mark.e2e
def test_assemble_compares_a_sweep_over_settings(tmp_path):
    for job, l1 in (("0", "0"), ("1", "1e-3")):
        fake_job(tmp_path / job, [f"solver.l1_rel={l1}"], {"heldout": {"a": {"psnr": 30.0}}})
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "assemble.py"), str(tmp_path)],
                          capture_output=True, text=True, env=repo_env(), timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "differing in solver.l1_rel" in proc.stdout and "not a sequence of frames" in proc.stdout
    assert (tmp_path / "sweep_summary.csv").read_text().splitlines()[0].startswith("job,solver.l1_rel,")
