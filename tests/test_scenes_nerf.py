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
    (lambda d: d.__setitem__("fl_x", -3), r"frames\[0\]\.fl_x: got -3; it must be > 0"),
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
