"""A capture of one's own (docs/own_capture.md): the example folder in the repository loads and
reconstructs; the converters from PINF/HyFluid info.json and COLMAP's text model give the cameras
the original loader (or the original numbers) give; the capture check finds a camera turned by a
few degrees, a box too small and a pose given the wrong way round."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from kornia.geometry.camera import PinholeCamera

import flamerecon as fr
from flamerecon.evaluate.capture_check import check_capture, check_figure
from flamerecon.geometry.cameras import opencv_w2c_to_opengl_c2w
from flamerecon.scenes import SceneError
from flamerecon.scenes.convert import colmap_to_opencv, pinf_to_opencv, write_calibration
from tests.helpers import REPO, repo_env
from tests.helpers.matlab_rig import BOX as RIG_BOX
from tests.helpers.matlab_rig import write_rig
from tests.helpers.views import (
    BOX,
    NAMES,
    centred_K,
    random_images,
    ring_cameras,
    write_colmap,
    write_pinf,
)

EXAMPLE = REPO / "examples" / "capture"
REAL = REPO.parent / "shared" / "data" / "scalarflow_real"
SILHOUETTE = {"method": "threshold", "threshold": 0.03, "speck_px": 1, "dilate_px": 2}


def script(name: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "scripts" / name), *map(str, args)], capture_output=True,
                          text=True, env=repo_env(), cwd=REPO, check=False, timeout=600)


def assert_same_cameras(a: fr.Scene, b: fr.Scene) -> None:
    assert a.views == b.views
    torch.testing.assert_close(a.cameras.intrinsics, b.cameras.intrinsics, atol=1e-4, rtol=0)
    torch.testing.assert_close(a.cameras.extrinsics, b.cameras.extrinsics, atol=1e-5, rtol=0)
    torch.testing.assert_close(a.images, b.images, atol=0, rtol=0)


# --- the example folder -----------------------------------------------------------------------


def test_the_example_capture_loads_and_reconstructs():
    scene = fr.load_scene("opencv", root=str(EXAMPLE))
    assert scene.num_views == len(scene.views) == 5 and scene.default_holdout == ["cam04"]
    assert scene.image_size == (48, 64) and scene.bbox_max == (0.5, 1.5, 0.5)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=20),
                                       solver=fr.SolverOptions().with_values(max_iters=150))
    held = fr.score(fr.reconstruct(scene, options))["heldout"]["cam04"]
    assert held["psnr"] > held["psnr_black"] + 8  # a prediction of the unseen camera, not a black image


def test_the_example_is_the_synthetic_flame_as_its_own_capture():
    """examples/capture/make_capture.py wrote the synthetic scene's cameras: the loader gives
    them back (the file's K in OpenCV's pixel convention, shifted back by half a pixel)."""
    synthetic = fr.load_scene("synthetic", width=64, height=48, n_cameras=5, phantom_resolution=32)
    scene = fr.load_scene("opencv", root=str(EXAMPLE))
    torch.testing.assert_close(scene.cameras.intrinsics, synthetic.cameras.intrinsics, atol=1e-4, rtol=0)
    torch.testing.assert_close(scene.cameras.extrinsics, synthetic.cameras.extrinsics, atol=1e-6, rtol=0)
    # 8-bit PNGs: half a step of rounding, plus the render's own float noise, which moves a value
    # lying near a half step across it (seen: 4e-5 with another thread count than the example's)
    assert (scene.images - synthetic.images.clamp(0, 1)).abs().max() <= 0.5 / 255 + 1e-4


# --- converters -------------------------------------------------------------------------------


def test_pinf_converted_loads_as_the_pinf_loader_loads_it(tmp_path):
    write_pinf(tmp_path / "pinf", random_images(len(NAMES), 3))
    out = tmp_path / "converted" / "calibration.yaml"
    record = pinf_to_opencv(tmp_path / "pinf" / "info.json", out).record
    write_calibration(out, record, "test")
    pinf = fr.load_scene("pinf", root=str(tmp_path / "pinf"))
    converted = fr.load_scene("opencv", root=str(out.parent))
    assert_same_cameras(pinf, converted)
    assert converted.default_holdout == pinf.default_holdout == NAMES[2:]
    np.testing.assert_allclose(converted.bbox_min, pinf.bbox_min, atol=1e-12)
    np.testing.assert_allclose(converted.bbox_max, pinf.bbox_max, atol=1e-12)


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "info.json").is_file(), reason=f"real capture absent: {REAL}")
def test_scalarflow_converted_is_scalarflow(tmp_path):
    proc = script("convert_capture.py", "pinf", REAL / "info.json", tmp_path / "calibration.yaml")
    assert proc.returncode == 0, proc.stderr
    assert "5 cameras" in proc.stdout and "held out: train02" in proc.stdout
    pinf = fr.load_scene("pinf", root=str(REAL), frame=59, downscale=4)
    converted = fr.load_scene("opencv", root=str(tmp_path), frame=59, downscale=4)
    assert_same_cameras(pinf, converted)
    assert converted.default_holdout == ["train02"] and converted.bbox_min == pinf.bbox_min


def test_colmap_converted_has_the_cameras_written(tmp_path):
    model = write_colmap(tmp_path, random_images(len(NAMES), 3))
    proc = script("convert_capture.py", "colmap", model, tmp_path / "out" / "calibration.yaml",
                  "--holdout", "cam03", "--bbox=" + ",".join(map(str, [*BOX[0], *BOX[1]])))
    assert proc.returncode == 0, proc.stderr
    scene = fr.load_scene("opencv", root=str(tmp_path / "out"))
    assert scene.views == NAMES and scene.default_holdout == ["cam03"] and scene.bbox_min == BOX[0]
    K = torch.from_numpy(centred_K()).float()
    torch.testing.assert_close(scene.cameras.intrinsics[:, :3, :3], K.expand(len(NAMES), 3, 3), atol=1e-4, rtol=0)
    torch.testing.assert_close(scene.cameras.extrinsics, ring_cameras(len(NAMES)).float(), atol=1e-6, rtol=0)


def test_colmap_distortion_goes_into_opencvs_order(tmp_path):
    model = write_colmap(tmp_path, random_images(len(NAMES)), "OPENCV", "45 46 20.5 16.5 0.1 -0.02 0.001 0.002")
    record = colmap_to_opencv(model, tmp_path / "images", tmp_path / "calibration.yaml").record
    camera = record["cameras"][0]
    assert camera["dist"] == [0.1, -0.02, 0.001, 0.002]
    assert camera["K"] == [[45.0, 0.0, 20.0], [0.0, 46.0, 16.0], [0.0, 0.0, 1.0]]  # OpenCV's pixel convention
    assert camera["image"] == "images/cam00.png"


@pytest.mark.parametrize("cameras, images, message", [
    ("1 FISHEYE 40 32 1 2 3", None, r"cameras.txt: line 1: camera model FISHEYE is not supported"),
    ("1 PINHOLE 40 32 45 45 20", None, r"cameras.txt: line 1: PINHOLE takes 4 parameters \(fx fy cx cy\), got 3"),
    ("1 PINHOLE 40 32 45 45 20 x", None, r"cameras.txt: line 1: PARAMS: expected numbers"),
    ("1 PINHOLE 40 32 45 45 20 16", "1 1 0 0 0 0 0 3 7 a.png\n", r"images.txt: line 1: CAMERA_ID 7 is not in"),
    ("1 PINHOLE 40 32 45 45 20 16", "1 1 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 0 0 3 1 a.png\n",
     r"images.txt: line 3: camera name 'a' \(the image's stem\) appears twice"),
])
def test_a_bad_colmap_model_names_the_file_and_line(tmp_path, cameras, images, message):
    (tmp_path / "cameras.txt").write_text(cameras + "\n")
    (tmp_path / "images.txt").write_text(images or "1 1 0 0 0 0 0 3 1 a.png\n")
    with pytest.raises(SceneError, match=message):
        colmap_to_opencv(tmp_path, tmp_path, tmp_path / "calibration.yaml")
    with pytest.raises(SceneError, match=r"nowhere/cameras.txt: not found .*model_converter"):
        colmap_to_opencv(tmp_path / "nowhere", tmp_path, tmp_path / "calibration.yaml")


# --- what to check first ----------------------------------------------------------------------


def with_cameras(scene: fr.Scene, extrinsics: torch.Tensor) -> fr.Scene:
    cams = scene.cameras
    return type(scene)(**{**scene.__dict__, "cameras": PinholeCamera(cams.intrinsics, extrinsics, cams.height,
                                                                     cams.width)})


def test_the_check_passes_the_example_and_finds_a_turned_camera():
    scene = fr.load_scene("opencv", root=str(EXAMPLE))
    checks, masks, footprints = check_capture(scene, SILHOUETTE)
    assert not [p for c in checks for p in c.problems] and min(c.hull_iou for c in checks) > 0.7
    a = math.radians(5)  # cam02 turned by 5 degrees about its own vertical axis: ~8 px at 64 px
    turn = torch.eye(4)
    turn[[0, 0, 2, 2], [0, 2, 0, 2]] = torch.tensor([math.cos(a), math.sin(a), -math.sin(a), math.cos(a)])
    extrinsics = scene.cameras.extrinsics.clone()
    extrinsics[2] = turn @ extrinsics[2]
    turned, _, _ = check_capture(with_cameras(scene, extrinsics), SILHOUETTE)
    assert min(turned, key=lambda c: c.hull_iou).name == "cam02"
    assert any("overlap by IoU" in p for p in turned[2].problems)
    figure = check_figure(scene, checks, masks, footprints)
    assert figure.shape[1] == 4 * 320 and figure.dtype == np.uint8


def test_the_check_finds_a_small_box_and_an_inverted_pose():
    scene = fr.load_scene("opencv", root=str(EXAMPLE))
    small, _, _ = check_capture(scene, SILHOUETTE, bbox=[[-0.2, 0.3, -0.2], [0.2, 0.9, 0.2]])
    assert all(any("outside the box's outline: enlarge the box" in p for p in c.problems) for c in small)
    extrinsics = scene.cameras.extrinsics.clone()
    extrinsics[1:3] = torch.linalg.inv(extrinsics[1:3])  # camera->world given where world->camera belongs
    inverted, _, _ = check_capture(with_cameras(scene, extrinsics), SILHOUETTE)
    assert "does not see the box" in inverted[1].problems[0] and "behind it" in inverted[2].problems[0]
    assert all("x_cam = R x_world + t" in c.problems[0] for c in inverted[1:3])


def test_each_pose_hint_names_the_convention_it_fixes(tmp_path):
    """On the MATLAB rig: a pose given camera->world is told to invert, one with OpenGL's axes
    to invert and flip, a MATLAB postmultiply one to transpose R only (inverting would break it)."""
    rig = write_rig(tmp_path, rendered=True, frames=(0,))
    scene = fr.load_scene("opencv", root=str(rig["reference"].parent), bbox=[list(b) for b in RIG_BOX])
    assert not [p for c in check_capture(scene, SILHOUETTE)[0] for p in c.problems]
    extrinsics = scene.cameras.extrinsics.clone()
    extrinsics[1] = torch.linalg.inv(extrinsics[1])
    extrinsics[2] = opencv_w2c_to_opengl_c2w(extrinsics[2])
    extrinsics[4, :3, :3] = extrinsics[4, :3, :3].T.clone()  # x_cam = x_world * R + t
    checks, _, _ = check_capture(with_cameras(scene, extrinsics), SILHOUETTE)
    said = {c.name: c.problems[0] for c in checks if c.problems}
    assert "camera->world (Blender, NeRF without their axes)" in said["cam2"] and "invert it" in said["cam2"]
    assert "with OpenGL's axes" in said["cam3"] and "flip its y and z" in said["cam3"]
    assert "MATLAB's postmultiply rotation" in said["cam5"] and "transpose R only" in said["cam5"]
    assert "enlarge the box" not in said["cam5"] and "invert" not in said["cam5"]


def without_box(folder: Path) -> Path:
    """A copy of the example capture whose calibration file gives no box."""
    shutil.copytree(EXAMPLE, folder)
    calibration = yaml.safe_load((folder / "calibration.yaml").read_text())
    del calibration["bbox"]
    (folder / "calibration.yaml").write_text(yaml.safe_dump(calibration))
    return folder


def test_a_box_the_loader_estimated_is_not_blamed_on_the_capture(tmp_path):
    """Without a box the loader estimates one from the silhouettes: by default from masks like the
    fit's, so that it holds them; estimated from narrower ones (Otsu's), the check puts the
    silhouette outside it down to that estimate, not to a box the user never gave."""
    capture = without_box(tmp_path / "capture")
    checks, _, _ = check_capture(fr.load_scene("opencv", root=str(capture)), SILHOUETTE)
    assert not [p for c in checks for p in c.problems]
    narrow = fr.load_scene("opencv", root=str(capture), silhouette={"method": "otsu", "dilate_px": 2})
    assert narrow.meta["bbox_source"] == "silhouette cones"
    problems = [p for c in check_capture(narrow, SILHOUETTE)[0] for p in c.problems]
    assert problems and all("the box the loader estimated (from scene.silhouette's masks)" in p for p in problems)
    assert not any("enlarge the box" in p for p in problems)


@pytest.mark.e2e
def test_the_check_script_prints_a_table_and_writes_its_picture(tmp_path):
    proc = script("check_capture.py", "scene=opencv", f"scene.root={EXAMPLE}", "--out", tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "no problem found" in proc.stdout and "hull IoU" in proc.stdout
    assert (tmp_path / "capture_check.png").is_file()


@pytest.mark.e2e
def test_the_check_script_exits_1_on_a_problem_and_writes_beside_the_capture(tmp_path):
    capture = tmp_path / "capture"
    shutil.copytree(EXAMPLE, capture)
    calibration = yaml.safe_load((capture / "calibration.yaml").read_text())
    calibration["bbox"] = [[-0.2, 0.3, -0.2], [0.2, 0.9, 0.2]]  # too small
    (capture / "calibration.yaml").write_text(yaml.safe_dump(calibration))
    proc = script("check_capture.py", "scene=opencv", f"scene.root={capture}")
    assert proc.returncode == 1, proc.stderr
    assert "PROBLEMS (" in proc.stdout and proc.stdout.count("enlarge the box") == 5
    assert f"picture: {capture / 'check' / 'capture_check.png'}" in proc.stdout
    assert (capture / "check" / "capture_check.png").is_file() and not (REPO / "outputs" / "check").exists()
