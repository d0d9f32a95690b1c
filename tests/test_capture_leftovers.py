"""What earlier red-team passes left (issue 38, family 6), one table per case kind: a camera
name or image path holding a control character (a NUL used to end in ``ValueError: embedded null
byte``), a camera given R and rvec that disagree, and images whose EXIF orientation turns them
(read as displayed, in every format that carries the tag; a size that then disagrees with the
calibration is refused naming the orientation). The warnings of a tiny field of view and a
1x1x1 grid are in tests/test_result_warnings.py."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flamerecon.scenes import SceneError, load_scene
from flamerecon.scenes.frames import read_image
from flamerecon.scenes.orientation import TURNS, displayed, exif_orientation
from tests.helpers import REPO, repo_env
from tests.helpers.views import (
    BOX,
    HEIGHT,
    NAMES,
    WIDTH,
    centred_K,
    random_images,
    ring_cameras,
    write_png,
)

ERROR = "flamerecon: error: "


def opencv_capture(root: Path, *, names=None, poses=None, image_ext: str = ".png", images=None, size=None) -> Path:
    """calibration.json (a camera list) and NAME/000000.<ext> per camera; ``poses``: {camera: the
    pose fields to write instead of R and t}."""
    root.mkdir(parents=True, exist_ok=True)
    names = names or NAMES
    E = ring_cameras(len(names)).numpy()
    images = random_images(len(names), 3) if images is None else images
    cameras = []
    for i, name in enumerate(names):
        entry = {"name": name, "K": centred_K().tolist(), "R": E[i, :3, :3].tolist(), "t": E[i, :3, 3].tolist(),
                 "width": (size or (WIDTH, HEIGHT))[0], "height": (size or (WIDTH, HEIGHT))[1]}
        entry.update((poses or {}).get(i, {}))
        cameras.append(entry)
        if "\0" not in name and image_ext == ".png":
            write_png(root / name / "000000.png", images[i])
    (root / "calibration.json").write_text(json.dumps({"cameras": cameras, "holdout": [names[-1]],
                                                       "bbox": [list(BOX[0]), list(BOX[1])]}))
    return root


def rvec_of(i: int, degrees_off: float = 0.0) -> list[float]:
    """Camera i's rotation as an rvec, turned ``degrees_off`` further about its own z axis."""
    R = ring_cameras(len(NAMES)).numpy()[i, :3, :3]
    turn = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(degrees_off)]))[0]
    return cv2.Rodrigues(turn @ R)[0].ravel().tolist()


# (the capture's change, the error's pattern or None: it loads)
CAPTURES = {
    "a NUL in a camera name": ({"names": ["cam\0x", *NAMES[1:]]},
                               r"calibration\.json: cameras\[0\]\.name: 'cam\\x00x' holds a control character"),
    "a newline in a camera name": ({"names": ["cam\n0", *NAMES[1:]]},
                                   r"cameras\[0\]\.name: 'cam\\n0' holds a control character"),
    "a NUL in an image path": ({"poses": {2: {"image": "cam02/\0.png"}}},
                               r"cameras\[2\]\.image: 'cam02/\\x00\.png' holds a control character"),
    "R and rvec of one rotation": ({"poses": {1: {"rvec": rvec_of(1)}}}, None),
    "R and rvec 0.005 degrees apart (a written file's rounding)": ({"poses": {1: {"rvec": rvec_of(1, 0.005)}}}, None),
    "R and rvec 5 degrees apart": ({"poses": {1: {"rvec": rvec_of(1, 5.0)}}},
                                   (r"cameras\[1\]\.R and cameras\[1\]\.rvec disagree: they are rotations 5 degrees "
                                   r"apart; give one of them")),
    "rvec alone": ({"poses": {1: {"R": None, "rvec": rvec_of(1)}}}, None),
}


@pytest.mark.parametrize("case", list(CAPTURES))
def test_names_and_poses_that_cannot_be_used_are_refused_by_field(case, tmp_path):
    change, message = CAPTURES[case]
    change = dict(change)
    poses = change.pop("poses", {})
    root = opencv_capture(tmp_path, poses=poses, **change)
    data = json.loads((root / "calibration.json").read_text())
    for camera in data["cameras"]:  # "R": None in a case: the file gives rvec alone
        if "R" in camera and camera["R"] is None:
            del camera["R"]
    (root / "calibration.json").write_text(json.dumps(data))
    load = lambda: load_scene({"name": "opencv", "root": str(root)})
    if message is None:
        scene = load()
        assert scene.views == NAMES
        return
    with pytest.raises(SceneError, match=message):
        load()


@pytest.mark.e2e
def test_a_nul_in_a_camera_name_is_one_line_from_train_py(tmp_path):
    root = opencv_capture(tmp_path / "capture", names=["cam\0x", *NAMES[1:]])
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), "scene=opencv", f"scene.root={root}",
                           f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, env=repo_env(),
                          timeout=300, check=False)
    lines = [x for x in (proc.stdout + proc.stderr).splitlines() if x.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(ERROR), proc.stdout + proc.stderr
    assert "holds a control character" in lines[0] and "embedded null byte" not in lines[0]
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------------------------
# EXIF orientation: read as displayed

def pillow():
    return pytest.importorskip("PIL.Image", reason="writing EXIF needs Pillow: pip install 'flamerecon[figures]'")


def with_orientation(path: Path, image: np.ndarray, orientation: int) -> Path:
    """``image`` (H, W, 3) uint8 RGB written to ``path`` with that EXIF orientation."""
    picture = pillow().fromarray(image)
    exif = picture.getexif()
    exif[0x0112] = orientation
    extra = {"quality": 100, "subsampling": 0} if path.suffix == ".jpg" else {"lossless": True} \
        if path.suffix == ".webp" else {}
    picture.save(path, exif=exif, **extra)
    return path


STORED = np.random.default_rng(3).integers(0, 256, size=(12, 20, 3), dtype=np.uint8)
FORMATS = [".jpg", ".png", ".webp", ".tif"]


@pytest.mark.parametrize("ext", FORMATS)
@pytest.mark.parametrize("orientation", range(1, 9))
def test_an_image_is_read_as_its_exif_orientation_displays_it(orientation, ext, tmp_path):
    ImageOps = pytest.importorskip("PIL.ImageOps")

    path = with_orientation(tmp_path / f"frame{ext}", STORED, orientation)
    assert exif_orientation(path) == orientation
    shown = np.asarray(ImageOps.exif_transpose(pillow().open(path)).convert("RGB"))  # as Pillow (a viewer) shows it
    assert shown.shape[:2] == displayed(STORED, orientation).shape[:2]
    try:
        image = read_image(path)
    except SceneError as err:  # this OpenCV cannot read a turned TIFF: said, not decoded wrong
        assert ext == ".tif" and orientation >= 5, err
        assert re.search(rf"frame\.tif: a TIFF whose orientation tag says {orientation} \({TURNS[orientation]}\), "
                         r"which this OpenCV .* cannot read; save the frame upright", str(err))
        return
    got = np.round(image * 255).astype(int)
    assert got.shape == shown.shape
    assert np.abs(got - shown.astype(int)).mean() < (3 if ext == ".jpg" else 0.5)  # JPEG: its compression


def test_a_calibration_of_the_stored_size_is_refused_naming_the_orientation(tmp_path):
    """A phone's portrait frames (stored 20x12, EXIF orientation 6: displayed 12x20) with a
    calibration that says 20x12: refused, the orientation named, not 'the image is 12x20'."""
    images = random_images(len(NAMES), 3)
    root = opencv_capture(tmp_path, image_ext=".jpg", images=images)
    for name, image in zip(NAMES, images):
        (root / name).mkdir()
        with_orientation(root / name / "000000.jpg", image, 6)
    with pytest.raises(SceneError, match=r"000000\.jpg: image is 32x40 \(WxH\) as displayed, its EXIF orientation 6 "
                                         r"\(rotated 90 degrees clockwise\) applied, but .*calibration\.json: "
                                         r"cameras\[0\]\.width/height says 40x32, the size as stored"):
        load_scene({"name": "opencv", "root": str(root)})
    data = json.loads((root / "calibration.json").read_text())  # calibrated on the displayed images: it loads
    for cam in data["cameras"]:
        cam["width"], cam["height"] = HEIGHT, WIDTH
        cam["K"] = [[45.0, 0, HEIGHT / 2 + 0.5], [0, 45.0, WIDTH / 2 + 0.5], [0, 0, 1.0]]
    (root / "calibration.json").write_text(json.dumps(data))
    scene = load_scene({"name": "opencv", "root": str(root)})
    assert scene.image_size == (WIDTH, HEIGHT)  # (H, W) as displayed
