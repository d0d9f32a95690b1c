"""A small synthetic capture for loader tests: cameras on a ring looking at the origin and
random 8-bit images (exact through PNG), with helpers that write it in each source format."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from flamerecon.geometry.cameras import look_at

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
