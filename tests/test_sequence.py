"""A Hydra multirun over frames assembled into one sequence, read back with numpy, VTK and csv."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest

from flamerecon.outputs.export import save_density
from flamerecon.outputs.sequence import SweepError, assemble_sweep, find_frame_runs, flatten_metrics
from tests.helpers import repo_env

REPO = Path(__file__).resolve().parents[1]
needs_vtk = pytest.mark.skipif(find_spec("vtkmodules") is None,
                               reason="vtk not installed: pip install 'flamerecon[export]'")
LO = np.array([-1.0, 0.0, -1.0])
HI = np.array([1.0, 4.0, 1.0])
SHAPE = (3, 6, 5, 4)  # (C, nz, ny, nx)


def _frame_volume(frame: int) -> np.ndarray:
    rng = np.random.default_rng(frame)
    return rng.random(SHAPE).astype(np.float32)


def _fake_run(sweep: Path, job: int, frame: int | None, metrics: dict | None = None,
              how: str = "overrides") -> Path:
    """A run folder as Hydra and the pipeline leave it."""
    run = sweep / str(job)
    (run / ".hydra").mkdir(parents=True)
    if how == "overrides" and frame is not None:
        (run / ".hydra" / "overrides.yaml").write_text(
            f"- scene=synthetic\n- scene.frame={frame}\n- solver=fista\n"
        )
    if how == "config" and frame is not None:
        (run / ".hydra" / "config.yaml").write_text(f"scene:\n  name: synthetic\n  frame: {frame}\n")
    extra = {"frame": frame} if how == "npz" and frame is not None else {}
    save_density(run / "density.npz", _frame_volume(job if frame is None else frame), LO, HI, ["c0", "c1"], **extra)
    if metrics is not None:
        (run / "metrics.json").write_text(json.dumps(metrics))
    return run


def _metrics(frame: int) -> dict:
    return {"solver": "fista", "iterations": 100 + frame, "heldout": {"cam2": {"psnr": 30.0 + frame,
            "ssim": 0.9}}, "train": {"psnr": 35.0}}


@pytest.mark.e2e
@needs_vtk
def test_assemble_script_on_three_frames(tmp_path):
    sweep = tmp_path / "multirun"
    for job, frame in enumerate([20, 0, 10]):  # jobs finish in any order; frames get sorted
        _fake_run(sweep, job, frame, _metrics(frame), how=["overrides", "config", "npz"][job])
    (sweep / "multirun.yaml").write_text("hydra: {}\n")
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "assemble.py"), str(sweep)], check=False,
        capture_output=True, text=True, env=repo_env(),
    )
    assert proc.returncode == 0, proc.stderr

    with np.load(sweep / "sequence.npz") as f:
        assert f["density"].shape == (3, *SHAPE) and f["density"].dtype == np.float32
        np.testing.assert_array_equal(f["frames"], [0, 10, 20])
        for t, frame in enumerate([0, 10, 20]):
            np.testing.assert_array_equal(f["density"][t], _frame_volume(frame))
        np.testing.assert_array_equal(f["bbox_min"], LO)
        np.testing.assert_array_equal(f["bbox_max"], HI)
        assert f["views"].tolist() == [["c0", "c1"]] * 3
        assert f["run_dirs"].tolist() == ["1", "2", "0"]

    vtk_io = pytest.importorskip("vtkmodules.vtkIOXML")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    sets = ET.parse(sweep / "sequence.pvd").getroot().find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in sets] == [0.0, 10.0, 20.0]
    step = (HI - LO) / [4, 5, 6]
    for d, frame in zip(sets, [0, 10, 20]):
        reader = vtk_io.vtkXMLImageDataReader()
        reader.SetFileName(str(sweep / d.get("file")))
        reader.Update()
        image = reader.GetOutput()
        assert image.GetDimensions() == (4, 5, 6)
        np.testing.assert_allclose(image.GetOrigin(), LO + step / 2)
        np.testing.assert_allclose(image.GetSpacing(), step)
        red = vtk_to_numpy(image.GetPointData().GetArray("R"))
        np.testing.assert_array_equal(red, _frame_volume(frame)[0].reshape(-1))

    with open(sweep / "sequence_metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in rows] == [0, 10, 20]
    assert [float(r["heldout.cam2.psnr"]) for r in rows] == [30.0, 40.0, 50.0]
    assert rows[0]["solver"] == "fista"
    try:
        import matplotlib  # noqa: F401
    except ImportError:  # the plot is skipped, the rest still written
        assert not (sweep / "sequence_metrics.png").exists() and "skipped" in proc.stdout
    else:
        png = (sweep / "sequence_metrics.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_frames_must_share_the_grid(tmp_path):
    _fake_run(tmp_path, 0, 0)
    run = _fake_run(tmp_path, 1, 1)
    save_density(run / "density.npz", _frame_volume(1), LO, HI * 2, [])
    with pytest.raises(SweepError, match="bbox_max") as err:
        assemble_sweep(tmp_path, vti=False)
    assert "1/density.npz" in str(err.value)
    assert not (tmp_path / "sequence.npz").exists()
    assert [p.name for p in tmp_path.iterdir() if p.is_file()] == []  # no temporary left


def test_incomplete_duplicate_and_unnumbered_runs(tmp_path):
    _fake_run(tmp_path, 0, 5)
    (tmp_path / "1" / ".hydra").mkdir(parents=True)  # a job that died before saving
    with pytest.raises(SweepError, match="without density.npz"):
        find_frame_runs(tmp_path)
    assert [r.frame for r in find_frame_runs(tmp_path, skip_incomplete=True)] == [5]
    _fake_run(tmp_path, 2, 5)
    with pytest.raises(SweepError, match="frame 5 reconstructed twice"):
        find_frame_runs(tmp_path, skip_incomplete=True)
    mixed = tmp_path / "mixed"
    _fake_run(mixed, 0, 3)
    _fake_run(mixed, 1, None)
    with pytest.raises(SweepError, match="do not say"):
        find_frame_runs(mixed)


def test_unnumbered_sweep_uses_job_order(tmp_path):
    for job in (10, 2, 1):
        _fake_run(tmp_path, job, None)
    assert [r.frame for r in find_frame_runs(tmp_path)] == [0, 1, 2]
    assert [r.run_dir.name for r in find_frame_runs(tmp_path)] == ["1", "2", "10"]


def test_flatten_metrics():
    assert flatten_metrics({"a": {"b": 1, "c": [2.0, "x"]}, "d": None}) == {
        "a.b": 1, "a.c.0": 2.0, "a.c.1": "x", "d": None}


_APP = """
import hydra
import numpy as np
from omegaconf import DictConfig

from flamerecon.outputs.export import save_density


@hydra.main(version_base=None, config_path=None, config_name=None)
def main(cfg: DictConfig) -> None:
    frame = int(cfg.scene.frame)
    rng = np.random.default_rng(frame)
    save_density("density.npz", rng.random((3, 6, 5, 4)).astype(np.float32),
                 [-1.0, 0.0, -1.0], [1.0, 4.0, 1.0], ["c0"])
    with open("metrics.json", "w") as fh:
        fh.write('{"psnr": %d}' % (30 + frame))


if __name__ == "__main__":
    main()
"""


@pytest.mark.slow
@pytest.mark.e2e
@needs_vtk
def test_joblib_multirun_then_assemble(tmp_path):
    """The sequence workflow end to end with Hydra's joblib launcher and a stand-in app."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    (tmp_path / "app.py").write_text(_APP)
    sweep = tmp_path / "sweep"
    env = repo_env()
    proc = subprocess.run(
        [sys.executable, "app.py", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
         "+scene.frame=range(0,30,10)", f"hydra.sweep.dir={sweep}", "hydra.job.chdir=true"],
        cwd=tmp_path, check=False, capture_output=True, text=True, env=env, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    written = assemble_sweep(sweep)
    with np.load(written["npz"]) as f:
        np.testing.assert_array_equal(f["frames"], [0, 10, 20])
        assert f["density"].shape == (3, 3, 6, 5, 4)
        np.testing.assert_array_equal(
            f["density"][2], np.random.default_rng(20).random((3, 6, 5, 4)).astype(np.float32))
    sets = ET.parse(written["pvd"]).getroot().find("Collection").findall("DataSet")
    assert len(sets) == 3


def test_slurm_launcher_config_composes():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose(config_name=None, overrides=["hydra/launcher=slurm",
                                                   "hydra.launcher.partition=gpu"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert launcher.partition == "gpu" and launcher.array_parallelism == 64
