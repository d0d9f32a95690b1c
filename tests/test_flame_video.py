"""Issue 5's whole workflow: a joblib multirun of train.py over three frames of the synthetic
flame, assembled into one series that VTK reads back with the right frames and geometry."""

import subprocess
import sys

import numpy as np
import pytest

from flamerecon.outputs.sequence import assemble_sweep
from tests.helpers import REPO, TINY


@pytest.mark.slow
@pytest.mark.e2e
def test_three_frames_through_joblib_then_vtk(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy
    sweep = tmp_path / "sweep"
    proc = subprocess.run(
        [sys.executable, "train.py", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
         *TINY, "solver.max_iters=10", "log.eval_every=0", "scene.frame=0,5,10",
         f"hydra.sweep.dir={sweep}"],
        cwd=REPO, check=False, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    written = assemble_sweep(sweep)
    with np.load(written["npz"]) as f:
        np.testing.assert_array_equal(f["frames"], [0, 5, 10])
        series = f["density"]
        lo, hi = f["bbox_min"], f["bbox_max"]
    assert series.shape[:2] == (3, 3) and not np.allclose(series[0], series[2])
    nz, ny, nx = series.shape[2:]
    size = (hi - lo) / np.array([nx, ny, nz])
    vtis = sorted((sweep / "sequence_vti").glob("*.vti"))
    assert len(vtis) == 3
    for t, path in enumerate(vtis):
        reader = vtk.vtkXMLImageDataReader()
        reader.SetFileName(str(path))
        reader.Update()
        image = reader.GetOutput()
        assert image.GetDimensions() == (nx, ny, nz)
        np.testing.assert_allclose(image.GetOrigin(), lo + size / 2, rtol=1e-6)
        np.testing.assert_allclose(image.GetSpacing(), size, rtol=1e-6)
        red = vtk_to_numpy(image.GetPointData().GetArray("R"))
        np.testing.assert_allclose(red.reshape(nz, ny, nx), series[t, 0], rtol=1e-6)
