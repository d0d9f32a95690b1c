"""OpenCV calibration loader: YAML/XML written by cv2.FileStorage, JSON, one file per camera;
undistortion against cv2.undistort; one-line errors for bad calibrations."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flamerecon.geometry.cameras import K_of
from flamerecon.scenes import SceneError
from flamerecon.scenes.opencv_calib import load_opencv
from tests.helpers.views import NAMES, as_float, random_images, ring_cameras, write_png

FRAME = 2
H, W = 32, 40


def opencv_K(i: int) -> np.ndarray:
    """A different K per camera, OpenCV pixel convention."""
    return np.array([[50.0 + i, 0, 19.3 + i], [0, 52.0 - i, 15.1], [0, 0, 1]])


def camera_entries(dist: np.ndarray | None = None, rvec: bool = False) -> list[dict]:
    w2c = ring_cameras(len(NAMES)).numpy()
    entries = []
    for i, name in enumerate(NAMES):
        e = {
            "name": name,
            "K": opencv_K(i),
            "t": w2c[i, :3, 3].reshape(3, 1),
            "width": W,
            "height": H,
        }
        if rvec:
            e["rvec"] = cv2.Rodrigues(w2c[i, :3, :3])[0]
        else:
            e["R"] = w2c[i, :3, :3]
        if dist is not None:
            e["dist"] = dist
        entries.append(e)
    return entries


def write_filestorage(path: Path, entries: list[dict], bbox=None, holdout=None) -> None:
    """Cameras as cv2.FileStorage writes them (strings, ints and floats as such, arrays as
    opencv-matrix), with a ``holdout`` sequence of names when given."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.startWriteStruct("cameras", cv2.FileNode_SEQ)
    for e in entries:
        fs.startWriteStruct("", cv2.FileNode_MAP)
        for key, value in e.items():
            fs.write(
                key,
                np.asarray(value, dtype=np.float64) if not isinstance(value, (str, int, float)) else value,
            )
        fs.endWriteStruct()
    fs.endWriteStruct()
    if bbox is not None:
        fs.write("bbox", np.asarray(bbox, dtype=np.float64))
    if holdout is not None:
        fs.startWriteStruct("holdout", cv2.FileNode_SEQ)
        for name in holdout:
            fs.write("", name)
        fs.endWriteStruct()
    fs.release()


def write_json(path: Path, entries: list[dict], bbox=None, holdout=(NAMES[1],)) -> None:
    plain = [
        {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in e.items()}
        for e in entries
    ]
    data = {"cameras": plain, "holdout": holdout if isinstance(holdout, str) else list(holdout)}
    if bbox is not None:
        data["bbox"] = bbox
    path.write_text(json.dumps(data))


def write_frames(folder: Path, images: np.ndarray) -> None:
    for name, image in zip(NAMES, images):
        write_png(folder / name / f"{FRAME:06d}.png", image)


def expected_K() -> torch.Tensor:
    return torch.from_numpy(
        np.stack([opencv_K(i) for i in range(len(NAMES))]) + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]
    ).float()


BOX = [[-1.0, -0.5, -1.0], [1.0, 1.5, 0.75]]


@pytest.mark.parametrize("fmt", ["yaml", "xml", "json", "folder-rvec"])
def test_round_trip(tmp_path, fmt):
    images = random_images(len(NAMES), channels=3)
    write_frames(tmp_path, images)
    if fmt in ("yaml", "xml"):
        write_filestorage(tmp_path / f"calibration.{fmt}", camera_entries(), BOX)
    elif fmt == "json":
        write_json(tmp_path / "calibration.json", camera_entries(), BOX)
    else:
        (tmp_path / "calib").mkdir()
        for e in camera_entries(rvec=True):
            fs = cv2.FileStorage(
                str(tmp_path / "calib" / f"{e['name']}.yml"), cv2.FILE_STORAGE_WRITE
            )
            for key in ("K", "rvec", "t"):
                fs.write(key, np.asarray(e[key], dtype=np.float64))
            fs.write("image_width", W)
            fs.write("image_height", H)
            fs.release()
    cfg = {"root": str(tmp_path), "frame": FRAME}
    if fmt == "folder-rvec":
        cfg.update(calibration="calib", bbox=BOX)
    scene = load_opencv(cfg)
    assert scene.views == NAMES
    torch.testing.assert_close(scene.images, as_float(images), atol=1e-6, rtol=0)
    torch.testing.assert_close(K_of(scene.cameras), expected_K(), atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.cameras.extrinsics, ring_cameras(4).float(), atol=1e-5, rtol=0)
    assert [list(scene.bbox_min), list(scene.bbox_max)] == BOX
    assert scene.default_holdout == ([NAMES[1]] if fmt == "json" else [])


def test_undistortion_matches_opencv(tmp_path):
    y, x = np.mgrid[0:H, 0:W]
    checker = (((x // 4 + y // 4) % 2) * 200 + 30).astype(np.uint8)
    images = np.repeat(checker[None, :, :, None], len(NAMES), axis=0)
    write_frames(tmp_path, images)
    dist = np.array([-0.25, 0.08, 0.001, -0.002, 0.0])
    write_filestorage(tmp_path / "calibration.yaml", camera_entries(dist=dist), BOX)
    scene = load_opencv({"root": str(tmp_path), "frame": FRAME})
    for i in range(len(NAMES)):
        expected = cv2.undistort(checker.astype(np.float32) / 255, opencv_K(i), dist)
        np.testing.assert_allclose(scene.images[i, 0].numpy(), expected, atol=1e-6)
        assert np.abs(expected - checker / 255).max() > 0.3  # the distortion did something


def test_plain_yaml_and_box_from_silhouettes(tmp_path):
    """Plain YAML (no %YAML header) and no box anywhere: the box comes from the silhouettes of a
    bright ball, and holds the ball's centre."""
    import yaml

    from flamerecon.geometry.cameras import make_cameras, project_points

    entries = camera_entries()
    K = expected_K()
    cams = make_cameras(K, ring_cameras(4).float(), H, W)
    centre = torch.tensor([[0.2, 0.1, -0.15]])
    uv, depth = project_points(cams, centre)
    images = np.zeros((len(NAMES), H, W, 1), np.uint8)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    for i in range(len(NAMES)):
        radius = K[i, 0, 0].item() * 0.3 / depth[i, 0].item()
        inside = (xx - uv[i, 0, 0].item()) ** 2 + (yy - uv[i, 0, 1].item()) ** 2 < radius**2
        images[i, inside, 0] = 220
    write_frames(tmp_path, images)
    plain = [
        {k: (np.asarray(v).tolist() if not isinstance(v, (str, int)) else v) for k, v in e.items()}
        for e in entries
    ]
    (tmp_path / "calibration.yml").write_text(yaml.safe_dump({"cameras": plain}))
    scene = load_opencv({"root": str(tmp_path), "frame": FRAME})
    lo, hi = np.array(scene.bbox_min), np.array(scene.bbox_max)
    assert scene.meta["bbox_source"] == "silhouette cones"
    assert (lo < centre.numpy()[0]).all() and (centre.numpy()[0] < hi).all()
    assert (hi - lo).max() < 1.2  # the ball has diameter 0.6; the box stays near it


def _bad(entries, i, key, value):
    if value is None:
        entries[i].pop(key)
    else:
        entries[i][key] = value
    return entries


BAD = [
    ("K", np.eye(2), r"cameras\[1\]\.K: expected shape \(3, 3\)"),
    ("K", np.diag([-50.0, 50.0, 1.0]), r"cameras\[1\]\.K: focal lengths must be positive"),
    (
        "K",
        np.array([[50, 0, np.nan], [0, 50, 16], [0, 0, 1]]),
        r"cameras\[1\]\.K\.data: holds NaN or Inf",
    ),
    ("R", np.diag([1.0, 2.0, 1.0]), r"cameras\[1\]\.R: rotation is not orthonormal"),
    ("R", np.diag([1.0, 1.0, -1.0]), r"cameras\[1\]\.R: rotation has determinant -1"),
    ("t", None, r"cameras\[1\]\.t: missing"),
    ("dist", np.zeros(3), r"cameras\[1\]\.dist: expected 4, 5, 8, 12 or 14 coefficients"),
    ("width", W + 8, r"cam01/000002\.png: image is 40x32 .*cameras\[1\]\.width/height says 48x32"),
]


@pytest.mark.parametrize("key, value, message", BAD, ids=[b[2][:40] for b in BAD])
def test_bad_calibration_names_file_and_field(tmp_path, key, value, message):
    write_frames(tmp_path, random_images(len(NAMES)))
    write_filestorage(tmp_path / "calibration.yaml", _bad(camera_entries(), 1, key, value), BOX)
    with pytest.raises(SceneError, match=message) as err:
        load_opencv({"root": str(tmp_path), "frame": FRAME})
    assert "calibration.yaml" in str(err.value) and "\n" not in str(err.value)


def test_missing_calibration_and_images(tmp_path):
    with pytest.raises(SceneError, match=r"no calibration\.yaml/\.yml/\.xml/\.json"):
        load_opencv({"root": str(tmp_path)})
    write_json(tmp_path / "calibration.json", camera_entries(), BOX)
    with pytest.raises(SceneError, match=r"camera 'cam00': found neither a video cam00\.mp4"):
        load_opencv({"root": str(tmp_path), "frame": FRAME})
    (tmp_path / "calibration.json").write_text(json.dumps({"cameras": [{"K": np.eye(3).tolist()}]}))
    with pytest.raises(SceneError, match=r"calibration\.json: cameras\[0\]\.name: missing"):
        load_opencv({"root": str(tmp_path)})


def _set(key, value, camera=1, drop=()):
    """A change of camera ``camera``'s entry: ``key`` set to ``value``, ``drop`` removed."""
    def change(entries):
        entries[camera][key] = value
        for k in drop:
            entries[camera].pop(k)
        return entries
    return change


ALL, JSON = ("yaml", "xml", "json"), ("json",)
#: (formats that can hold the damage, change of the camera entries, the message)
DAMAGED_VALUES = {
    "width as a string": (ALL, _set("width", "40"),
                          r"cameras\[1\]\.width: got the string '40'; write a number \(an integer >= 1\) without quotes"),
    "non-integer width": (ALL, _set("width", 40.5), r"cameras\[1\]\.width: got 40\.5; it must be an integer >= 1"),
    "zero height": (ALL, _set("height", 0), r"cameras\[1\]\.height: got 0; it must be an integer >= 1"),
    "negative width": (ALL, _set("width", -40), r"cameras\[1\]\.width: got -40; it must be an integer >= 1"),
    "width as a bool": (JSON, _set("width", True), r"cameras\[1\]\.width: got True; it must be an integer >= 1"),
    "width as a list": (ALL, _set("width", np.array([40.0, 41.0])),
                        r"cameras\[1\]\.width: got \[.*40\.0.*41\.0.*\]; it must be an integer >= 1"),
    "non-integer image_size": (ALL, _set("image_size", np.array([40.5, 32.0]), drop=("width", "height")),
                               r"cameras\[1\]\.image_size: got \[40\.5, 32\.0\]; it must be \[W, H\] of integers >= 1"),
    "image_size as a string": (ALL, _set("image_size", "40x32", drop=("width", "height")),
                               r"cameras\[1\]\.image_size: got '40x32'; it must be a number"),
    "image_size of three": (ALL, _set("image_size", np.array([40.0, 32.0, 3.0]), drop=("width", "height")),
                            r"cameras\[1\]\.image_size: expected shape \(2,\), got \((1, )?3,?( 1)?\)"),
    "a string in K": (JSON, _set("K", [["50", 0, 19.3], [0, 52, 15.1], [0, 0, 1]]),
                      r"cameras\[1\]\.K \(item 0\): got the string '50'; write a number"),
    "K as a map": (JSON, _set("K", {"fx": 50}), r"cameras\[1\]\.K: got \{'fx': 50\}; it must be a number"),
    "t as one string": (ALL, _set("t", "0 0 3"), r"cameras\[1\]\.t: got '0 0 3'; it must be a number"),
    "ragged t": (JSON, _set("t", [[0], [0, 1], [3]]),
                 r"cameras\[1\]\.t: got \[\[0\], \[0, 1\], \[3\]\]; it must be an array of numbers with rows"),
    "a string in dist": (JSON, _set("dist", ["-0.1", 0, 0, 0]),
                         r"cameras\[1\]\.dist \(item 0\): got the string '-0\.1'"),
    "a bool in rvec": (JSON, _set("rvec", [True, 0, 0], drop=("R",)),
                       r"cameras\[1\]\.rvec \(item 0\): got True; it must be a number"),
    "a list as the name": (JSON, _set("name", [1, 2]), r"cameras\[1\]\.name: got \[1, 2\]; it must be a non-empty string"),
    "NaN focal length": (JSON, _set("K", [[float("nan"), 0, 19.3], [0, 52, 15.1], [0, 0, 1]]),
                         r"cameras\[1\]\.K: holds NaN or Inf"),
}
CASES = [(name, fmt) for name, (formats, _, _) in DAMAGED_VALUES.items() for fmt in formats]


@pytest.mark.parametrize("case, fmt", CASES, ids=[f"{fmt}: {name}" for name, fmt in CASES])
def test_a_damaged_value_names_file_and_field(tmp_path, case, fmt):
    _, change, message = DAMAGED_VALUES[case]
    write_frames(tmp_path, random_images(len(NAMES)))
    path = tmp_path / f"calibration.{fmt}"
    entries = change(camera_entries())
    (write_json if fmt == "json" else write_filestorage)(path, entries, BOX)
    with pytest.raises(SceneError, match=message) as err:
        load_opencv({"root": str(tmp_path), "frame": FRAME})
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)


#: (what is damaged, {format: (text written by cv2.FileStorage, its damaged text)}, the message)
DAMAGED_TEXT = {
    "a matrix with more rows than data": ({"yaml": ("rows: 3", "rows: 4"), "xml": ("<rows>3</rows>", "<rows>4</rows>")},
                                          (r"cameras\[0\]\.K\.data: holds 9 numbers but cameras\[0\]\.K is 4x3 with "
                                          r"1 channel\(s\), 12 numbers; the file is truncated")),
    "rows that are not a number": ({"yaml": ("rows: 3", "rows: a"), "xml": ("<rows>3</rows>", "<rows>a</rows>")},
                                   r"cameras\[0\]\.K\.rows: got 'a'; it must be an integer >= 1"),
    "a matrix of no element type": ({"yaml": ("dt: d", "dt: q"), "xml": ("<dt>d</dt>", "<dt>q</dt>")},
                                    r"cameras\[0\]\.K\.dt: got 'q'; it must be an OpenCV element type"),
    "a word among the data": ({"yaml": ("data: [ 50.,", "data: [ fifty,"), "xml": ("50. 0.", "fifty 0.")},
                              r"cameras\[0\]\.K\.data \(item 0\): got 'fifty'; it must be a number"),
    "a width that is a word": ({"yaml": ("width: 40", "width: forty"), "xml": ("<width>40", "<width>forty")},
                               r"cameras\[0\]\.width: got 'forty'; it must be an integer >= 1"),
    "a quoted width": ({"yaml": ("width: 40", 'width: "40"'), "xml": ("<width>40", '<width>"40"')},
                       r"cameras\[0\]\.width: got the string '40'; write a number"),
}
TEXT_CASES = [(name, fmt) for name in DAMAGED_TEXT for fmt in ("yaml", "xml")]


@pytest.mark.parametrize("case, fmt", TEXT_CASES, ids=[f"{fmt}: {name}" for name, fmt in TEXT_CASES])
def test_a_damaged_filestorage_file_names_file_and_field(tmp_path, case, fmt):
    edits, message = DAMAGED_TEXT[case]
    write_frames(tmp_path, random_images(len(NAMES)))
    path = tmp_path / f"calibration.{fmt}"
    write_filestorage(path, camera_entries(), BOX)
    old, new = edits[fmt]
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(SceneError, match=message) as err:
        load_opencv({"root": str(tmp_path), "frame": FRAME})
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)


@pytest.mark.parametrize("fmt", ["yaml", "xml"])
@pytest.mark.parametrize("twentieths", range(1, 20))
def test_a_cut_short_filestorage_file_is_named_never_an_opencv_error(tmp_path, fmt, twentieths):
    """Cut anywhere: a one-line SceneError naming the file (a YAML file cut exactly between
    two cameras is a shorter valid file: it loads with fewer cameras or fails on what is missing)."""
    write_frames(tmp_path, random_images(len(NAMES)))
    path = tmp_path / f"calibration.{fmt}"
    write_filestorage(path, camera_entries(), BOX)
    text = path.read_text()
    path.write_text(text[: len(text) * twentieths // 20])
    with pytest.raises(SceneError) as err:
        load_opencv({"root": str(tmp_path), "frame": FRAME})
    message = str(err.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    assert "please report" not in message and "OpenCV(" not in message


@pytest.mark.parametrize("fmt, holdout, config", [
    ("json", "cam01", None),  # one string in a JSON calibration
    ("xml", ["cam01"], None),  # a sequence of one name, as cv2.FileStorage writes it in XML
    ("yaml", ["cam01"], None),
    ("xml", ["cam01", "cam02"], None),
    ("json", ["cam03"], "cam02"),  # one string in the config wins over the file
])
def test_a_holdout_of_one_name_is_one_view(tmp_path, fmt, holdout, config):
    write_frames(tmp_path, random_images(len(NAMES)))
    path = tmp_path / f"calibration.{fmt}"
    if fmt == "json":
        write_json(path, camera_entries(), BOX, holdout=holdout)
    else:
        write_filestorage(path, camera_entries(), BOX, holdout=holdout)
    scene = load_opencv({"root": str(tmp_path), "frame": FRAME, "holdout": config})
    expected = [config] if config else ([holdout] if isinstance(holdout, str) else holdout)
    assert scene.default_holdout == expected
