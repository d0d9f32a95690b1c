"""Pinhole cameras as kornia ``PinholeCamera`` batches, and the rays through their pixels.

Conventions used everywhere in flamerecon:

- world -> camera extrinsics in the OpenCV frame (x right, y down, z forward);
- pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``; its centre is ``(u + 0.5, v + 0.5)``;
- intrinsics ``K`` map camera coordinates to those continuous pixel coordinates.

Loaders whose source puts pixel index ``k`` at coordinate ``k`` (PINF, OpenCV calibration
files) shift the principal point by +0.5 when they build ``K``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import tensor, value, wrong_type, wrong_value
from flamerecon.rules import integer, number


def intrinsics_matrix(fx, fy, cx, cy) -> torch.Tensor:
    """Stack focal lengths and principal points (each (B,) or scalar) into K of shape (B, 3, 3)."""
    fx, fy, cx, cy = (torch.as_tensor(v, dtype=torch.float32).reshape(-1) for v in (fx, fy, cx, cy))
    fx, fy, cx, cy = torch.broadcast_tensors(fx, fy, cx, cy)
    K = torch.zeros(fx.shape[0], 3, 3)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fx, fy, cx, cy, 1.0
    return K


def make_cameras(K: torch.Tensor, world_to_camera: torch.Tensor, height, width) -> PinholeCamera:
    """Build a kornia camera batch from K (B, 3, 3), OpenCV world->camera (B, 4, 4) and sizes (B,)."""
    K = torch.as_tensor(K, dtype=torch.float32)
    E = torch.as_tensor(world_to_camera, dtype=torch.float32)
    B = K.shape[0]
    K4 = torch.eye(4, dtype=K.dtype).repeat(B, 1, 1)
    K4[:, :3, :3] = K
    h = torch.as_tensor(height, dtype=torch.float32).reshape(-1).expand(B).clone()
    w = torch.as_tensor(width, dtype=torch.float32).reshape(-1).expand(B).clone()
    return PinholeCamera(K4, E.clone(), h, w)


def camera_subset(cams: PinholeCamera, index) -> PinholeCamera:
    """The cameras at ``index`` (list of ints or a tensor) as a new batch."""
    idx = torch.as_tensor(index, dtype=torch.long, device=cams.intrinsics.device)
    return PinholeCamera(
        cams.intrinsics[idx], cams.extrinsics[idx], cams.height[idx], cams.width[idx]
    )


def cameras_to(cams: PinholeCamera, device) -> PinholeCamera:
    """Move a camera batch to ``device``."""
    return PinholeCamera(
        cams.intrinsics.to(device), cams.extrinsics.to(device),
        cams.height.to(device), cams.width.to(device),
    )


def resized_cameras(cams: PinholeCamera, height: int, width: int) -> PinholeCamera:
    """The cameras for images resized to ``height`` x ``width`` pixels: fx, cx scaled by the
    width ratio and fy, cy by the height ratio (pixel centres at +0.5, so a continuous pixel
    coordinate scales exactly with the image; the same map ``scene.downscale`` applies to K),
    poses unchanged."""
    B = cams.batch_size
    scale = torch.stack([width / cams.width, height / cams.height, torch.ones_like(cams.width)], -1)  # (B, 3)
    K = K_of(cams) * scale[:, :, None]
    return make_cameras(K, cams.extrinsics, torch.full((B,), float(height)), torch.full((B,), float(width)))


def K_of(cams: PinholeCamera) -> torch.Tensor:
    """Intrinsics (B, 3, 3)."""
    return cams.intrinsics[:, :3, :3]


def opengl_c2w_to_opencv_w2c(c2w: torch.Tensor) -> torch.Tensor:
    """NeRF/Blender camera->world (…, 4, 4), y up and z back, to OpenCV world->camera (…, 4, 4)."""
    c2w = torch.as_tensor(c2w, dtype=torch.float64)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=c2w.dtype))
    return torch.linalg.inv(c2w @ flip).to(torch.float32)


def opencv_w2c_to_opengl_c2w(w2c: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`opengl_c2w_to_opencv_w2c`."""
    w2c = torch.as_tensor(w2c, dtype=torch.float64)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=w2c.dtype))
    return (torch.linalg.inv(w2c) @ flip).to(torch.float32)


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> torch.Tensor:
    """OpenCV world->camera (B, 4, 4) for cameras at ``eye`` (B, 3) looking at ``target`` (B, 3).

    ``up`` is the world direction that appears upwards in the image (negative camera y).
    """
    eye = torch.as_tensor(eye, dtype=torch.float64).reshape(-1, 3)
    target = torch.as_tensor(target, dtype=torch.float64).reshape(-1, 3).expand_as(eye)
    up = torch.as_tensor(up, dtype=torch.float64).reshape(-1, 3).expand_as(eye)
    z = torch.nn.functional.normalize(target - eye, dim=-1)
    x = torch.nn.functional.normalize(torch.cross(z, up, dim=-1), dim=-1)
    y = torch.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=1)  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=torch.float64).repeat(eye.shape[0], 1, 1)
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = -(R @ eye.unsqueeze(-1)).squeeze(-1)
    return w2c.to(torch.float32)


def look_at_camera(eye, target, up=(0.0, 1.0, 0.0), width: int = 320, height: int = 240,
                   fov_deg: float = 40.0) -> PinholeCamera:
    """Pinhole cameras at ``eye`` ((3,) or (B, 3), world units) looking at ``target``, with
    ``up`` the world direction upwards in the image, a ``width`` x ``height`` pixel image,
    ``fov_deg`` its vertical field of view and the principal point at the image centre: a
    kornia batch of B cameras (1 for one eye), ready for :func:`flamerecon.render`.
    A bad argument is an :class:`~flamerecon.errors.ArgumentError` (or ArgumentTypeError) naming it."""
    eye = points("look_at_camera.eye", eye)
    target = points("look_at_camera.target", target, len(eye))
    up = points("look_at_camera.up", up, len(eye))
    value("look_at_camera.width", width, integer(1))
    value("look_at_camera.height", height, integer(1))
    value("look_at_camera.fov_deg", fov_deg, number(0.0, 180.0, lo_open=True, hi_open=True))
    if bool(((target - eye).norm(dim=-1) == 0).any()):
        raise wrong_value("look_at_camera.target", target, "away from the eye (a direction to look in)")
    if bool((torch.linalg.cross(target - eye, up.expand_as(eye)).norm(dim=-1) == 0).any()):
        raise wrong_value("look_at_camera.up", up, "a direction not along the line of sight")
    w2c = look_at(eye, target, up)
    focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    K = intrinsics_matrix(focal, focal, width / 2, height / 2).expand(w2c.shape[0], 3, 3)
    return make_cameras(K, w2c, height, width)


def points(name: str, given, count: int | None = None) -> torch.Tensor:
    """``given`` (a sequence, array or tensor) as finite float64 points (B, 3), B = 1 for one
    point; with ``count``, one point or ``count`` of them. Else an ArgumentError naming ``name``."""
    if isinstance(given, (str, bytes)) or given is None:
        raise wrong_type(name, given, "a point (x, y, z) or a (B, 3) array of them")
    try:
        t = torch.as_tensor(given if isinstance(given, torch.Tensor) else np.asarray(given, dtype=np.float64))
    except (TypeError, ValueError):
        raise wrong_type(name, given, "a point (x, y, z) or a (B, 3) array of them") from None
    t = tensor(name, t.to(torch.float64) if t.dtype != torch.bool else t, "(3,) or (B, 3)")
    if t.shape[-1:] != (3,) or t.ndim > 2 or (count is not None and t.numel() != 3 and len(t.reshape(-1, 3)) != count):
        raise wrong_value(name, t, "a point (x, y, z)" if count == 1 else "a point (x, y, z) or a (B, 3) array of "
                          + ("them" if count is None else f"{count} of them, one per eye"))
    tensor(name, t, "(3,) or (B, 3)", finite=True)
    return t.reshape(-1, 3).cpu()


def camera_centers(cams: PinholeCamera) -> torch.Tensor:
    """Camera centres in world coordinates (B, 3)."""
    R = cams.extrinsics[:, :3, :3]
    t = cams.extrinsics[:, :3, 3:]
    return -(R.transpose(1, 2) @ t).squeeze(-1)


def pixel_centers(height: int, width: int, device=None) -> torch.Tensor:
    """Continuous coordinates of every pixel centre, (H*W, 2) as (u, v), row-major (v slowest)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def pixel_rays(cams: PinholeCamera, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through pixel coordinates ``uv`` (B, R, 2) of each camera.

    Returns origins (B, R, 3) and unit directions (B, R, 3), from ``PinholeCamera.unproject``.
    """
    B, R = uv.shape[:2]
    points = cams.unproject(uv, torch.ones(B, R, 1, dtype=uv.dtype, device=uv.device))
    origins = camera_centers(cams)[:, None, :].expand(B, R, 3)
    directions = torch.nn.functional.normalize(points - origins, dim=-1)
    return origins.contiguous(), directions


def project_points(cams: PinholeCamera, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points xyz (N, 3) into every camera.

    Returns pixel coordinates (B, N, 2) and depths along the optical axis (B, N).
    """
    B = cams.batch_size
    pts = xyz[None].expand(B, -1, -1)
    R = cams.extrinsics[:, :3, :3]
    t = cams.extrinsics[:, :3, 3]
    depth = (pts @ R.transpose(1, 2) + t[:, None, :])[..., 2]
    return cams.project(pts), depth
