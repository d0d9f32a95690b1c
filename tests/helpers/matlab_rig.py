"""A chemiluminescence rig as its owner's MATLAB calibration leaves it (issue 36): seven cameras
around a burner flame whose axis is +z, 96 x 96 16-bit PNGs in one flat folder named
``{camera}_t{frame:04d}.png``, world units of 0.5 mm, the cameras' image-down axis along +z
(the flame shows upside down), a little lens distortion; the calibration written as MATLAB's
``jsonencode`` of a map from camera name to ``cameraParameters`` in either convention, and the
same rig by hand in scene=opencv's format (the cameras it was rendered with: the reference the
conversion must equal).

    PYTHONPATH=. python tests/helpers/matlab_rig.py OUT      # writes OUT/matlab_pre.json, ...

The images are rendered from a phantom twice as fine as a 48-cell reconstruction grid, then
distorted by each camera's OpenCV distortion (each pixel samples the pinhole image where
``cv2.undistortPoints`` puts it), so that the loader's ``cv2.undistort`` undoes it.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.scenes.synthetic import smooth_flame_emission

NAMES = [f"cam{i}" for i in range(1, 8)]
SIZE = 96
UNIT = 0.0005  # metres per world unit: half millimetres
FRAMES = (0, 1, 2)
PATTERN = "{camera}_t{frame:04d}.png"
#: the flame's box in world units (x, y across the burner, z along its axis)
BOX = ((-36.0, -36.0, 0.0), (36.0, 36.0, 132.0))
#: world units per unit of the synthetic flame (1.25 high there: 62.5 mm here)
SCALE = 100.0


def opencv_cameras() -> list[dict]:
    """The hand-made calibration in OpenCV's conventions: per camera K (pixel index k at
    coordinate k), dist (k1 k2 p1 p2 k3), world->camera R and t (world units)."""
    cameras = []
    for i, name in enumerate(NAMES):
        azimuth = 2 * math.pi * i / len(NAMES) + 0.2
        height = 66.0 + 40.0 * (-1) ** i
        eye = torch.tensor([620.0 * math.cos(azimuth), 620.0 * math.sin(azimuth), height])
        w2c = look_at(eye, torch.tensor([0.0, 0.0, 66.0]), up=(0.0, 0.0, -1.0))[0].double().numpy()  # down: +z
        u, _, vt = np.linalg.svd(w2c[:3, :3])  # orthonormal in float64, not only to float32's precision
        w2c[:3, :3] = u @ vt
        fx = 360.0 + 7.5 * i
        K = [[fx, 0.0, 47.3 + 0.4 * i], [0.0, fx * 1.002, 47.8 - 0.3 * i], [0.0, 0.0, 1.0]]
        dist = [-0.04 + 0.01 * i, 0.012, 0.0008 * (i - 3), -0.0005, 0.002 * (i % 2)]
        cameras.append({"name": name, "K": K, "dist": dist, "R": w2c[:3, :3].tolist(), "t": w2c[:3, 3].tolist()})
    return cameras


def _kornia(cameras: list[dict]):
    K = torch.tensor([c["K"] for c in cameras], dtype=torch.float64)
    K[:, :2, 2] += 0.5  # flamerecon's pixel centres
    w2c = torch.eye(4, dtype=torch.float64).repeat(len(cameras), 1, 1)
    w2c[:, :3, :3] = torch.tensor([c["R"] for c in cameras], dtype=torch.float64)
    w2c[:, :3, 3] = torch.tensor([c["t"] for c in cameras], dtype=torch.float64)
    return make_cameras(intrinsics_matrix(K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]), w2c, SIZE, SIZE)


def render(cameras: list[dict], frame: int, resolution: int = 96) -> np.ndarray:
    """The rig's 16-bit images (7, 96, 96) of frame ``frame`` (0.04 s apart), distorted."""
    grid = VoxelGrid.from_box(BOX[0], BOX[1], resolution)
    points = grid.centers() / SCALE
    flame = smooth_flame_emission(points[..., [0, 2, 1]], seed=3, time=0.04 * frame).mean(-1)  # z up
    volume = (flame * 0.02)[None].float()  # a line integral of a few tenths at the core
    pinhole = render_image(volume, grid, _kornia(cameras))[:, 0].numpy()
    out = []
    for cam, image in zip(cameras, pinhole):
        K, dist = np.array(cam["K"]), np.array(cam["dist"])
        u, v = np.meshgrid(np.arange(SIZE, dtype=np.float64), np.arange(SIZE, dtype=np.float64))
        undone = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K, dist, P=K).reshape(SIZE, SIZE, 2)
        warped = cv2.remap(image.astype(np.float32), undone[..., 0].astype(np.float32),
                           undone[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderValue=0.0)
        out.append(warped)
    images = np.stack(out)
    return (np.clip(images / 0.8, 0, 1) * 65535 + 0.5).astype(np.uint16)


def matlab_camera(cam: dict, convention: str) -> dict:
    """One camera as MATLAB's jsonencode writes a cameraParameters calibrated on one pattern
    (the rig's world), in ``convention`` ``pre`` (R2022a and before) or ``post`` (R2022b+)."""
    K = np.array(cam["K"])
    K[:2, 2] += 1.0  # MATLAB's first pixel centre is (1, 1)
    R, t = np.array(cam["R"]), np.array(cam["t"])
    k1, k2, p1, p2, k3 = cam["dist"]
    rvec = cv2.Rodrigues(R)[0].reshape(3)
    entry = {"RadialDistortion": [k1, k2, k3], "TangentialDistortion": [p1, p2], "ImageSize": [SIZE, SIZE],
             "WorldUnits": "mm", "EstimateSkew": False, "NumRadialDistortionCoefficients": 3,
             "EstimateTangentialDistortion": True, "FocalLength": [K[0, 0], K[1, 1]],
             "PrincipalPoint": [K[0, 2], K[1, 2]], "Skew": 0, "NumPatterns": 1,
             "RotationVectors": rvec.tolist(), "TranslationVectors": t.tolist(), "MeanReprojectionError": 0.12}
    if convention == "pre":  # K transposed; x_cam = x_world * R + t
        entry.update(IntrinsicMatrix=K.T.tolist(), RotationMatrices=R.T.tolist())
    else:  # K; rigidtform3d, x_cam = R * x_world + t
        A = np.eye(4)
        A[:3, :3], A[:3, 3] = R, t
        entry.update(K=K.tolist(), PatternExtrinsics={"Dimensionality": 3, "R": R.tolist(), "Translation": t.tolist(),
                                                      "A": A.tolist()})
    return entry


def write_rig(folder: Path, rendered: bool = True, frames: tuple[int, ...] = FRAMES) -> dict[str, Path]:
    """Write the rig into ``folder``: ``frames/`` (the flat folder), ``matlab_pre.json`` and
    ``matlab_post.json`` (the calibration in each convention) and ``reference/`` (the same rig
    in scene=opencv's format by hand: calibration.yaml and NAME/NNNNNN.png). Returns the paths.
    Without ``rendered`` the images are blank (quick, for tests of the calibration alone).
    ``frames``: which frames (each 5 s to render)."""
    cameras = opencv_cameras()
    flat, reference = folder / "frames", folder / "reference"
    flat.mkdir(parents=True)
    for frame in frames:
        images = render(cameras, frame) if rendered else np.zeros((len(cameras), SIZE, SIZE), np.uint16)
        for cam, image in zip(cameras, images):
            assert cv2.imwrite(str(flat / PATTERN.format(camera=cam["name"], frame=frame)), image)
            (reference / cam["name"]).mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(reference / cam["name"] / f"{frame:06d}.png"), image)
    paths = {"frames": flat, "reference": reference / "calibration.yaml"}
    for convention in ("pre", "post"):
        paths[convention] = folder / f"matlab_{convention}.json"
        paths[convention].write_text(json.dumps({c["name"]: matlab_camera(c, convention) for c in cameras}))
    record = {"cameras": [{**c, "width": SIZE, "height": SIZE} for c in cameras], "unit": UNIT, "up": "+z"}
    paths["reference"].write_text("# the rig by hand (tests/helpers/matlab_rig.py)\n" + yaml.safe_dump(record))
    return paths


if __name__ == "__main__":
    print(write_rig(Path(sys.argv[1])))
