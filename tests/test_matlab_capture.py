"""A rig calibrated in MATLAB converts with one command (docs/own_capture.md, "MATLAB"): both of
MATLAB's conventions give the OpenCV calibration the rig was rendered with, to float precision
(K with the pixel-centre shift, R, t, distortion), stereo pairs, arrays and MAT-files too; a
file that mixes up the conventions is refused, never read wrong. Then every converter's bad
input, one row each: one line, exit status 2, nothing written."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

import flamerecon as fr
from flamerecon.scenes import SceneError
from flamerecon.scenes.convert import matlab_to_opencv
from tests.helpers import REPO, repo_env
from tests.helpers.matlab_rig import (
    BOX,
    NAMES,
    PATTERN,
    UNIT,
    matlab_camera,
    opencv_cameras,
    write_rig,
)
from tests.helpers.views import random_images, write_colmap, write_pinf

CONVENTION_SAID = {"pre": "MATLAB pre-R2022b: IntrinsicMatrix = K', pose postmultiply x_cam = x_world*R + t",
                   "post": "MATLAB R2022b+: K, pose premultiply x_cam = R*x_world + t"}


def convert(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "scripts" / "convert_capture.py"), *map(str, args)],
                          capture_output=True, text=True, env=repo_env(), cwd=REPO, check=False, timeout=300)


def as_matrix(cam: dict) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = cam["R"], cam["t"]
    return w2c


# --- the rig of issue 36 ------------------------------------------------------------------------


@pytest.mark.parametrize("convention", ["pre", "post"])
def test_a_matlab_rig_converts_to_the_calibration_it_was_rendered_with(tmp_path, convention):
    rig = write_rig(tmp_path, rendered=False)
    out = tmp_path / "out" / "calibration.yaml"
    proc = convert("matlab", rig[convention], out, "--images", rig["frames"], "--pattern", PATTERN,
                   "--unit", UNIT, "--up", "+z")
    assert proc.returncode == 0, proc.stderr
    assert CONVENTION_SAID[convention] in proc.stdout and "7 cameras" in proc.stdout and "3 frames each" in proc.stdout
    converted, reference = yaml.safe_load(out.read_text()), yaml.safe_load(rig["reference"].read_text())
    assert converted["unit"] == UNIT and converted["up"] == "+z"
    assert [c["name"] for c in converted["cameras"]] == NAMES
    for got, want in zip(converted["cameras"], reference["cameras"]):
        np.testing.assert_allclose(got["K"], want["K"], rtol=0, atol=1e-9)  # MATLAB's (1, 1) first centre: -1 px
        np.testing.assert_allclose(got["R"], want["R"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got["t"], want["t"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(got["dist"], want["dist"], rtol=0, atol=1e-15)
        assert (got["width"], got["height"]) == (96, 96)
        frames = sorted((out.parent / got["image"]).iterdir())
        assert [f.name for f in frames] == ["000000.png", "000001.png", "000002.png"]
        assert frames[1].resolve() == (rig["frames"] / f"{got['name']}_t0001.png").resolve()


def test_the_converted_rig_loads_as_the_hand_made_one(tmp_path):
    rig = write_rig(tmp_path)
    out = tmp_path / "out" / "calibration.yaml"
    assert convert("matlab", rig["pre"], out, "--images", rig["frames"], "--pattern", PATTERN).returncode == 0
    reference = fr.load_scene("opencv", root=str(rig["reference"].parent), frame=2, bbox=[list(b) for b in BOX])
    converted = fr.load_scene("opencv", root=str(out.parent), frame=2, bbox=[list(b) for b in BOX])
    assert converted.views == reference.views == NAMES
    torch.testing.assert_close(converted.cameras.intrinsics, reference.cameras.intrinsics, atol=1e-9, rtol=0)
    torch.testing.assert_close(converted.cameras.extrinsics, reference.cameras.extrinsics, atol=1e-9, rtol=0)
    torch.testing.assert_close(converted.images, reference.images, atol=0, rtol=0)
    assert float(converted.images.max()) > 0.3  # the flame, undistorted, in 16 bits


@pytest.mark.slow
@pytest.mark.e2e
def test_the_converted_rig_reconstructs_and_scores_as_the_hand_made_one(tmp_path):
    """train.py runs on the converted rig with every camera fitted, its up axis and unit from the
    file; leave-one-view-out (two cameras, a small grid) scores it as the hand-made calibration
    to 0.15 dB (every camera, the default grid: docs/results.md)."""
    rig = write_rig(tmp_path)
    out = tmp_path / "out" / "calibration.yaml"
    assert convert("matlab", rig["post"], out, "--images", rig["frames"], "--pattern", PATTERN, "--unit", UNIT,
                   "--up", "+z").returncode == 0
    quick = ["grid.resolution=24", "calibration.refine=none", "select.auto=false", "solver.max_iters=40"]
    run = subprocess.run([sys.executable, str(REPO / "train.py"), "scene=opencv", f"scene.root={out.parent}",
                          f"hydra.run.dir={tmp_path / 'run'}", *quick], capture_output=True,
                         text=True, env=repo_env(), cwd=tmp_path, timeout=900, check=False)
    assert run.returncode == 0, run.stderr
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["scene"]["up"] == "+z" and metrics["scene"]["unit"] == UNIT
    assert "all 7 cameras fitted" in run.stdout
    means = []
    for root in (out.parent, rig["reference"].parent):
        proc = subprocess.run([sys.executable, str(REPO / "scripts" / "leave_one_out.py"), "--views", "cam2,cam5",
                               "--out", tmp_path / f"loo-{root.name}", "scene=opencv", f"scene.root={root}", *quick],
                              capture_output=True, text=True, env=repo_env(), cwd=tmp_path, timeout=900, check=False)
        assert proc.returncode == 0, proc.stderr
        loo = json.loads((tmp_path / f"loo-{root.name}" / "loo.json").read_text())
        means.append(np.mean([v["psnr"] for v in loo["views"].values()]))
    assert abs(means[0] - means[1]) <= 0.15 and means[0] > 25


# --- other shapes of a MATLAB file -------------------------------------------------------------


def write_images(folder: Path, names: list[str], height: int = 96, width: int = 96) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        assert cv2.imwrite(str(folder / f"{name}.png"), np.full((height, width), 1000, np.uint16))
    return folder


@pytest.mark.parametrize("convention", ["pre", "post"])
def test_a_stereo_pair_puts_camera_1_at_the_origin(tmp_path, convention):
    one, two = opencv_cameras()[:2]
    relative = as_matrix(two) @ np.linalg.inv(as_matrix(one))  # camera 1 -> camera 2 coordinates
    R, t = relative[:3, :3], relative[:3, 3]
    pair = {"CameraParameters1": matlab_camera(one, convention), "CameraParameters2": matlab_camera(two, convention),
            "NumPatterns": 12}
    for cam in ("CameraParameters1", "CameraParameters2"):  # a stereo calibration's own pattern poses
        pair[cam].update(RotationVectors=np.zeros((12, 3)).tolist(), TranslationVectors=np.ones((12, 3)).tolist())
        pair[cam].pop("RotationMatrices", None), pair[cam].pop("PatternExtrinsics", None)
    if convention == "pre":
        pair.update(RotationOfCamera2=R.T.tolist(), TranslationOfCamera2=t.tolist())
    else:
        pair.update(PoseCamera2={"R": R.tolist(), "Translation": t.tolist(), "Dimensionality": 3})
    (tmp_path / "stereo.json").write_text(json.dumps(pair))
    conversion = matlab_to_opencv(tmp_path / "stereo.json", write_images(tmp_path / "images", ["camera1", "camera2"]),
                                  tmp_path / "calibration.yaml")
    first, second = conversion.record["cameras"]
    np.testing.assert_allclose(as_matrix(first), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(as_matrix(second), relative, atol=1e-9)
    np.testing.assert_allclose(second["K"], two["K"], atol=1e-9)
    assert "stereoParameters" in conversion.notes[0]


def test_a_saved_mat_file_of_structs_converts_as_its_json(tmp_path):
    """MATLAB's toStruct(cameraParams) saved per camera: IntrinsicMatrix and the pattern's
    RotationVectors (the same vector in both conventions, OpenCV's rvec)."""
    scipy_io = pytest.importorskip("scipy.io")
    cameras = opencv_cameras()
    structs = {}
    for cam in cameras:
        entry = matlab_camera(cam, "pre")
        structs[cam["name"]] = {k: v for k, v in entry.items() if k != "RotationMatrices"}
    scipy_io.savemat(tmp_path / "rig.mat", structs)
    images = write_images(tmp_path / "images", NAMES)
    record = matlab_to_opencv(tmp_path / "rig.mat", images, tmp_path / "calibration.yaml").record
    for got, want in zip(record["cameras"], cameras):
        np.testing.assert_allclose(got["R"], want["R"], atol=1e-12)
        np.testing.assert_allclose(got["K"], want["K"], atol=1e-9)


def test_a_pose_from_extrinsics_or_estimate_extrinsics_and_a_camera_array(tmp_path):
    """A camera's rig pose as extrinsics() gives it (RotationMatrix, postmultiply), as
    estimateExtrinsics gives it (a rigidtform3d) or as a legacy rigid3d; cameras in an array."""
    cams = opencv_cameras()[:3]
    entries = []
    for i, cam in enumerate(cams):
        entry = {k: v for k, v in matlab_camera(cam, "post").items() if k not in ("PatternExtrinsics",
                                                                                "RotationVectors", "TranslationVectors")}
        R, t = np.array(cam["R"]), cam["t"]
        entry.update([{"RotationMatrix": R.T.tolist(), "TranslationVector": t},
                      {"Extrinsics": {"R": R.tolist(), "Translation": t}},
                      {"Extrinsics": {"Rotation": R.T.tolist(), "Translation": t}}][i])
        entries.append(entry)
    (tmp_path / "rig.json").write_text(json.dumps(entries))
    record = matlab_to_opencv(tmp_path / "rig.json", write_images(tmp_path / "images", ["cam1", "cam2", "cam3"]),
                              tmp_path / "calibration.yaml").record
    for got, want in zip(record["cameras"], cams):
        np.testing.assert_allclose(as_matrix(got), as_matrix(want), atol=1e-12)


def pre_rig(tmp_path: Path, change=None, images: tuple[int, int] = (96, 96)) -> Path:
    """The rig's first two cameras in the pre-R2022b convention, ``change`` applied to cam1's
    entry, their images (``images``: rows, cols) beside it."""
    entries = {c["name"]: matlab_camera(c, "pre") for c in opencv_cameras()[:2]}
    for entry in entries.values():
        entry["ImageSize"] = list(images)
    if change is not None:
        change(entries["cam1"])
    (tmp_path / "rig.json").write_text(json.dumps(entries))
    write_images(tmp_path, list(entries), *images)
    return tmp_path / "rig.json"


def transpose(key: str):
    return lambda e: e.update({key: np.array(e[key]).T.tolist()})


# (change to cam1's entry, the error's words): a file whose conventions are mixed up is refused
REFUSED = {
    "IntrinsicMatrix given as K": (lambda e: e.update(K=e.pop("IntrinsicMatrix")),
                                   r"cam1\.K: has the layout of pre-R2022b's IntrinsicMatrix"),
    "K given as IntrinsicMatrix": (transpose("IntrinsicMatrix"), r"cam1\.IntrinsicMatrix: has the layout of K"),
    "K and IntrinsicMatrix disagree": (lambda e: e.update(K=np.array(e["IntrinsicMatrix"]).tolist()),
                                       r"cam1\.K: has the layout"),
    "FocalLength disagrees": (lambda e: e.update(FocalLength=[1.0, 2.0]), r"cam1\.FocalLength/PrincipalPoint: disagree"),
    "a premultiply rotation under a postmultiply name": (transpose("RotationMatrices"),
                                                         r"cam1\.RotationVectors: disagrees with RotationMatrices"),
    "NaN (jsonencode's null)": (lambda e: e.update(TranslationVectors=[1.0, None, 2.0]),
                                r"cam1\.TranslationVectors \(item 1\): missing"),
    "not a rotation": (lambda e: e.update(RotationMatrices=(2 * np.array(e["RotationMatrices"])).tolist()),
                       r"cam1\.RotationMatrices: rotation is not orthonormal"),
    "a reflection": (lambda e: e.update(RotationMatrices=(-np.array(e["RotationMatrices"])).tolist()),
                     r"cam1\.RotationMatrices: rotation has determinant -1"),
    "many patterns": (lambda e: e.update(TranslationVectors=[e["TranslationVectors"]] * 4),
                      r"cam1\.TranslationVectors: holds 4 pattern poses, not the rig's one"),
    "no pose": (lambda e: [e.pop(k) for k in ("RotationMatrices", "RotationVectors", "TranslationVectors")],
                r"cam1\.pose: missing"),
    "no intrinsics": (lambda e: [e.pop(k) for k in ("IntrinsicMatrix", "FocalLength", "PrincipalPoint")],
                      r"cam1: not a camera"),
    "two radial terms too many": (lambda e: e.update(RadialDistortion=[0.1, 0.2, 0.3, 0.4, 0.5]),
                                  r"cam1\.RadialDistortion: expected \[k1 k2\] or \[k1 k2 k3\]"),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_a_mixed_up_matlab_file_is_refused(tmp_path, case):
    change, words = REFUSED[case]
    with pytest.raises(SceneError, match=words):
        matlab_to_opencv(pre_rig(tmp_path, change), tmp_path, tmp_path / "out" / "calibration.yaml")


def test_image_size_is_rows_then_columns(tmp_path):
    path = pre_rig(tmp_path, images=(32, 40))
    assert matlab_to_opencv(path, tmp_path, tmp_path / "out.yaml").record["cameras"][0]["width"] == 40
    swapped = pre_rig(tmp_path, lambda e: e.update(ImageSize=[40, 32]), images=(32, 40))
    with pytest.raises(SceneError, match=r"cam1: ImageSize is \[40, 32\] but .* is 32 rows x 40 columns \(MATLAB's "
                                         r"ImageSize is \[rows, cols\]: this one is \[cols, rows\]\)"):
        matlab_to_opencv(swapped, tmp_path, tmp_path / "out.yaml")


def test_a_key_given_twice_is_refused(tmp_path):
    (tmp_path / "rig.json").write_text('{"cam1": {"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "cam1": {}}')
    with pytest.raises(SceneError, match=r"rig.json: key 'cam1' appears twice in one object"):
        matlab_to_opencv(tmp_path / "rig.json", tmp_path, tmp_path / "out.yaml")


# --- every converter's bad input: one line, exit status 2, nothing written ---------------------


def capture(root: Path) -> dict[str, Path]:
    """A COLMAP model (ring cameras, images/), a PINF capture and the MATLAB rig (blank images)
    side by side under ``root``."""
    model = write_colmap(root / "colmap", random_images(4))
    write_pinf(root / "pinf", random_images(4))
    rig = write_rig(root / "matlab", rendered=False)
    return {"model": model, "images": root / "colmap" / "images", "pinf": root / "pinf" / "info.json", **rig}


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def first_pose_line(d: dict) -> str:
    return next(line for line in (d["model"] / "images.txt").read_text().splitlines() if line.startswith("1 "))


def set_first_quaternion(d: dict, quaternion: str) -> None:
    line = first_pose_line(d)
    fields = line.split()
    edit(d["model"] / "images.txt", line, " ".join([fields[0], quaternion, *fields[5:]]))


def add_link_folder_in_the_way(d: dict) -> None:
    (d["frames"].parent / "out" / "cam1").mkdir(parents=True)
    (d["frames"].parent / "out" / "cam1" / "notes.txt").write_text("mine")


OUT = "out/calibration.yaml"
# case: (arguments after convert_capture.py, with <model> <images> <pinf> <pre> <frames> <root>
# filled in; a change to the inputs first or None; the words of the one line)
CASES = {
    "colmap onto its own cameras.txt": (["colmap", "<model>", "<model>/cameras.txt"], None,
                                        r"cameras\.txt: is the converter's own input"),
    "colmap onto its own images.txt, forced": (["colmap", "<model>", "<model>/images.txt", "--force"], None,
                                               r"images\.txt: is the converter's own input"),
    "a zero quaternion": (["colmap", "<model>", OUT], lambda d: set_first_quaternion(d, "0 0 0 0"),
                          r"images\.txt: line 2: QW QX QY QZ: a zero quaternion is no rotation"),
    "a NaN quaternion": (["colmap", "<model>", OUT], lambda d: set_first_quaternion(d, "nan 0 0 1"),
                         r"images\.txt: line 2: QW QX QY QZ TX TY TZ: holds NaN or Inf"),
    "a quaternion of norm 2": (["colmap", "<model>", OUT], lambda d: set_first_quaternion(d, "2 0 0 0"),
                               r"images\.txt: line 2: QW QX QY QZ: not a unit quaternion \(norm 2\)"),
    "a CAMERA_ID defined twice": (["colmap", "<model>", OUT],
                                  lambda d: edit(d["model"] / "cameras.txt", "\n1 PINHOLE", "\n1 PINHOLE 40 32 1 1 1 1\n1 PINHOLE"),
                                  r"cameras\.txt: line 3: CAMERA_ID 1 is defined twice \(lines 2 and 3\)"),
    "an IMAGE_ID defined twice": (["colmap", "<model>", OUT], lambda d: edit(d["model"] / "images.txt", "\n2 ", "\n1 "),
                                  r"images\.txt: line \d+: IMAGE_ID 1 is defined twice"),
    "a NaN focal length": (["colmap", "<model>", OUT], lambda d: edit(d["model"] / "cameras.txt", "PINHOLE 40 32 45.0",
                                                                       "PINHOLE 40 32 nan"),
                           r"cameras\.txt: line 2: PARAMS: holds NaN or Inf"),
    "a line of neither kind": (["colmap", "<model>", OUT], lambda d: edit(d["model"] / "images.txt", "12.5 3.5 -1",
                                                                           "12.5 3.5 -1 7"),
                               r"images\.txt: line \d+: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
    "an image that is not there": (["colmap", "<model>", OUT, "--images", "<root>"], None,
                                   r"images\.txt: line 2: image 'cam00\.png' not found in"),
    "an output that exists": (["colmap", "<model>", "<model>/../notes.yaml"],
                              lambda d: (d["model"].parent / "notes.yaml").write_text("mine"),
                              r"notes\.yaml: exists; give --force to replace it"),
    "an output that is not YAML": (["colmap", "<model>", "out/calibration.json"], None,
                                   r"calibration\.json: the converter writes YAML"),
    "an unknown held-out camera": (["colmap", "<model>", OUT, "--holdout", "cam99"], None,
                                   r"--holdout: 'cam99' is not a camera"),
    "a box with NaN": (["colmap", "<model>", OUT, "--bbox=0,0,0,nan,1,1"], None, r"argument --bbox: expected xmin"),
    "a unit of 0": (["colmap", "<model>", OUT, "--unit", "0"], None, r"argument --unit: got '0'; give metres"),
    "an up that is no axis": (["colmap", "<model>", OUT, "--up", "z"], None, r"argument --up: invalid choice: 'z'"),
    "a pattern without {camera}": (["matlab", "<pre>", OUT, "--pattern", "t{frame}.png"], None,
                                   r"argument --pattern: 't\{frame\}\.png' has no \{camera\} field"),
    "a pattern with another field": (["matlab", "<pre>", OUT, "--pattern", "{view}.png"], None,
                                     r"argument --pattern: '\{view\}\.png': unknown field \{view\}"),
    "a pattern that fits no file": (["matlab", "<pre>", OUT, "--images", "<frames>", "--pattern", "{camera}.tif"], None,
                                    r"no file fits --pattern '\{camera\}\.tif' for camera 'cam1'"),
    "matlab without images": (["matlab", "<pre>", OUT], None, r"no image of camera 'cam1'"),
    "matlab onto its own file": (["matlab", "<pre_yaml>", "<pre_yaml>", "--images", "<frames>", "--pattern", PATTERN,
                                  "--force"], lambda d: d["pre"].rename(d["pre"].with_suffix(".yaml")),
                                 r"matlab_pre\.yaml: is the converter's own input"),
    "a frame folder in the way": (["matlab", "<pre>", "<root>/matlab/out/calibration.yaml", "--images", "<frames>",
                                   "--pattern", PATTERN, "--force"], add_link_folder_in_the_way,
                                  r"out/cam1: exists; .* it holds files that are not links"),
    "pinf with --pattern": (["pinf", "<pinf>", OUT, "--pattern", "{camera}.png"], None,
                            r"--images and --pattern are for colmap and matlab"),
    "pinf cameras of one name": (["pinf", "<pinf>", OUT],
                                 lambda d: edit(d["pinf"], '"cam01.mp4"', '"cam00.mp4"'),
                                 r"info\.json: train_videos\[1\]\.file_name: camera 'cam00' appears twice"),
    "pinf NaN pose": (["pinf", "<pinf>", OUT], lambda d: edit(d["pinf"], '"transform_matrix": [[', '"transform_matrix": [[NaN, '),
                      r"train_videos\[0\]\.transform_matrix"),
    "pinf onto its own info.json": (["pinf", "<pinf_yaml>", "<pinf_yaml>", "--force"],
                                    lambda d: d["pinf"].rename(d["pinf"].with_suffix(".yaml")),
                                    r"info\.yaml: is the converter's own input"),
}


def snapshot(root: Path) -> dict[str, tuple]:
    return {str(p.relative_to(root)): (p.is_symlink(), p.stat().st_size if p.is_file() else None,
                                       p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


@pytest.mark.e2e
@pytest.mark.parametrize("case", list(CASES))
def test_a_converter_refuses_bad_input_in_one_line_and_writes_nothing(tmp_path, case):
    args, change, words = CASES[case]
    d = capture(tmp_path)
    if change is not None:
        change(d)
    names = {**{k: str(v) for k, v in d.items()}, "root": str(tmp_path),
             "pre_yaml": str(d["pre"].with_suffix(".yaml")), "pinf_yaml": str(d["pinf"].with_suffix(".yaml"))}
    before = snapshot(tmp_path)
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "convert_capture.py"),
                           *[re.sub(r"<(\w+)>", lambda m: names[m[1]], a) for a in args]],
                          capture_output=True, text=True, env=repo_env(), cwd=tmp_path, check=False, timeout=300)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stdout == "" and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("flamerecon: error: ")
    assert re.search(words, proc.stderr), proc.stderr
    assert snapshot(tmp_path) == before  # nothing written, nothing replaced


def test_an_image_name_with_a_space_is_read_whole(tmp_path):
    d = capture(tmp_path)
    edit(d["model"] / "images.txt", "cam00.png", "cam 00.png")
    (d["images"] / "cam00.png").rename(d["images"] / "cam 00.png")
    proc = convert("colmap", d["model"], tmp_path / OUT)
    assert proc.returncode == 0, proc.stderr
    assert yaml.safe_load((tmp_path / OUT).read_text())["cameras"][0]["name"] == "cam 00"


def test_a_mat_file_without_scipy_says_how_to_install_it(tmp_path, monkeypatch):
    scipy_io = pytest.importorskip("scipy.io")
    scipy_io.savemat(tmp_path / "rig.mat", {"cam1": {"K": np.eye(3)}})
    monkeypatch.setitem(sys.modules, "scipy.io", None)  # as where scipy is not installed
    with pytest.raises(SceneError, match=r"rig\.mat: reading a MAT-file needs scipy: pip install 'flamerecon\[matlab\]'"):
        matlab_to_opencv(tmp_path / "rig.mat", tmp_path, tmp_path / "out.yaml")


def test_a_colmap_model_of_a_video_rig_maps_its_flat_folder_by_pattern(tmp_path):
    """COLMAP calibrated one frame of each camera (cam00_t0000.png ...): --pattern names the
    camera by {camera} and links every frame of it found in the flat folder."""
    d = capture(tmp_path)
    for name in ["cam00", "cam01", "cam02", "cam03"]:
        edit(d["model"] / "images.txt", f" {name}.png", f" {name}_t0000.png")
        (d["images"] / f"{name}.png").rename(d["images"] / f"{name}_t0000.png")
        (d["images"] / f"{name}_t0001.png").write_bytes((d["images"] / f"{name}_t0000.png").read_bytes())
    proc = convert("colmap", d["model"], tmp_path / OUT, "--pattern", PATTERN, "--unit", "0.001", "--up", "-y")
    assert proc.returncode == 0, proc.stderr
    record = yaml.safe_load((tmp_path / OUT).read_text())
    assert [c["name"] for c in record["cameras"]] == ["cam00", "cam01", "cam02", "cam03"]
    assert (record["unit"], record["up"]) == (0.001, "-y")
    assert sorted(p.name for p in (tmp_path / "out" / "cam02").iterdir()) == ["000000.png", "000001.png"]
    scene = fr.load_scene("opencv", root=str(tmp_path / "out"), frame=1, bbox=[[-1, -1, -1], [1, 1, 1]])
    assert scene.views == ["cam00", "cam01", "cam02", "cam03"]
