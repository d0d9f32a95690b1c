"""Every bad input ends in one FlameReconError whose message names the file or field at fault
and says what to try; train.py prints it on one line and exits with status 2."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from hydra.errors import ConfigCompositionException, MissingConfigException
from omegaconf import OmegaConf

from flamerecon.errors import (
    ConfigError,
    FlameReconError,
    HullError,
    MemoryBudgetError,
    ResumeError,
)
from flamerecon.operators.projector import MatrixFreeOperator
from flamerecon.outputs.export import DensityFileError
from flamerecon.run.checkpoint import save_checkpoint
from flamerecon.run.pipeline import evaluate, prepare, reconstruct
from flamerecon.run.runner import run_task
from flamerecon.scenes import SceneError
from tests.helpers import FAST, REPO, TINY, defective, repo_env, tiny_cfg, tiny_synthetic

# (config overrides, error type, pattern the message must match)
CASES = {
    "holdout unknown view": (["holdout=[cam99]"], SceneError, r"holdout: unknown view 'cam99'.*cam00"),
    "holdout index out of range": (["holdout=[7]"], SceneError, r"holdout: view index 7 is out of range"),
    "holdout every view": (["holdout=[0,1,2,3,4]"], SceneError, r"holdout: .*holds out every view"),
    "nan in an image": (defective("nan_image"), SceneError,
                        r"defective.json .*view 'cam01': the image holds 1 NaN/Inf"),
    "inf in an image": (defective("inf_image"), SceneError, r"view 'cam00': the image holds 1 NaN/Inf"),
    "camera does not see the box": (defective("looks_away"), SceneError,
                                    r"defective.json .*view 'cam03': the camera does not see the box"),
    "image size disagrees with calibration": (
        defective("size_mismatch"), SceneError, r"view 'cam00': the image is 48x36 but its calibration says 50x36"),
    "negative focal length": (defective("negative_focal"), SceneError,
                              r"view 'cam01': K focal lengths must be positive, got fx=-"),
    "rotation not orthonormal": (defective("not_orthonormal"), SceneError,
                                 r"view 'cam02': the rotation of world_to_camera is not orthonormal"),
    "fewer view names than images": (defective("missing_view_name"), SceneError,
                                     r"5 images, 4 view names and 5 cameras"),
    "empty silhouettes": (["silhouette.threshold=1.5"], HullError,
                          (r"every training view's silhouette is empty: silhouette.threshold=1.5 is above every "
                          r"pixel.*try silhouette.threshold=0\.\d+")),
    "one empty silhouette": (defective("dark_view"), HullError,
                             (r"silhouette of view\(s\) \['cam02'\] is empty.*view 'cam02' is black; check its image "
                             r"file or hold those views out")),
    "empty visual hull": ([*defective("disjoint_silhouette"), "grid.bbox=[[-0.3,0.2,-0.3],[0.3,1,0.3]]"],
                          HullError,
                          (r"visual hull .* is empty; camera 'cam02' alone carves away the \d+ voxels.*"
                          r"silhouette.threshold=0.015 \(now 0.03\).*hull.margin_voxels=3 \(now 1\)")),
    "unknown solver name": (["solver.name=nope"], ConfigError, r"solver.name: unknown solver 'nope'.*fista"),
    "unknown projector backend": (["projector.backend=bogus"], ConfigError,
                                  r"projector.backend: unknown backend 'bogus'"),
    "negative l1": (["solver.l1=-1"], ConfigError, r"solver.l1 must be >= 0"),
    "bad grid resolution": (["grid.resolution=0"], ConfigError, r"grid.resolution: got 0; grid.resolution must be"),
    "grid too big for memory": (["grid.resolution=100000"], MemoryBudgetError,
                                (r"grid.resolution: a 66667x100000x66667 grid .* needs about .*TiB.*"
                                r"smaller grid.resolution")),
    "assembled operator too big": (
        ["projector.backend=assembled", "projector.max_memory_gb=0.001"], MemoryBudgetError,
        (r"^projector\.max_memory_gb: 5 views of 48x36 px on a .* grid need about .* more memory while .*, but "
         r"it allows 1\.0 MiB; raise it")),  # refused before any work, the budget set named

}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_message(case, tmp_path):
    overrides, kind, pattern = CASES[case]
    with pytest.raises(kind, match=pattern) as info:
        reconstruct(tiny_cfg(*overrides), tmp_path / "run")
    assert isinstance(info.value, FlameReconError) and info.value.exit_code == 2
    assert "\n" not in str(info.value)
    assert not (tmp_path / "run" / "density.npz").exists()


@pytest.mark.slow
def test_auto_backend_falls_back_to_matrix_free_when_assembled_would_not_fit():
    cfg = tiny_cfg("projector.max_memory_gb=0.001")
    setup = prepare(cfg, tiny_synthetic(), torch.device("cpu"))
    assert isinstance(setup.operator, MatrixFreeOperator)
    setup = prepare(tiny_cfg(), tiny_synthetic(), torch.device("cpu"))
    assert not isinstance(setup.operator, MatrixFreeOperator)


@pytest.mark.parametrize("override, error", [("solver=nope", MissingConfigException),
                                             ("no_such_key=1", ConfigCompositionException)])
def test_unknown_config_group_or_key_is_hydras_error(override, error):
    with pytest.raises(error, match="nope|no_such_key"):
        tiny_cfg(override)


def test_resume_errors(tmp_path):
    with pytest.raises(FlameReconError, match=r"\.hydra/config.yaml: not found"):
        run_task(OmegaConf.create({"resume": str(tmp_path / "nothing"), "debug": True}), tmp_path)
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    cfg = tiny_cfg()
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    with pytest.raises(ResumeError, match=r"checkpoint.pt: no checkpoint; the run stopped before"):
        reconstruct(cfg, run, resume=True)
    save_checkpoint(run, {"state": {"iteration": 10, "x": torch.zeros(3, 3)}, "exact": False,
                          "meta": {"solver": "fista", "shape": [1, 3]}})
    with pytest.raises(ResumeError, match=r"checkpoint.pt: field 'shape' is \[1, 3\] but the run's config"):
        reconstruct(cfg, run, resume=True)
    (run / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ResumeError, match=r"checkpoint.pt: unreadable checkpoint"):
        reconstruct(cfg, run, resume=True)


def test_damaged_density_file_on_evaluate(tmp_path):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(tiny_cfg(), run / ".hydra" / "config.yaml")
    np.savez(run / "density.npz", bbox_min=np.zeros(3))
    with pytest.raises(DensityFileError, match=r"density.npz.*'density'") as info:
        evaluate(run, device="cpu")
    assert isinstance(info.value, FlameReconError)


def test_debug_shows_the_exception_instead_of_exiting(tmp_path):
    cfg = tiny_cfg("holdout=[cam99]", "debug=true")
    with pytest.raises(SceneError):
        run_task(cfg, tmp_path)
    with pytest.raises(SystemExit) as info:
        run_task(tiny_cfg("holdout=[cam99]"), tmp_path)
    assert info.value.code == 2
    assert "unknown view 'cam99'" in (tmp_path / "FAILED").read_text()


@pytest.mark.slow
@pytest.mark.e2e
def test_train_py_prints_one_line_and_exits_2(tmp_path):
    env = repo_env()
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), *TINY, *FAST, "holdout=[cam99]", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True, env=env, timeout=300, check=False,
    )
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("flamerecon: error:")]
    assert errors == [("flamerecon: error: holdout: unknown view 'cam99'; scene 'synthetic' has views "
                      "['cam00', 'cam01', 'cam02', 'cam03', 'cam04']")]
    assert "Traceback" not in proc.stderr + proc.stdout
