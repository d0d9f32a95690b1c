"""PINF/HyFluid info.json loader: round trip of a synthetic capture, the real ScalarFlow capture,
and one-line errors for bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flamerecon.geometry.cameras import K_of, opencv_w2c_to_opengl_c2w, project_points
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.silhouettes import estimate_bbox, silhouettes
from flamerecon.scenes import SceneError
from flamerecon.scenes.pinf import load_pinf
from tests.helpers.views import (
    BOX,
    HEIGHT,
    NAMES,
    WIDTH,
    as_float,
    centred_K,
    random_images,
    ring_cameras,
    write_png,
    write_video,
)

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "scalarflow_real"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/scalarflow_real")
FRAME = 7
F = 45.0


def write_capture(folder: Path, images: np.ndarray, videos: bool = False) -> dict:
    """Write a PINF capture of the synthetic views; the last camera is the test view."""
    w2c = ring_cameras(len(NAMES))
    angle = 2 * math.atan(0.5 * WIDTH / F)
    entries = []
    for i, name in enumerate(NAMES):
        if videos:
            frames = np.zeros((FRAME + 2, HEIGHT, WIDTH), np.uint8)
            frames[FRAME] = images[i, :, :, 0]
            if not write_video(folder / f"{name}.avi", frames, "FFV1"):
                pytest.skip("this OpenCV build cannot write FFV1 .avi videos")
        else:
            write_png(folder / name / f"{FRAME:06d}.png", images[i])
        entries.append(
            {
                "file_name": f"{name}.mp4",
                "frame_num": FRAME + 2,
                "camera_angle_x": angle,
                "camera_hw": [HEIGHT, WIDTH],
                "transform_matrix": opencv_w2c_to_opengl_c2w(w2c[i]).double().tolist(),
            }
        )
    lo, hi = np.array(BOX[0]), np.array(BOX[1])
    placed = np.eye(4)
    placed[:3, 3] = lo
    info = {
        "train_videos": entries[:-1],
        "test_videos": entries[-1:],
        "voxel_matrix": placed[:, [2, 1, 0, 3]].tolist(),  # PINF swaps columns 0 and 2 on load
        "voxel_scale": (hi - lo).tolist(),
        "near": 2.0,
        "far": 4.0,
    }
    (folder / "info.json").write_text(json.dumps(info))
    return info


@pytest.mark.parametrize("videos", [False, True], ids=["frame folders", "videos"])
def test_round_trip(tmp_path, videos):
    images = random_images(len(NAMES))
    write_capture(tmp_path, images, videos=videos)
    scene = load_pinf({"root": str(tmp_path), "frame": FRAME})
    order = [0, 1, 2, 3]  # train entries first, then the test entry: here the same order
    assert scene.views == NAMES
    assert scene.default_holdout == [NAMES[-1]]
    torch.testing.assert_close(scene.images, as_float(images[order]), atol=1e-6, rtol=0)
    K = torch.from_numpy(centred_K(F)).float().expand(4, 3, 3)
    torch.testing.assert_close(K_of(scene.cameras), K, atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(scene.cameras.extrinsics, ring_cameras(4).float(), atol=1e-5, rtol=0)
    np.testing.assert_allclose(scene.bbox_min, BOX[0], atol=1e-6)
    np.testing.assert_allclose(scene.bbox_max, BOX[1], atol=1e-6)


def test_a_response_keeps_the_recorded_images_for_scoring(tmp_path):
    images = random_images(len(NAMES))
    write_capture(tmp_path, images)
    plain = load_pinf({"root": str(tmp_path), "frame": FRAME})
    assert plain.response is None and plain.recorded_images is None
    scene = load_pinf({"root": str(tmp_path), "frame": FRAME, "gamma": 2.2, "black_level": 0.1})
    assert scene.response == {"gamma": 2.2, "black_level": 0.1}
    torch.testing.assert_close(scene.recorded_view(0), plain.images[0])
    torch.testing.assert_close(scene.images, ((plain.images - 0.1) / 0.9).clamp_min(0) ** 2.2)


def test_downscale_averages_pixels_and_scales_intrinsics(tmp_path):
    images = random_images(len(NAMES))
    write_capture(tmp_path, images)
    full = load_pinf({"root": str(tmp_path), "frame": FRAME})
    half = load_pinf({"root": str(tmp_path), "frame": FRAME, "downscale": 2})
    assert half.image_size == (HEIGHT // 2, WIDTH // 2)
    expected = cv2.resize(
        images[0, :, :, 0].astype(np.float32) / 255,
        (WIDTH // 2, HEIGHT // 2),
        interpolation=cv2.INTER_AREA,
    )
    np.testing.assert_allclose(half.images[0, 0].numpy(), expected, atol=1e-6)
    # the same world point lands at half the continuous pixel coordinate
    point = torch.tensor([[0.1, 0.2, -0.05]])
    uv_full, _ = project_points(full.cameras, point)
    uv_half, _ = project_points(half.cameras, point)
    torch.testing.assert_close(uv_half, uv_full / 2, atol=1e-4, rtol=0)


def test_config_box_overrides_the_file(tmp_path):
    write_capture(tmp_path, random_images(len(NAMES)))
    scene = load_pinf({"root": str(tmp_path), "frame": FRAME, "bbox": [[0, 0, 0], [1, 2, 3]]})
    assert scene.bbox_min == (0, 0, 0) and scene.bbox_max == (1, 2, 3)


def _edit(folder: Path, change) -> None:
    path = folder / "info.json"
    info = json.loads(path.read_text())
    change(info)
    path.write_text(json.dumps(info))


def _set(info, field, value):
    info["train_videos"][1][field] = value


BAD_INFO = [
    (
        lambda i: i["train_videos"][1].pop("camera_angle_x"),
        r"train_videos\[1\]\.camera_angle_x: missing",
    ),
    (
        lambda i: _set(i, "camera_angle_x", -0.4),
        r"train_videos\[1\]\.camera_angle_x: got -0\.4; it must be a number > 0 and < 3\.14159",
    ),
    (
        lambda i: _set(i, "transform_matrix", [[1, 0, 0], [0, 1, 0]]),
        r"train_videos\[1\]\.transform_matrix: expected shape \(4, 4\)",
    ),
    (
        lambda i: i["train_videos"][1]["transform_matrix"][0].__setitem__(0, 3.0),
        r"train_videos\[1\]\.transform_matrix: rotation is not orthonormal",
    ),
    (
        lambda i: i["train_videos"][1]["transform_matrix"][1].__setitem__(3, float("nan")),
        r"train_videos\[1\]\.transform_matrix: holds NaN or Inf",
    ),
    (
        lambda i: _set(i, "camera_hw", [HEIGHT, WIDTH + 2]),
        r"cam01/000007\.png: image is 40x32 .*camera_hw",
    ),
    (lambda i: _set(i, "file_name", "nowhere.mp4"), r"camera 'nowhere.mp4': found neither"),
    (lambda i: _set(i, "frame_num", 3), r"train_videos\[1\]\.frame_num: frame 7 is outside"),
    (lambda i: i.__setitem__("voxel_scale", [1, -1, 1]), r"voxel_scale: must be positive"),
    (lambda i: i.pop("train_videos") and i.pop("test_videos"), r"train_videos: missing or empty"),
]


@pytest.mark.parametrize("change, message", BAD_INFO)
def test_bad_info_names_file_and_field(tmp_path, change, message):
    write_capture(tmp_path, random_images(len(NAMES)))
    _edit(tmp_path, change)
    with pytest.raises(SceneError, match=message) as err:
        load_pinf({"root": str(tmp_path), "frame": FRAME})
    assert "\n" not in str(err.value)
    assert "info.json" in str(err.value) or str(tmp_path) in str(err.value)


def test_bad_images_and_frames(tmp_path):
    write_capture(tmp_path, random_images(len(NAMES)))
    with pytest.raises(SceneError, match=r"cam00: frame 3: no file 000003\.png there"):
        load_pinf({"root": str(tmp_path), "frame": 3})
    (tmp_path / "cam02" / f"{FRAME:06d}.png").write_bytes(b"not a png at all")
    with pytest.raises(SceneError, match=r"cam02/000007\.png: cannot decode the image"):
        load_pinf({"root": str(tmp_path), "frame": FRAME})
    with pytest.raises(SceneError, match=r"scene\.root: '.*missing' does not exist"):
        load_pinf({"root": str(tmp_path / "missing")})
    (tmp_path / "cam02" / f"{FRAME:06d}.png").unlink()
    write_png(tmp_path / "cam02" / f"{FRAME:06d}.png", random_images(1)[0])
    with pytest.raises(SceneError, match=r"config: scene\.downscale: got 0; it must be an integer >= 1"):
        load_pinf({"root": str(tmp_path), "frame": FRAME, "downscale": 0})
    (tmp_path / "info.json").write_text("{not json")
    with pytest.raises(SceneError, match=r"info\.json: not valid JSON"):
        load_pinf({"root": str(tmp_path)})


real = pytest.mark.skipif(not (REAL / "info.json").is_file(), reason=f"real capture absent: {REAL}")


@real
def test_real_capture_loads_with_its_conventions():
    scene = load_pinf({"root": str(REAL), "frame": 59, "downscale": 4})
    assert sorted(scene.views) == ["train00", "train01", "train02", "train03", "train04"]
    assert scene.default_holdout == ["train02"]
    assert scene.images.shape == (5, 1, 480, 270)
    assert 0.5 < float(scene.images.max()) <= 1.0 and float(scene.images.min()) == 0.0
    # f = 0.5 W / tan(0.5 camera_angle_x) at full width 1080, quartered; the README's box
    # x [0.082, 0.573], y [-0.045, 0.692], z [-0.496, -0.005]
    info = json.loads((REAL / "info.json").read_text())
    entries = {Path(e["file_name"]).stem: e for e in info["train_videos"] + info["test_videos"]}
    angles = torch.tensor([entries[v]["camera_angle_x"] for v in scene.views], dtype=torch.float64)
    expected = (0.5 * 1080 / torch.tan(0.5 * angles)) / 4
    torch.testing.assert_close(K_of(scene.cameras)[:, 0, 0].double(), expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(
        K_of(scene.cameras)[:, 0, 2], torch.full((5,), (540 + 0.5) / 4), rtol=0, atol=1e-4
    )
    np.testing.assert_allclose(scene.bbox_min, (0.082, -0.045, -0.496), atol=1e-3)
    np.testing.assert_allclose(scene.bbox_max, (0.573, 0.692, -0.005), atol=1e-3)


@real
@pytest.mark.parametrize("frame", [20, 59])
def test_real_box_and_silhouettes_agree(frame):
    scene = load_pinf({"root": str(REAL), "frame": frame, "downscale": 4})
    masks = silhouettes(scene.images, method="threshold", threshold=0.02)
    H, W = scene.image_size
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    centre = (grid.lo() + grid.hi()) / 2
    uv, depth = project_points(scene.cameras, torch.cat([grid.corners(), centre[None]]))
    assert bool((depth > 0).all())
    hull_lo, hull_hi = estimate_bbox(scene.cameras, masks)
    hull_centre = torch.tensor([(a + b) / 2 for a, b in zip(hull_lo, hull_hi)]).float()
    uv_hull, _ = project_points(scene.cameras, hull_centre[None])
    for b in range(scene.num_views):
        u, v = uv[b, -1]
        assert 0 <= u < W and 0 <= v < H, f"box centre outside view {scene.views[b]}"
        if frame == 59:  # the plume fills the box's middle by then
            assert bool(masks[b, int(v), int(u)]), f"box centre outside silhouette {scene.views[b]}"
        # every silhouette pixel lies inside the projected box
        corners = np.round(cv2.convexHull(uv[b, :8].numpy().astype(np.float32))).astype(np.int32)
        footprint = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(footprint, corners, 1)
        silhouette = masks[b].numpy()
        assert (silhouette & footprint.astype(bool)).sum() >= 0.999 * silhouette.sum()
        # the silhouette cones meet where every view sees smoke
        uh, vh = uv_hull[b, 0].long()
        assert bool(masks[b, vh, uh]), f"hull centre outside silhouette {scene.views[b]}"
    for a, b_, lo, hi in zip(hull_lo, hull_hi, scene.bbox_min, scene.bbox_max):
        assert lo - 0.05 < a < b_ < hi + 0.05


def _matrix_item(row, col, value):
    return lambda i: i["train_videos"][1]["transform_matrix"][row].__setitem__(col, value)


#: a damaged value of info.json -> the message naming file and field
DAMAGED_VALUES = {
    "a string in camera_hw": (lambda i: _set(i, "camera_hw", ["32", 40]),
                              r"train_videos\[1\]\.camera_hw \(item 0\): got the string '32'; write a number"),
    "a non-integer image height": (lambda i: _set(i, "camera_hw", [32.5, 40]),
                                   (r"train_videos\[1\]\.camera_hw: got \[32\.5, 40\.0\]; it must be \[H, W\] of "
                                   r"integers >= 1")),
    "a zero image height": (lambda i: _set(i, "camera_hw", [0, 40]),
                            r"train_videos\[1\]\.camera_hw: got \[0\.0, 40\.0\]; it must be \[H, W\] of integers"),
    "camera_hw as one string": (lambda i: _set(i, "camera_hw", "32x40"),
                                r"train_videos\[1\]\.camera_hw: got '32x40'; it must be a number"),
    "camera_hw of three": (lambda i: _set(i, "camera_hw", [32, 40, 3]),
                           r"train_videos\[1\]\.camera_hw: expected shape \(2,\), got \(3,\)"),
    "the field of view as a string": (lambda i: _set(i, "camera_angle_x", "0.8"),
                                      r"train_videos\[1\]\.camera_angle_x: got the string '0\.8'; write a number"),
    "a field of view past pi": (lambda i: _set(i, "camera_angle_x", 4.0),
                                r"train_videos\[1\]\.camera_angle_x: got 4\.0; it must be a number > 0 and < 3\.14159"),
    "a null field of view": (lambda i: _set(i, "camera_angle_x", None),
                             r"train_videos\[1\]\.camera_angle_x: missing; it must be a number > 0 and < 3\.14159"),
    "frame_num as a string": (lambda i: _set(i, "frame_num", "9"),
                              r"train_videos\[1\]\.frame_num: got the string '9'; write a number"),
    "a non-integer frame_num": (lambda i: _set(i, "frame_num", 8.5),
                                r"train_videos\[1\]\.frame_num: got 8\.5; it must be an integer >= 1"),
    "an empty list as file name": (lambda i: _set(i, "file_name", []),
                                   r"train_videos\[1\]\.file_name: got \[\]; it must be a non-empty string"),
    "a string in the voxel scale": (lambda i: i.__setitem__("voxel_scale", ["1", 1, 1]),
                                    r"info\.json: voxel_scale \(item 0\): got the string '1'"),
    "a string in the voxel matrix": (lambda i: i["voxel_matrix"][0].__setitem__(3, "0.5"),
                                     r"info\.json: voxel_matrix \(item 3\): got the string '0\.5'"),
    "near as a string": (lambda i: i.__setitem__("near", "2.0"), r"info\.json: near: got the string '2\.0'"),
    "a bool in a transform": (_matrix_item(0, 0, True),
                              r"train_videos\[1\]\.transform_matrix \(item 0\): got True; it must be a number"),
    "a transform of rows": (lambda i: _set(i, "transform_matrix", "identity"),
                            r"train_videos\[1\]\.transform_matrix: got 'identity'; it must be a number"),
}


@pytest.mark.parametrize("case", list(DAMAGED_VALUES))
def test_a_damaged_value_names_file_and_field(tmp_path, case):
    change, message = DAMAGED_VALUES[case]
    write_capture(tmp_path, random_images(len(NAMES)))
    _edit(tmp_path, change)
    with pytest.raises(SceneError, match=message) as err:
        load_pinf({"root": str(tmp_path), "frame": FRAME})
    assert str(err.value).startswith(f"{tmp_path / 'info.json'}: ") and "\n" not in str(err.value)


@pytest.mark.parametrize("key, value, message", [
    ("frame", 7.5, r"config: scene\.frame: got 7\.5; it must be an integer >= 0"),
    ("frame", "7", r"config: scene\.frame: got the string '7'"),
    ("downscale", True, r"config: scene\.downscale: got True; it must be an integer >= 1"),
])
def test_a_bad_config_value_names_its_field(tmp_path, key, value, message):
    write_capture(tmp_path, random_images(len(NAMES)))
    with pytest.raises(SceneError, match=message):
        load_pinf({"root": str(tmp_path), "frame": FRAME, key: value})
