"""Pictures on tiny volumes: values, orientation and files read back with their own readers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from flamerecon.cameras import camera_centers, project_points
from flamerecon.figures import (
    framing_distance,
    montage,
    orbit_cameras,
    overlay_mask,
    project_along,
    slices_figure,
    to_rgb8,
    top_view,
    write_gif,
    write_mp4,
    write_png,
)

LO = np.array([0.0, 0.0, 0.0])
HI = np.array([2.0, 4.0, 1.0])  # nx, ny, nz = 4, 8, 2 -> voxel size 0.5 in every direction


def _blob() -> np.ndarray:
    """(1, nz=2, ny=8, nx=4) with one bright voxel at (k, j, i) = (1, 6, 3)."""
    vol = np.zeros((1, 2, 8, 4), dtype=np.float32)
    vol[0, 1, 6, 3] = 2.0
    vol[0, 0, 0, 0] = 1.0
    return vol


def test_project_along_is_line_integral_in_world_units():
    vol = _blob()
    along_y = project_along(vol, LO, HI, "y")
    assert along_y.shape == (1, 2, 4)  # (C, nz, nx)
    assert along_y[0, 1, 3] == pytest.approx(2.0 * 0.5)
    assert along_y.sum() == pytest.approx(vol.sum() * 0.5)
    assert project_along(vol, LO, HI, "x").shape == (1, 2, 8)
    assert project_along(torch.from_numpy(vol), LO, HI, "z")[0, 6, 3] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="axis"):
        project_along(vol, LO, HI, "up")


def test_top_view_and_to_rgb8():
    img = top_view(_blob(), LO, HI, up="y")
    assert img.shape == (2, 4, 3) and img.dtype == np.uint8
    brightest = np.unravel_index(img.sum(axis=2).argmax(), img.shape[:2])
    assert brightest == (1, 3)  # row = z index, column = x index
    rgb = to_rgb8(np.stack([np.full((2, 2), v) for v in (1.0, 0.5, 0.0)]))
    assert rgb[0, 0].tolist() == [255, 128, 0]
    # an empty volume maps to the colormap's bottom colour everywhere (no division by zero)
    bottom = cv2.applyColorMap(np.zeros((1, 1), np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]
    assert (to_rgb8(np.zeros((1, 3, 3))) == bottom).all()


def test_slices_figure_png(tmp_path):
    pytest.importorskip("matplotlib")
    path = slices_figure(tmp_path / "slices.png", _blob(), LO, HI, index=(3, 6, 1))
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] > img.shape[0] > 100
    with pytest.raises(ValueError, match="outside"):
        slices_figure(tmp_path / "bad.png", _blob(), LO, HI, index=(4, 0, 0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slices.png"]


def test_overlay_mask_tints_inside_and_outlines():
    image = np.zeros((3, 20, 30), dtype=np.float32)
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:15, 10:20] = True
    out = overlay_mask(image, mask, color=(0, 255, 0), alpha=0.5)
    assert out.shape == (20, 30, 3)
    assert out[10, 15].tolist() == [0, 128, 0]  # inside: half-tinted
    assert out[5, 15].tolist() == [0, 255, 0]  # border: full outline
    assert out[2, 2].tolist() == [0, 0, 0]  # outside: untouched
    with pytest.raises(ValueError, match="mask"):
        overlay_mask(image, mask[:10])


def test_montage_layout():
    tiles = [np.full((4, 5, 3), 10 * n, dtype=np.uint8) for n in range(5)]
    sheet = montage(tiles, columns=3)
    assert sheet.shape == (8, 15, 3)
    assert sheet[5, 6, 0] == 40 and sheet[5, 12, 0] == 0  # tile 4 at row 1 col 1; empty slot


def test_png_mp4_gif_read_back(tmp_path):
    frames = [np.full((32, 48, 3), (20 * t, 100, 200 - 20 * t), dtype=np.uint8) for t in range(6)]
    write_png(tmp_path / "f.png", frames[2])
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "f.png"))[..., ::-1], frames[2])

    write_mp4(tmp_path / "t.mp4", frames, fps=10)
    capture = cv2.VideoCapture(str(tmp_path / "t.mp4"))
    assert capture.get(cv2.CAP_PROP_FRAME_COUNT) == 6
    assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (48, 32)
    ok, first = capture.read()
    capture.release()
    assert ok and np.abs(first[..., ::-1].astype(int) - frames[0]).mean() < 8  # lossy codec

    from PIL import Image

    write_gif(tmp_path / "t.gif", frames, fps=10)
    with Image.open(tmp_path / "t.gif") as gif:
        assert gif.n_frames == 6 and gif.size == (48, 32)
        gif.seek(3)
        assert np.abs(np.asarray(gif.convert("RGB")).astype(int) - frames[3]).max() <= 8
    with pytest.raises(ValueError, match="frame 1"):
        write_gif(tmp_path / "bad.gif", [frames[0], frames[1][:8]])


def test_orbit_cameras_look_at_target_with_up_upwards():
    target = torch.tensor([0.0, 1.0, 0.0])
    cams = orbit_cameras([0.0, 90.0, 180.0], elevation_deg=30.0, distance=2.0, target=target,
                         width=64, height=48, fov_deg=40.0)
    centres = camera_centers(cams)
    np.testing.assert_allclose(torch.linalg.norm(centres - target, dim=1), 2.0, rtol=1e-5)
    np.testing.assert_allclose(centres[:, 1], 1.0 + 2.0 * np.sin(np.radians(30)), rtol=1e-5)
    np.testing.assert_allclose(centres[0], [0.0, 2.0, np.sqrt(3)], atol=1e-5)  # azimuth 0: +z
    np.testing.assert_allclose(centres[1], [np.sqrt(3), 2.0, 0.0], atol=1e-5)  # 90: +x
    uv, depth = project_points(cams, torch.stack([target, target + torch.tensor([0, 0.2, 0])]))
    np.testing.assert_allclose(uv[:, 0], [[32.0, 24.0]] * 3, atol=1e-4)  # target at the centre
    assert (uv[:, 1, 1] < 24.0).all()  # a point above the target appears above the centre
    assert (depth > 0).all()


def test_framing_distance_sees_the_whole_box():
    lo, hi = np.array([-1.0, 0.0, -1.0]), np.array([1.0, 3.0, 1.0])
    dist = framing_distance(lo, hi, fov_deg=40.0)
    cams = orbit_cameras(np.arange(0, 360, 45), 20.0, dist, (lo + hi) / 2, 80, 80, 40.0)
    corners = torch.tensor([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=torch.float32)
    uv, _ = project_points(cams, corners)
    assert (uv >= 0).all() and (uv <= 80).all()
