"""Reading a camera's frames from a video or a folder of numbered images."""

from __future__ import annotations

import numpy as np
import pytest

from flamerecon.scenes import SceneError
from flamerecon.scenes.frames import (
    frame_source,
    read_camera_frame,
    read_image,
    read_video_frame,
    video_length,
)
from tests.helpers.views import write_png, write_video

T, H, W = 5, 24, 32


def frames() -> np.ndarray:
    """Five gray frames (T, H, W), each a distinct smooth ramp (survives lossy codecs)."""
    y, x = np.mgrid[0:H, 0:W]
    return np.stack([((x * 4 + y * 2 + 40 * t) % 200 + 20).astype(np.uint8) for t in range(T)])


@pytest.mark.parametrize(
    "name, fourcc, tolerance",
    [("cam.avi", "FFV1", 0.0), ("cam.mp4", "mp4v", 12 / 255)],
    ids=["lossless avi", "mp4"],
)
def test_video_read_frame_by_frame(tmp_path, name, fourcc, tolerance):
    clip = frames()
    if not write_video(tmp_path / name, clip, fourcc):
        pytest.skip(f"this OpenCV build cannot write {fourcc} {name}")
    assert video_length(tmp_path / name) == T
    for t in range(T):
        image = read_video_frame(tmp_path / name, t)
        assert image.shape == (H, W, 3) and image.dtype == np.float32
        gray = image.mean(axis=2)
        assert np.abs(gray - clip[t] / 255).mean() <= max(tolerance, 1e-6)
        others = [np.abs(gray - clip[s] / 255).mean() for s in range(T) if s != t]
        assert min(others) > 5 * max(tolerance / 4, 1e-3)  # it is this frame, not a neighbour
    with pytest.raises(
        SceneError, match=rf"{name}: frame {T}: beyond the end of the video \({T} frames\)"
    ):
        read_video_frame(tmp_path / name, T)


def test_camera_frames_from_video_or_folder(tmp_path):
    clip = frames()
    if not write_video(tmp_path / "left.avi", clip, "FFV1"):
        pytest.skip("this OpenCV build cannot write FFV1 .avi videos")
    write_png(tmp_path / "right" / "000003.png", clip[3][:, :, None])
    image, source = read_camera_frame(tmp_path, "left.mp4", 3)  # PINF names videos .mp4
    assert source == tmp_path / "left.avi"
    np.testing.assert_allclose(image[:, :, 0], clip[3] / 255, atol=1e-6)
    image, source = read_camera_frame(tmp_path, "right.mp4", 3)
    assert source == tmp_path / "right" / "000003.png"
    assert image.shape == (H, W, 1)
    np.testing.assert_allclose(image[:, :, 0], clip[3] / 255, atol=1e-6)
    with pytest.raises(
        SceneError, match=r"right: frame 4: no file 000004\.png there \(it has frames 000003\)"
    ):
        read_camera_frame(tmp_path, "right", 4)
    with pytest.raises(SceneError, match=r"camera 'middle': found neither a video middle\.mp4"):
        frame_source(tmp_path, "middle")


def test_undecodable_files_are_named(tmp_path):
    (tmp_path / "broken.mp4").write_bytes(b"\x00\x01garbage" * 100)
    with pytest.raises(SceneError, match=r"broken\.mp4: cannot (open|decode)"):
        read_video_frame(tmp_path / "broken.mp4", 0)
    (tmp_path / "broken.png").write_bytes(b"garbage")
    with pytest.raises(SceneError, match=r"broken\.png: cannot decode the image"):
        read_image(tmp_path / "broken.png")
    with pytest.raises(SceneError, match=r"absent\.png: image file not found"):
        read_image(tmp_path / "absent.png")


def test_sixteen_bit_and_alpha_images(tmp_path):
    import cv2

    deep = (np.arange(H * W, dtype=np.uint16).reshape(H, W) * 61).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    np.testing.assert_allclose(read_image(tmp_path / "deep.png")[:, :, 0], deep / 65535, atol=1e-7)
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., 2], rgba[..., 3] = 200, 128  # red (BGR order on disk), half transparent
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    image = read_image(tmp_path / "rgba.png")
    assert image.shape == (H, W, 3)
    np.testing.assert_allclose(image[0, 0], [200 / 255 * 128 / 255, 0, 0], atol=1e-6)
