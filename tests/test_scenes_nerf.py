"""NeRF transforms.json loader: round trip of a synthetic capture, distortion, bad input."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from flamerecon.geometry.cameras import K_of, opencv_w2c_to_opengl_c2w
from flamerecon.scenes import SceneError
from flamerecon.scenes.nerf import load_nerf
from tests.helpers.views import (
    HEIGHT,
    NAMES,
    WIDTH,
    as_float,
    random_images,
    ring_cameras,
    write_png,
)

FL_X, FL_Y, CX, CY = 47.0, 45.5, 21.25, 15.75
BOX = [[-0.5, -0.4, -0.6], [0.6, 0.5, 0.4]]


def write_transforms(folder, images, **top) -> dict:
    w2c = ring_cameras(len(NAMES))
    frames = []
    for i, name in enumerate(NAMES):
        write_png(folder / "images" / f"{name}.png", images[i])
        c2w = opencv_w2c_to_opengl_c2w(w2c[i]).double().tolist()
        frames.append({"file_path": f"./images/{name}", "transform_matrix": c2w})
    data = {"w": WIDTH, "h": HEIGHT, "bbox": BOX, "frames": frames, **top}
    (folder / "transforms.json").write_text(json.dumps(data))
    return data


def test_round_trip_with_explicit_intrinsics(tmp_path):
    images = random_images(len(NAMES), channels=3)
    write_transforms(tmp_path, images, fl_x=FL_X, fl_y=FL_Y, cx=CX, cy=CY)
    scene = load_nerf({"root": str(tmp_path), "holdout": [NAMES[2]]})
    assert scene.views == NAMES and scene.default_holdout == [NAMES[2]]
    torch.testing.assert_close(scene.images, as_float(images), atol=1e-6, rtol=0)
    K = torch.tensor([[FL_X, 0, CX], [0, FL_Y, CY], [0, 0, 1]]).expand(4, 3, 3)
    torch.testing.assert_close(K_of(scene.cameras), K, atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.cameras.extrinsics, ring_cameras(4).float(), atol=1e-5, rtol=0)
    assert [list(scene.bbox_min), list(scene.bbox_max)] == BOX


def test_camera_angle_gives_centred_intrinsics(tmp_path):
    images = random_images(len(NAMES), channels=1)
    write_transforms(tmp_path, images, camera_angle_x=2 * math.atan(0.5 * WIDTH / FL_X))
    scene = load_nerf({"root": str(tmp_path), "downscale": 2})
    K = torch.tensor([[FL_X / 2, 0, WIDTH / 4], [0, FL_X / 2, HEIGHT / 4], [0, 0, 1]])
    torch.testing.assert_close(K_of(scene.cameras), K.expand(4, 3, 3), atol=1e-4, rtol=0)
    assert scene.images.shape == (4, 1, HEIGHT // 2, WIDTH // 2)


def test_distortion_is_removed_like_opencv(tmp_path):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    checker = (((x // 4 + y // 4) % 2) * 200 + 30).astype(np.uint8)
    images = np.repeat(checker[None, :, :, None], len(NAMES), axis=0)
    k = {"k1": -0.2, "k2": 0.05, "p1": 0.002, "p2": -0.001}
    write_transforms(tmp_path, images, fl_x=FL_X, fl_y=FL_Y, cx=CX, cy=CY, **k)
    scene = load_nerf({"root": str(tmp_path)})
    K_opencv = np.array([[FL_X, 0, CX - 0.5], [0, FL_Y, CY - 0.5], [0, 0, 1]])
    dist = np.array([k["k1"], k["k2"], k["p1"], k["p2"], 0.0])
    expected = cv2.undistort(checker.astype(np.float32) / 255, K_opencv, dist)
    np.testing.assert_allclose(scene.images[0, 0].numpy(), expected, atol=1e-6)


BAD = [
    (lambda d: d["frames"][1].pop("file_path"), r"frames\[1\]\.file_path: missing"),
    (
        lambda d: d["frames"][1].__setitem__("file_path", "./images/none"),
        r"images/none: image file not found",
    ),
    (lambda d: d.pop("fl_x"), r"frames\[0\]\.camera_angle_x: missing \(and no fl_x\)"),
    (lambda d: d.__setitem__("fl_x", -3), r"frames\[0\]\.fl_x: got -3; it must be a number > 0"),
    (
        lambda d: d["frames"][1]["transform_matrix"][2].__setitem__(1, 5.0),
        r"frames\[1\]\.transform_matrix: rotation",
    ),
    (
        lambda d: d.__setitem__("w", WIDTH * 2),
        r"cam00\.png: image is 40x32 .*frames\[0\]\.w/h says 80x32",
    ),
    (
        lambda d: d.__setitem__("bbox", [[0, 0, 0], [1, -1, 1]]),
        r"transforms\.json: bbox: min must be below max",
    ),
    (lambda d: d.__setitem__("frames", []), r"transforms\.json: frames: missing or empty"),
]


@pytest.mark.parametrize("change, message", BAD, ids=[b[1][:40] for b in BAD])
def test_bad_transforms_name_file_and_field(tmp_path, change, message):
    data = write_transforms(tmp_path, random_images(len(NAMES)), fl_x=FL_X, cx=CX, cy=CY)
    change(data)
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneError, match=message) as err:
        load_nerf({"root": str(tmp_path)})
    assert "\n" not in str(err.value)


def _top(key, value):
    return lambda d: d.__setitem__(key, value)


def _frame(i, key, value):
    return lambda d: d["frames"][i].__setitem__(key, value)


def _matrix_item(i, row, col, value):
    return lambda d: d["frames"][i]["transform_matrix"][row].__setitem__(col, value)


#: a damaged value of transforms.json -> the message naming file and field
DAMAGED_VALUES = {
    "w as a string": (_top("w", "40"), r"frames\[0\]\.w: got the string '40'; write a number \(an integer >= 1\)"),
    "non-integer h": (_top("h", 32.5), r"frames\[0\]\.h: got 32\.5; it must be an integer >= 1"),
    "h as a bool": (_top("h", True), r"frames\[0\]\.h: got True; it must be an integer >= 1"),
    "zero w in one frame": (_frame(2, "w", 0), r"frames\[2\]\.w: got 0; it must be an integer >= 1"),
    "fl_x as a string": (_top("fl_x", "47"), r"frames\[0\]\.fl_x: got the string '47'; write a number"),
    "fl_x as a list": (_top("fl_x", [47]), r"frames\[0\]\.fl_x: got \[47\]; it must be a number > 0"),
    "fl_x as a word in one frame": (_frame(2, "fl_x", "x"), r"frames\[2\]\.fl_x: got 'x'; it must be a number > 0"),
    "cx null": (_top("cx", None), r"frames\[0\]\.cx: missing; it must be a finite number"),
    "cy as a string": (_top("cy", "15.75"), r"frames\[0\]\.cy: got the string '15\.75'"),
    "infinite cy": (_top("cy", float("inf")), r"frames\[0\]\.cy: got inf; it must be a finite number"),
    "k1 as a string": (_top("k1", "0.1"), r"frames\[0\]\.k1: got the string '0\.1'"),
    "a field of view past pi": (lambda d: (d.pop("fl_x"), d.__setitem__("camera_angle_x", 3.5)),
                                r"frames\[0\]\.camera_angle_x: got 3\.5; it must be a number > 0 and < 3\.14159"),
    "camera_angle_y as a string": (lambda d: (d.pop("fl_x"), d.update(camera_angle_x=0.8, camera_angle_y="0.8")),
                                   r"frames\[0\]\.camera_angle_y: got the string '0\.8'"),
    "a string in a transform": (_matrix_item(1, 1, 1, "1"),
                                r"frames\[1\]\.transform_matrix \(item 5\): got the string '1'; write a number"),
    "a ragged transform": (lambda d: d["frames"][1]["transform_matrix"][0].pop(),
                           r"frames\[1\]\.transform_matrix: got .*; it must be an array of numbers with rows of one"),
    "a string in the box": (_top("bbox", [["-0.5", -0.4, -0.6], [0.6, 0.5, 0.4]]),
                            r"transforms\.json: bbox \(item 0\): got the string '-0\.5'"),
    "a list as a file path": (_frame(1, "file_path", ["./images/cam01"]),
                              r"frames\[1\]\.file_path: got \['\./images/cam01'\]; it must be a non-empty string"),
}


@pytest.mark.parametrize("case", list(DAMAGED_VALUES))
def test_a_damaged_value_names_file_and_field(tmp_path, case):
    change, message = DAMAGED_VALUES[case]
    data = write_transforms(tmp_path, random_images(len(NAMES)), fl_x=FL_X, cx=CX, cy=CY)
    change(data)
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneError, match=message) as err:
        load_nerf({"root": str(tmp_path)})
    assert str(err.value).startswith(f"{tmp_path / 'transforms.json'}: ") and "\n" not in str(err.value)


@pytest.mark.parametrize("key, value, message", [
    ("frame", "0", r"config: scene\.frame: got the string '0'; write a number \(an integer >= 0\)"),
    ("frame", 0.5, r"config: scene\.frame: got 0\.5; it must be an integer >= 0"),
    ("downscale", 1.5, r"config: scene\.downscale: got 1\.5; it must be an integer >= 1"),
    ("black_level", "0.1", r"config: scene\.black_level: got the string '0\.1'"),
    ("holdout", {"cam01": 1}, r"config: scene\.holdout: got \{'cam01': 1\}; it must be a list of names"),
])
def test_a_bad_config_value_names_its_field(tmp_path, key, value, message):
    write_transforms(tmp_path, random_images(len(NAMES)), fl_x=FL_X, cx=CX, cy=CY)
    with pytest.raises(SceneError, match=message):
        load_nerf({"root": str(tmp_path), key: value})


def test_a_holdout_of_one_name_is_one_view(tmp_path):
    write_transforms(tmp_path, random_images(len(NAMES)), fl_x=FL_X, cx=CX, cy=CY)
    assert load_nerf({"root": str(tmp_path), "holdout": NAMES[2]}).default_holdout == [NAMES[2]]
