"""A capture's calibration is a file (flamerecon/fit/capture_calibration.py): ``calibration.file``
takes a given cameras.json and skips the fit, a bad one is one line naming the field, the
report reads the corrections off the cameras, and the summary says where the cameras came from."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.errors import ConfigError
from flamerecon.fit import capture_calibration, reconstruct
from flamerecon.fit.checks import check_before_work
from flamerecon.fit.reconstruct import calibrated_scene
from flamerecon.fit.refine_cameras import (
    N_PARAMS,
    RefineOptions,
    corrected_cameras,
    correction_report,
)
from flamerecon.geometry.cameras import K_of, camera_subset, make_cameras, resized_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.outputs.cameras_file import camera_records
from flamerecon.outputs.export import load_density
from flamerecon.run.pipeline import reconstruct as reconstruct_run
from flamerecon.run.summary import calibration_source, summary_table
from tests.helpers import tiny_cfg

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def scene():
    return fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32)


def options(**calibration) -> fr.ReconstructionOptions:
    return fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                    solver=fr.SolverOptions().with_values(max_iters=10),
                                    calibration=RefineOptions(**calibration))


def moved(scene, shift: float = 0.01):
    """The scene's cameras with every translation moved by ``shift`` along x."""
    E = scene.cameras.extrinsics.clone()
    E[:, 0, 3] += shift
    return make_cameras(K_of(scene.cameras), E, scene.cameras.height, scene.cameras.width)


@pytest.mark.parametrize("mode", ["pose", "none"])
def test_a_given_calibration_file_replaces_the_training_cameras_without_a_fit(scene, tmp_path, monkeypatch, mode):
    fits = []
    for module in (reconstruct, capture_calibration):
        monkeypatch.setattr(module, "refine", lambda *a, **k: fits.append(1))
    train, holdout = scene.split(None)
    given = moved(scene)
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"cameras": camera_records(scene.views, given, train)}))
    refined, record = calibrated_scene(scene, options(refine=mode, frames=(3,), file=str(path)), CPU)
    assert not fits and (record["source"], record["file"]) == ("read", str(path))
    assert torch.equal(refined.cameras.extrinsics[train], given.extrinsics[train])
    assert torch.equal(refined.cameras.extrinsics[holdout], scene.cameras.extrinsics[holdout])
    assert refined.meta["calibrated_cameras"] is scene.cameras
    assert calibration_source(record) == f"read from {path}"
    shifts = [r["translation"] for r in record["cameras"].values()]
    assert shifts == pytest.approx([0.01] * len(train), rel=1e-3)  # the centres moved by the shift


def test_a_bad_calibration_file_is_one_line_naming_the_field(scene, tmp_path):
    train, _ = scene.split(None)
    cases = {"missing.json": None, "not-json.json": "{", "no-cameras.json": json.dumps({"K": []}),
             "other-names.json": json.dumps({"cameras": [dict(r, name=f"x{i}") for i, r in
                                                         enumerate(camera_records(scene.views, scene.cameras, train))]}),
             "other-size.json": json.dumps({"cameras": [dict(r, width=2 * r["width"]) for r in
                                                        camera_records(scene.views, scene.cameras, train)]})}
    for name, text in cases.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError, match=r"^calibration\.file: .*; .*") as err:
            calibrated_scene(scene, options(refine="pose", file=str(tmp_path / name)), CPU)
        assert "\n" not in str(err.value)


def test_a_refined_scene_is_refined_again_from_the_captures_own_cameras(scene, tmp_path):
    """A scene that carries refined cameras (a loaded run's) starts from its own calibration:
    refining it again gives the cameras refining the capture gave."""
    first, _ = calibrated_scene(scene, options(refine="pose", rounds=1, iterations=1), CPU)
    again, _ = calibrated_scene(first, options(refine="pose", rounds=1, iterations=1), CPU)
    assert torch.equal(again.cameras.extrinsics, first.cameras.extrinsics)
    assert again.meta["calibrated_cameras"] is scene.cameras


def test_the_report_reads_the_corrections_off_the_cameras(scene):
    """Rotation angle, focal scale and principal point shift as the corrections theta made them."""
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    cams = camera_subset(scene.cameras, [0, 1, 2])
    theta = torch.zeros(3, N_PARAMS)
    theta[:, :3] = torch.tensor([[0.01, 0.0, 0.0], [0.0, -0.02, 0.01], [0.0, 0.0, 0.0]])
    theta[:, 6] = torch.tensor([0.01, 0.0, -0.02])
    theta[:, 7:] = torch.tensor([[1.0, -2.0], [0.0, 0.5], [0.0, 0.0]])
    refined = corrected_cameras(cams, theta, 0.5 * (grid.lo() + grid.hi()))
    report = correction_report(cams, refined, grid)
    for i, r in enumerate(report):
        assert r["rotation_deg"] == pytest.approx(math.degrees(float(theta[i, :3].norm())), abs=1e-4)
        assert r["focal_scale"] == pytest.approx(math.exp(float(theta[i, 6])), rel=1e-6)
        assert r["principal_point_px"] == pytest.approx(theta[i, 7:].tolist(), abs=1e-4)
    assert all(r["box_px"] > 0.1 for r in report)


def test_the_summary_says_whether_the_cameras_were_fitted_now_or_read():
    assert calibration_source({"source": "fitted", "file": "/c/x.json"}) == "fitted now, kept in /c/x.json"
    assert "this frame" in calibration_source({"source": "fitted", "file": None})
    assert calibration_source({"source": "read", "file": "/c/x.json"}) == "read from /c/x.json"


def test_a_runs_cameras_json_given_as_calibration_file_is_read_and_said_so(tmp_path):
    """calibration.file on the command line: a second run takes the first run's refined
    training cameras without a fit, and its metrics.json and summary say where they came from."""
    first = reconstruct_run(tiny_cfg("calibration.refine=pose", "calibration.rounds=1", "calibration.iterations=1"),
                            tmp_path / "first")
    assert (first["calibration"]["source"], first["calibration"]["file"]) == ("fitted", None)
    given = tmp_path / "first" / "cameras.json"
    second = reconstruct_run(tiny_cfg(f"calibration.file={given}"), tmp_path / "second")
    assert (second["calibration"]["source"], second["calibration"]["file"]) == ("read", str(given))
    assert f"read from {given}" in summary_table(second)
    cams = [json.loads((tmp_path / run / "cameras.json").read_text())["cameras"] for run in ("first", "second")]
    assert [(c["K"], c["world_to_camera"], c["split"]) for c in cams[0]] == [
        (c["K"], c["world_to_camera"], c["split"]) for c in cams[1]]
    densities = [load_density(tmp_path / run).density for run in ("first", "second")]
    np.testing.assert_array_equal(*densities)  # the same cameras solve to the same density


def test_a_calibration_file_is_checked_before_the_work_at_the_images_it_is_read_with(scene, tmp_path):
    """A ladder reads calibration.file on its coarsest rung's images (a full-resolution run with
    the file the default 1/4 run wrote): the check before any work takes it at that size, and
    refuses the scene's own size there."""
    train, _ = scene.split(None)
    H, W = scene.image_size
    for name, cams in {"own": scene.cameras, "half": resized_cameras(scene.cameras, H // 2, W // 2)}.items():
        (tmp_path / f"{name}.json").write_text(json.dumps({"cameras": camera_records(scene.views, cams, train)}))
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    given = {name: options(file=str(tmp_path / f"{name}.json")) for name in ("own", "half")}
    check_before_work(scene, given["own"], grid)
    check_before_work(scene, given["half"], grid, read_at=2)
    for opts, read_at in ((given["half"], None), (given["own"], 2)):
        with pytest.raises(ConfigError, match=r"^calibration\.file: .* pixels \(height, width\), the scene's"):
            check_before_work(scene, opts, grid, read_at)


def test_reusing_the_captures_operator_does_not_key_its_calibration(scene):
    """projector.reuse gives the same operator entry for entry, so a run with it off reads the
    calibration file the default run wrote; the march's step, which changes the operator, is keyed."""
    train, _ = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    base = options(refine="pose")

    def key(**projector):
        opts = base.replace(projector=replace(base.projector, **projector))
        return capture_calibration.calibration_key(scene, train, grid, opts, CPU, {})

    assert key(reuse=False) == key(reuse=True) == key(reuse="auto")
    assert key(step=0.25) != key(step=0.5)
