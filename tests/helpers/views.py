"""A small synthetic capture for loader tests: cameras on a ring looking at the origin and
random 8-bit images (exact through PNG), with helpers that write it in each source format."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from flamerecon.geometry.cameras import look_at, opencv_w2c_to_opengl_c2w

WIDTH, HEIGHT = 40, 32
NAMES = ["cam00", "cam01", "cam02", "cam03"]
BOX = ((-0.4, -0.3, -0.5), (0.5, 0.6, 0.35))


def ring_cameras(n: int = 4, radius: float = 3.0) -> torch.Tensor:
    """OpenCV world->camera (n, 4, 4) on a tilted ring around the origin."""
    angles = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + 0.3
    eye = torch.stack(
        [radius * torch.cos(angles), 0.4 + 0.2 * torch.sin(2 * angles), radius * torch.sin(angles)],
        dim=-1,
    )
    return look_at(eye, torch.zeros(3)).double()


def centred_K(f: float = 45.0) -> np.ndarray:
    """flamerecon K (pixel centres at +0.5) with the principal point PINF uses (W/2, H/2 there)."""
    return np.array([[f, 0, WIDTH / 2 + 0.5], [0, f, HEIGHT / 2 + 0.5], [0, 0, 1.0]])


def random_images(n: int = 4, channels: int = 1, seed: int = 0) -> np.ndarray:
    """uint8 images (n, H, W, C)."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(n, HEIGHT, WIDTH, channels), dtype=np.uint8)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB or gray uint8 image (H, W, C) as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = image[:, :, ::-1] if image.shape[2] == 3 else image[:, :, 0]
    assert cv2.imwrite(str(path), np.ascontiguousarray(bgr))


def write_video(path: Path, frames: np.ndarray, fourcc: str) -> bool:
    """Write gray uint8 frames (T, H, W) as a video; False when this OpenCV cannot encode it."""
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (frames.shape[2], frames.shape[1]), False
    )
    if not writer.isOpened():
        return False
    for f in frames:
        writer.write(np.ascontiguousarray(f))
    writer.release()
    return path.is_file() and path.stat().st_size > 0


def as_float(images: np.ndarray) -> torch.Tensor:
    """uint8 (B, H, W, C) -> float (B, C, H, W) in [0, 1], as the loaders return."""
    return torch.from_numpy(images.astype(np.float32) / 255.0).permute(0, 3, 1, 2)


def write_pinf(folder: Path, images: np.ndarray) -> None:
    """A PINF info.json capture of the ring cameras (two held out), frames NAME/000000.png."""
    w2c = ring_cameras(len(NAMES))
    angle = 2 * math.atan(0.5 * WIDTH / centred_K()[0, 0])
    entries = [{"file_name": f"{name}.mp4", "camera_hw": [HEIGHT, WIDTH], "camera_angle_x": angle,
                "transform_matrix": opencv_w2c_to_opengl_c2w(w2c[v]).double().tolist()} for v, name in enumerate(NAMES)]
    for v, name in enumerate(NAMES):
        write_png(folder / name / "000000.png", images[v])
    scale = np.subtract(BOX[1], BOX[0])
    matrix = np.eye(4)
    matrix[:3, 3] = BOX[0]
    matrix = matrix[:, [2, 1, 0, 3]]  # PINF's column swap, undone by its loader
    info = {"train_videos": entries[:2], "test_videos": entries[2:], "voxel_matrix": matrix.tolist(),
            "voxel_scale": scale[[2, 1, 0]].tolist()}
    (folder / "info.json").write_text(json.dumps(info))


def rotation_quaternion(R: np.ndarray) -> list[float]:
    """(w, x, y, z) by scipy, independent of the converter's own quaternion code."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [float(w), float(x), float(y), float(z)]


def write_colmap(folder: Path, images: np.ndarray, model: str = "PINHOLE", params: str | None = None) -> Path:
    """A COLMAP text model of the ring cameras (pixel centres at +0.5, as flamerecon's K) and
    its images in folder/images/; returns the model folder."""
    K = centred_K()
    params = params or f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}"
    model_dir = folder / "sparse" / "0"
    model_dir.mkdir(parents=True)
    (model_dir / "cameras.txt").write_text(f"# Camera list\n1 {model} {WIDTH} {HEIGHT} {params}\n")
    lines = ["# Image list with two lines of data per image:"]
    for v, w2c in enumerate(ring_cameras(len(NAMES)).numpy()):
        q = rotation_quaternion(w2c[:3, :3])
        lines += [f"{v + 1} {' '.join(map(repr, q))} {' '.join(map(repr, w2c[:3, 3].tolist()))} 1 {NAMES[v]}.png",
                  "12.5 3.5 -1" if v % 2 else ""]
        write_png(folder / "images" / f"{NAMES[v]}.png", images[v])
    (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    return model_dir
