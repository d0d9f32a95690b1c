"""Where to put the next camera: each candidate camera ranked by how much of a confidence
volume's variance its image would remove.

The confidence (:class:`~flamerecon.evaluate.uncertainty.Confidence`) is an ensemble: voxel v
(and channel) has the deviations ``d_v`` (J,) of its J members (members minus the
reconstruction, and the shifts), weighted so that ``|d_v|^2`` is the confidence volume squared
there. A camera sees them as ``y`` (J,) at the pixel v's centre projects to (the deviations
rendered). Observing pixels with noise of variance ``s^2`` updates the ensemble as a Kalman
filter does; localised to one pixel per camera and voxel (with a handful of members, an update
by every pixel at once would claim that any camera resolves the whole ensemble), the cameras'
pixels ``Y_v`` (T, J) on voxel v remove ``(Y_v d_v)^T (Y_v Y_v^T + s^2 I)^-1 (Y_v d_v)`` (at
most ``|d_v|^2``) of its variance. The ensemble's members are not conditioned on the cameras
already fitted (a member fitted without camera k deviates where k sees), so those cameras are
assimilated first and a candidate's value is what it removes beyond them: a camera beside a
fitted one adds little. The sum over voxels and channels is in density units squared; a
prediction of the ensemble's linear-Gaussian model, checked by ``scripts/plan_cameras.py
--check-*``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.evaluate.uncertainty import Confidence
from flamerecon.geometry.axes import ground_frame
from flamerecon.geometry.cameras import (
    camera_centers,
    camera_subset,
    cameras_to,
    look_at,
    make_cameras,
    project_points,
)
from flamerecon.operators.projector import render_image

#: two cameras whose sight lines through the box centre lie within this angle (degrees) of each
#: other, or of opposite directions, see nearly the same line integrals (:func:`alike`)
MIRROR_DEG = 20.0


def weighted_deviations(conf: Confidence) -> list[torch.Tensor]:
    """The deviations (C, nz, ny, nx) of ``conf``, each times ``scale / sqrt(n)`` for the ``n``
    members of its kind: the sum of their squares is the confidence volume squared."""
    out = []
    for _, devs in conf.deviations():
        devs = list(devs)
        weight = float(conf.scale) / len(devs) ** 0.5
        out += [weight * d for d in devs]
    return out


def voxel_observations(conf: Confidence, devs: list[torch.Tensor], where: torch.Tensor,
                       cams: PinholeCamera) -> torch.Tensor:
    """(C, V, B, J) float64: for each voxel of the flat indices ``where`` (V,), what each
    camera of ``cams`` sees of the deviations ``devs`` (J of (C, nz, ny, nx)): their renders at
    the pixel the voxel's centre projects to (pixel i covers [i, i + 1)); 0 where it projects
    outside the image or behind the camera."""
    C, B = devs[0].shape[0], cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    centres = conf.grid.centers(conf.x.device).reshape(-1, 3)[where]
    out = torch.zeros(C, where.numel(), B, len(devs), dtype=torch.float64, device=conf.x.device)
    for b in range(B):
        one = camera_subset(cams, [b])
        Y = torch.stack([render_image(d, conf.grid, one, conf.step)[0].reshape(C, -1) for d in devs], -1)
        uv, depth = project_points(one, centres.to(one.extrinsics.dtype))
        u, v = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
        seen = (depth[0] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        out[:, seen, b] = Y[:, (v * W + u)[seen]].double()
    return out


def removed(d: torch.Tensor, Y: torch.Tensor, noise: float) -> torch.Tensor:
    """(C, V) the variance the observations ``Y`` (C, V, T, J) with noise ``noise`` remove
    from the voxels whose deviations are ``d`` (C, V, J) (the module's docstring)."""
    if Y.shape[2] == 0:
        return d.new_zeros(d.shape[:2])
    Yd = torch.einsum("cvtj,cvj->cvt", Y, d)
    M = Y @ Y.transpose(-1, -2) + noise**2 * torch.eye(Y.shape[2], dtype=Y.dtype, device=Y.device)
    return (Yd * torch.linalg.solve(M, Yd.unsqueeze(-1)).squeeze(-1)).sum(-1)


def variance_reduction(conf: Confidence, cams: PinholeCamera, noise: float,
                       fitted: PinholeCamera | None = None, progress=None) -> torch.Tensor:
    """(B,) float64: for each camera of ``cams``, the predicted reduction of the confidence
    volume's total variance (sum over voxels and channels of its square, density units squared)
    if that camera alone were added to the ``fitted`` cameras (assimilated first; None: none),
    pixels observed with one-sigma ``noise`` (image units, > 0); see the module's docstring.
    Channels are independent observations of their own deviations. ``progress(b)`` is called
    after each camera."""
    if not noise > 0:
        raise ValueError(f"variance_reduction: noise must be > 0, got {noise}")
    devs = weighted_deviations(conf)
    B = cams.batch_size
    if not devs:
        return torch.zeros(B, dtype=torch.float64)
    C = devs[0].shape[0]
    D = torch.stack([d.reshape(C, -1) for d in devs], -1).double()  # (C, V, J)
    where = (D != 0).any(-1).any(0).nonzero().squeeze(1)  # voxels with any deviation
    D = D[:, where]
    cams = cameras_to(cams, conf.x.device)
    base = (voxel_observations(conf, devs, where, cameras_to(fitted, conf.x.device)) if fitted is not None
            else D.new_zeros(C, where.numel(), 0, len(devs)))
    before = removed(D, base, noise).sum()
    out = torch.zeros(B, dtype=torch.float64)
    for b in range(B):
        Y = voxel_observations(conf, devs, where, camera_subset(cams, [b]))
        out[b] = float(removed(D, torch.cat([base, Y], 2), noise).sum() - before)
        if progress is not None:
            progress(b)
    return out


def total_variance(conf: Confidence) -> float:
    """The confidence volume's total variance: the sum of its square over voxels and channels."""
    return float(conf.volume().double().pow(2).sum())


def rank_cameras(conf: Confidence, cams: PinholeCamera, noise: float) -> list[tuple[int, float]]:
    """(camera index, predicted reduction) of every camera of ``cams``, best first
    (:func:`variance_reduction`)."""
    found = variance_reduction(conf, cams, noise)
    return sorted(((b, float(r)) for b, r in enumerate(found)), key=lambda t: -t[1])


def orbit_candidates(rig: PinholeCamera, target, count: int, up) -> tuple[PinholeCamera, torch.Tensor]:
    """``count`` candidate cameras evenly around ``target`` (3,) world, at world azimuths 0,
    360/count, ... about the scene's ``up`` (3,) (:func:`~flamerecon.geometry.axes.ground_frame`),
    at the rig's mean distance from ``target`` and mean elevation, looking at it, with the first
    camera's intrinsics and image size: (cameras, azimuths (count,) degrees)."""
    target = torch.as_tensor(target, dtype=torch.float64).reshape(3)
    up = torch.as_tensor(np.asarray(up, np.float64))
    offsets = camera_centers(rig).double() - target
    distance = float(offsets.norm(dim=-1).mean())
    elevation = float(torch.asin(((offsets @ up) / offsets.norm(dim=-1)).clamp(-1, 1)).mean())
    first, second = (torch.as_tensor(v) for v in ground_frame(up.numpy()))
    azimuths = torch.arange(count, dtype=torch.float64) * 360.0 / count
    a = torch.deg2rad(azimuths)
    eyes = target + distance * (math.cos(elevation) * (torch.cos(a)[:, None] * first + torch.sin(a)[:, None] * second)
                                + math.sin(elevation) * up)
    w2c = look_at(eyes, target.expand(count, 3), up)
    K = rig.intrinsics[:1, :3, :3].expand(count, 3, 3)
    return make_cameras(K, w2c, int(rig.height[0]), int(rig.width[0])), azimuths


def sight_lines(cams: PinholeCamera, target) -> np.ndarray:
    """(B, 3) unit directions from each camera's centre to ``target`` (3,)."""
    d = np.asarray(target, np.float64).reshape(1, 3) - camera_centers(cams).double().cpu().numpy()
    return d / np.linalg.norm(d, axis=1, keepdims=True).clip(1e-12)


def alike(lines: np.ndarray, others: np.ndarray, degrees: float = MIRROR_DEG) -> list[list[tuple[int, str]]]:
    """For each sight line of ``lines`` (N, 3), the indices of ``others`` (M, 3) within
    ``degrees`` of it, each with how: ``beside`` (the same direction) or ``mirror`` (the opposite
    one: emission-only images are line integrals, so a camera facing another sees nearly its
    image mirrored, and adds nearly nothing to it)."""
    cos = np.asarray(lines) @ np.asarray(others).T
    limit = math.cos(math.radians(degrees))
    return [[(m, "beside" if c > 0 else "mirror") for m, c in enumerate(row) if abs(c) >= limit] for row in cos]


def volume_error(conf: Confidence, variance: float) -> float:
    """The relative L2 error of the density that a confidence of total ``variance`` (density
    units squared) predicts: sqrt(variance) / |density| (NaN for an empty density)."""
    norm = float(conf.x.double().pow(2).sum())
    return math.sqrt(max(variance, 0.0) / norm) if norm > 0 else math.nan

