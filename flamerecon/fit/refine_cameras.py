"""Camera self-calibration: small corrections of the training cameras, fitted through the
differentiable renderer, alternating with the density solve.

Corrections of training camera ``i`` (a row of ``theta`` (T, 9), world units, radians, pixels):

- ``[0:3]`` rotation ``w`` (axis-angle) and ``[3:6]`` translation ``t``: the camera moves rigidly
  with the world motion ``G(x) = R(w) (x - p) + p + t`` about the box centre ``p``, so its
  world->camera becomes ``world_to_camera @ G^-1``;
- ``[6]`` log focal scale ``k`` (fx and fy times ``exp(k)``) and ``[7:9]`` principal point
  shift in pixels (``pose+intrinsics`` only; zero with ``pose``).

Gauge. Moving every camera by the same ``G`` (and the density with it), or scaling the world
about ``p``, changes no training image, so no training view can tell it; a held-out camera,
scored with its own unrefined calibration, would. The corrections are therefore held in the
calibration's world frame: every parameter has zero mean over the training cameras and the
translations have no component along ``c_i - p`` (a common scaling; ``c_i`` the centres). A
common focal or principal point change nearly is such a motion too, so it gets the same zero
mean. A quadratic prior (one-sigma sizes in :class:`RefineOptions`) holds what the views see
weakly (e.g. a pivot rotation against a principal point shift).

Frames. The cameras of a capture stand still while the flame moves, so one set of corrections
may be fitted to several frames at once (:class:`CalibrationFrame`, one density each): a frame
holding little smoke leaves parts of the box unseen, and its corrections there are guesses.

Camera step: Levenberg-Marquardt on the corrections with the density fixed, over each training
camera's silhouette pixels grown by a background band (at most ``max_rays`` per camera, shared
among the frames). Its
Jacobian comes from one backward pass per channel through the matrix-free renderer (a pixel
depends only on its own ray: d pixel / d ray) chained with the derivative of the rays with
respect to the corrections, in closed form (:func:`ray_tangents`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.liegroup import So3

from flamerecon import interrupt
from flamerecon.errors import ArgumentError
from flamerecon.fit.option_rules import check_section
from flamerecon.geometry.cameras import (
    K_of,
    camera_centers,
    camera_subset,
    make_cameras,
    pixel_rays,
    project_points,
)
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import Rays, integrate_dense, support_box
from flamerecon.progress import Progress

#: parameters per camera: rotation (3), translation (3), log focal scale (1), principal point (2).
N_PARAMS = 9


def auto_frames(numbers: Sequence[int]) -> tuple[int, ...]:
    """``calibration.frames: auto`` for a capture whose cameras hold the frame ``numbers`` (in
    order): those at 2/5 and 14/15 of the list (30 and 69 of 0-74; 51 and 53 of 50, 51, 53),
    the one frame of a capture of one."""
    numbers = list(numbers)
    return tuple(sorted({numbers[round(f * (len(numbers) - 1))] for f in (0.4, 14 / 15)}))


@dataclass(frozen=True)
class RefineOptions:
    """What :func:`refine` does (the ``calibration:`` node of the config).

    - ``refine``: ``none``, ``pose`` (rotation + translation) or ``pose+intrinsics`` (+ focal
      scale and principal point);
    - ``rounds``: density solve / camera step alternations (the caller solves once more after);
    - ``iterations``: Levenberg-Marquardt iterations per camera step;
    - ``band_px``: background pixels around each (dilated) silhouette that enter the camera fit;
    - ``max_rays``: pixels per camera in the camera fit (a random subset, drawn per round);
    - ``prior_*``: one-sigma sizes of the corrections: rotation in degrees, translation as a
      fraction of the camera's distance to the box centre, focal as a fraction, principal
      point in pixels of the working images;
    - ``fit_against``: ``others``: each camera is fitted to the density solved from the other
      training cameras (one solve per camera and round; the density cannot absorb the
      camera's own error, so the fit converges in a few rounds), ``all``: to the density of
      every training camera (one solve per round; converges slowly, as that density was
      fitted to the errors); ``others`` needs three training cameras or more;
    - ``resolution``: the grid of the densities the cameras are fitted to (cells along the
      box's longest side; None: the reconstruction's). A coarser, smoother density cannot
      absorb the cameras' errors as a fine one does;
    - ``frames``: the frames of the capture whose training views the cameras are fitted to
      (the cameras stand still); empty: the frame reconstructed; ``auto``: two frames at 2/5
      and 14/15 of the capture (ScalarFlow's 30 and 70 of 75, where the plume has risen; its
      one frame for a capture of one, :func:`auto_frames`). Fitted once per capture and
      options, kept as a cameras.json file in ``folder`` and read back from it
      (:func:`flamerecon.fit.capture_calibration.capture_refinement`);
    - ``gauge``: how the refined cameras are held in the calibration's world frame: ``mean``
      (zero-mean corrections, see the module doc) or ``similarity`` (also, after the fit, the
      similarity that best maps the refined cameras' centres and axes onto the calibration's,
      :func:`align_similarity`, applied to all of them: the rig keeps its shape, a camera that
      was not refined sits where the calibration put it relative to the others);
    - ``rig``: with ``frames``, refine every camera of the capture on those frames, the held-out
      ones included (they are one rig): the frame reconstructed must not be one of ``frames``,
      so that a held-out camera's pixels of a scored frame never enter the fit. Off (the
      *strict* protocol): held-out cameras keep the calibration file's pose;
    - ``first_iterations``: iterations of each frame's first density solve (from zero, with
      the capture's cameras); None: the solver's own ``max_iters``. The cameras need the
      density's structure, not its last digits;
    - ``solve_iterations``: iterations of each density solve after the first one of a frame,
      warm-started from that frame's previous density (the cameras moved by a fraction of a
      pixel, so the density barely changes); None: the solver's own ``max_iters``;
    - ``seed``: of the pixel subsets;
    - ``folder``: where a capture's calibration files are kept (None: ``calibration/`` in the
      cache folder, :func:`flamerecon.scenes.cache.cache_home`);
    - ``file``: a cameras.json (a run's, or a capture's calibration file) whose cameras replace
      the training cameras; no camera fit runs, whatever ``refine`` says;
    - ``min_gain``: the relative drop of the camera fit's residual RMS in its first round below
      which it found nothing to correct: the fit stops there and keeps the capture's own
      cameras (a fit that gains less chases the noise and the density's bias: 0.1-0.4% on exact
      synthetic cameras, 2.3% with a coarse 20-cell, 40-iteration density, where it moved them by
      up to a pixel over three rounds; cameras off by 0.1 degree and 0.5 px gain 7-10%, and
      ScalarFlow's first round 6.7%);
    - ``score_before``: record the scores of this frame's density solved with the capture's own
      cameras (``train_psnr_before``, ``heldout_psnr_before``) also when the cameras come from a
      file (``frames`` or ``file``), for one more density solve; a fit on the frame itself records
      them anyway (its first solve);
    - ``offsets``: with ``frames``, also measure every camera's pose offset
      (:mod:`flamerecon.fit.pose_uncertainty`: which camera's calibration limits the result, the
      confidence's pose part) once per capture and keep it in the calibration file; a run with the
      confidence on (``uncertainty.enabled``) measures them anyway. Off, a capture's first run
      costs the camera fit alone (ScalarFlow: 13.0 s against 28.9 s with them, a later frame 6.7-6.9 s).
    """

    refine: str = "none"
    rounds: int = 3
    iterations: int = 5
    band_px: int = 3
    max_rays: int = 10000
    prior_rotation_deg: float = 1.0
    prior_translation: float = 0.02
    prior_focal: float = 0.02
    prior_principal_px: float = 5.0
    fit_against: str = "all"
    resolution: int | None = None
    frames: tuple[int, ...] | str = ()
    gauge: str = "mean"
    rig: bool = False
    first_iterations: int | None = None
    solve_iterations: int | None = None
    seed: int = 0
    folder: str | None = None
    file: str | None = None
    score_before: bool = False
    min_gain: float = 0.03
    offsets: bool = False

    def __post_init__(self) -> None:
        check_section("calibration", self)
        if self.rig and not self.frames:
            raise ArgumentError("calibration.rig: needs calibration.frames (the frames the rig is fitted to, none "
                                "of them scored); set calibration.frames=[...] or calibration.rig=false")

    def for_capture(self, numbers: Sequence[int]) -> RefineOptions:
        """These options with ``frames: auto`` resolved for a capture holding the frame ``numbers``."""
        return replace(self, frames=auto_frames(numbers)) if self.frames == "auto" else self

    @property
    def active(self) -> list[int]:
        """The parameter columns fitted: 0-5 (pose), 0-8 (pose+intrinsics), none for ``none``."""
        return {"none": [], "pose": list(range(6)), "pose+intrinsics": list(range(N_PARAMS))}[self.refine]


@dataclass
class Refinement:
    """What :func:`refine` found.

    - ``cameras``: every camera of the scene (B), training ones corrected, held-out unchanged;
    - ``corrections``: ``theta`` (T, 9) of the training cameras (see the module docstring);
    - ``initial_volume``: the density (C, nz, ny, nx) solved with the unrefined cameras (of
      the first frame fitted; None when the refinement was read from the cache);
    - ``history``: per round: ``rms_before`` / ``rms_after`` (camera-fit residual, image
      units), ``iterations`` and ``rays``; a first round that gained less than ``min_gain``
      also ``kept`` (the capture's own cameras, :func:`found_nothing`) and ``stopped`` (why).
    """

    cameras: PinholeCamera
    corrections: torch.Tensor
    initial_volume: torch.Tensor | None
    history: list[dict] = field(default_factory=list)


def found_nothing(history: list[dict]) -> bool:
    """Whether a camera fit's ``history`` says it found nothing to correct (its first round
    gained less than ``min_gain``: the capture's own cameras were kept)."""
    return bool(history) and bool(history[0].get("kept"))


def round_gain(record: dict) -> float:
    """The relative drop of the residual RMS in one round of a camera fit's history."""
    return 1.0 - record["rms_after"] / record["rms_before"] if record["rms_before"] > 0 else 0.0


def skew(w: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices (T, 3, 3) of vectors w (T, 3)."""
    z = torch.zeros_like(w[:, 0])
    return torch.stack([
        torch.stack([z, -w[:, 2], w[:, 1]], -1),
        torch.stack([w[:, 2], z, -w[:, 0]], -1),
        torch.stack([-w[:, 1], w[:, 0], z], -1),
    ], 1)


def corrected_cameras(cams: PinholeCamera, theta: torch.Tensor, pivot: torch.Tensor) -> PinholeCamera:
    """The cameras ``cams`` (T) moved and re-focused by ``theta`` (T, 9) about ``pivot`` (3,);
    differentiable in ``theta``."""
    theta = theta.to(cams.extrinsics.dtype)
    R = torch.linalg.matrix_exp(skew(theta[:, :3]))
    t = pivot + theta[:, 3:6] - (R @ pivot[:, None]).squeeze(-1)  # G(x) = R x + t
    top = torch.cat([R.transpose(1, 2), -(R.transpose(1, 2) @ t[..., None])], -1)  # G^-1
    bottom = torch.zeros_like(top[:, :1])
    bottom = torch.cat([bottom[..., :3], torch.ones_like(bottom[..., :1])], -1)
    E = cams.extrinsics @ torch.cat([top, bottom], 1)
    return make_cameras(refocused(K_of(cams), theta), E, cams.height, cams.width)


def refocused(K: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Intrinsics K (T, 3, 3) re-focused by ``theta`` (T, 9): focal lengths (and skew) times
    exp(theta[:, 6]), principal point moved by theta[:, 7:9] px; differentiable in ``theta``."""
    scale = torch.exp(theta[:, 6])
    row0 = torch.stack([K[:, 0, 0] * scale, K[:, 0, 1] * scale, K[:, 0, 2] + theta[:, 7]], -1)
    row1 = torch.stack([K[:, 1, 0], K[:, 1, 1] * scale, K[:, 1, 2] + theta[:, 8]], -1)
    return torch.stack([row0, row1, K[:, 2]], 1)


def ray_tangents(cams: PinholeCamera, theta: torch.Tensor, pivot: torch.Tensor, uv: torch.Tensor,
                 active: list[int]) -> torch.Tensor:
    """d (origin, direction) / d theta (T, R, 6, 9) of the rays :func:`pixel_rays` gives through
    pixels ``uv`` (T, R, 2) of ``corrected_cameras(cams, theta, pivot)``, analytic, in float64;
    zero for parameters not in ``active``. A correction moves the camera by G(x) = R x + t about
    ``pivot`` (R = Exp(w), t = pivot + v - R pivot) and re-focuses it (K'), so a pixel's ray
    starts at G(c) and points along q = R Rc^T K'^-1 (u, v, 1), normalised (Rc: the camera's
    rotation, c its centre)."""
    T, R = uv.shape[:2]
    dtype, device = torch.float64, uv.device
    th = theta.detach().to(dtype)
    Rg = torch.linalg.matrix_exp(skew(th[:, :3]))
    Jr = So3.right_jacobian(th[:, :3])  # Exp(w + d) = Exp(w) Exp(Jr d) to first order
    Rc = cams.extrinsics[:, :3, :3].to(dtype)
    Kp = refocused(K_of(cams).to(dtype), th)
    pix = torch.cat([uv.to(dtype), torch.ones(T, R, 1, dtype=dtype, device=device)], -1).transpose(1, 2)
    p = torch.linalg.solve(Kp, pix)  # (T, 3, R): K'^-1 (u, v, 1)
    b = Rc.transpose(1, 2) @ p  # (T, 3, R)
    q = Rg @ b
    norm = q.norm(dim=1, keepdim=True)
    d = q / norm
    out = torch.zeros(T, R, 6, N_PARAMS, dtype=dtype, device=device)
    arm = camera_centers(cams).to(dtype) - pivot.to(dtype)  # (T, 3)
    out[:, :, :3, :3] = (-Rg @ skew(arm) @ Jr)[:, None]
    out[:, :, :3, 3:6] = torch.eye(3, dtype=dtype, device=device)
    bt = b.transpose(1, 2).reshape(-1, 3)  # (T R, 3)
    dq = torch.zeros(T, R, 3, N_PARAMS, dtype=dtype, device=device)
    dq[..., :3] = -(Rg[:, None] @ skew(bt).view(T, R, 3, 3)) @ Jr[:, None]
    dK = torch.zeros(T, 3, 3, 3, dtype=dtype, device=device)  # d K' / d theta_6..8
    dK[:, 0, 0, :2] = Kp[:, 0, :2]
    dK[:, 0, 1, 1] = Kp[:, 1, 1]
    dK[:, 1, 0, 2] = 1.0
    dK[:, 2, 1, 2] = 1.0
    for k in range(3):  # d p = -K'^-1 dK p
        dp = -torch.linalg.solve(Kp, dK[:, k] @ p)
        dq[..., 6 + k] = (Rg @ Rc.transpose(1, 2) @ dp).transpose(1, 2)
    dn = d.transpose(1, 2)  # (T, R, 3)
    project = (torch.eye(3, dtype=dtype, device=device) - dn[..., :, None] * dn[..., None, :])
    out[:, :, 3:] = project @ dq / norm.transpose(1, 2)[..., None]
    keep = torch.zeros(N_PARAMS, dtype=torch.bool, device=device)
    keep[list(active)] = True
    return out * keep


def similarity(source: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """The similarity ``x -> s R x + t`` that maps points ``source`` (N, 3) onto ``target`` (N, 3)
    in the least-squares sense (Umeyama 1991), in float64: (s, R (3, 3), t (3,))."""
    a, b = source.double(), target.double()
    mu_a, mu_b = a.mean(0), b.mean(0)
    xa, xb = a - mu_a, b - mu_b
    U, S, Vh = torch.linalg.svd(xb.T @ xa / len(a))
    D = torch.ones(3, dtype=torch.float64)
    D[2] = torch.sign(torch.linalg.det(U @ Vh))
    R = U @ torch.diag(D) @ Vh
    s = float((S * D).sum() / xa.pow(2).sum(1).mean())
    return s, R, mu_b - s * R @ mu_a


def camera_frame_points(cams: PinholeCamera, pivot: torch.Tensor) -> torch.Tensor:
    """Each camera's centre and the points one pivot distance along its x, y and z axes
    (4T, 3): where a camera is and where it looks, in world units."""
    centres = camera_centers(cams).double()
    axes = cams.extrinsics[:, :3, :3].double()  # rows: the camera's axes in world coordinates
    reach = (centres - pivot.double()).norm(dim=-1)[:, None, None]
    return torch.cat([centres[:, None], centres[:, None] + reach * axes], 1).reshape(-1, 3)


def align_similarity(refined: PinholeCamera, calibrated: PinholeCamera, pivot: torch.Tensor) -> PinholeCamera:
    """``refined`` (T) moved as one rigid rig, with a common scale, so that its centres and
    axes (:func:`camera_frame_points`) best match ``calibrated``'s: a similarity S of the
    world changes no image the refined cameras see of a density moved by S, so this only picks
    the frame, the one in which the calibration's other cameras belong. World->camera
    ``[R_i | t_i]`` becomes ``[R_i R^T | s t_i - R_i R^T t]`` (the 1/s of the camera frame
    does not change a pinhole projection)."""
    s, R, t = similarity(camera_frame_points(refined, pivot), camera_frame_points(calibrated, pivot))
    E = refined.extrinsics.double()
    Ri, ti = E[:, :3, :3], E[:, :3, 3]
    E = E.clone()
    E[:, :3, :3] = Ri @ R.T
    E[:, :3, 3] = s * ti - (Ri @ R.T @ t[:, None]).squeeze(-1)
    return make_cameras(K_of(refined), E.to(refined.extrinsics.dtype), refined.height, refined.width)


def prior_sizes(cams: PinholeCamera, pivot: torch.Tensor, options: RefineOptions) -> torch.Tensor:
    """One-sigma size of every correction (T, 9), in its own unit (radians, world, log, px)."""
    distance = (camera_centers(cams) - pivot).norm(dim=-1)  # (T,)
    s = torch.empty(cams.batch_size, N_PARAMS, dtype=torch.float64)
    s[:, :3] = math.radians(options.prior_rotation_deg)
    s[:, 3:6] = options.prior_translation * distance[:, None].double().cpu()
    s[:, 6] = options.prior_focal
    s[:, 7:] = options.prior_principal_px
    return s


def gauge_basis(cams: PinholeCamera, pivot: torch.Tensor, sizes: torch.Tensor, active: list[int]) -> torch.Tensor:
    """Orthonormal basis (9T, K) of the scaled corrections ``z = theta / sizes`` (flattened
    camera-major) that keep the gauge: zero mean of every active parameter over the cameras,
    no common scaling (translations orthogonal to ``c_i - p``), inactive parameters zero."""
    T = cams.batch_size
    rows = []
    for k in range(N_PARAMS):
        if k in active:
            r = torch.zeros(T, N_PARAMS, dtype=torch.float64)
            r[:, k] = 1.0
            rows.append(r)
        else:
            for i in range(T):
                r = torch.zeros(T, N_PARAMS, dtype=torch.float64)
                r[i, k] = 1.0
                rows.append(r)
    if 3 in active:
        r = torch.zeros(T, N_PARAMS, dtype=torch.float64)
        r[:, 3:6] = (camera_centers(cams) - pivot).double().cpu()
        rows.append(r)
    C = torch.stack([r.reshape(-1) for r in rows]) * sizes.reshape(1, -1)  # constraints on z
    _, S, Vh = torch.linalg.svd(C, full_matrices=True)
    rank = int((S > 1e-9 * S.max()).sum())
    return Vh[rank:].T.contiguous()


def fit_pixels(masks: torch.Tensor, band_px: int, max_rays: int, generator: torch.Generator
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of the camera fit: each mask (T, H, W) grown by ``band_px``, at most
    ``max_rays`` per camera drawn at random. Returns flat pixel indices ``v * W + u`` (T, R),
    padded by repetition, and which of them count (T, R) bool."""
    grown = masks.float()[:, None]
    if band_px > 0:
        grown = F.max_pool2d(grown, 2 * band_px + 1, stride=1, padding=band_px)
    grown = grown[:, 0].reshape(masks.shape[0], -1).cpu() > 0
    picks = []
    for m in grown:
        idx = m.nonzero().squeeze(1)
        if idx.numel() > max_rays:
            idx = idx[torch.randperm(idx.numel(), generator=generator)[:max_rays]].sort().values
        picks.append(idx)
    R = max(1, max(p.numel() for p in picks))
    index = torch.zeros(len(picks), R, dtype=torch.long)
    valid = torch.zeros(len(picks), R, dtype=torch.bool)
    for i, p in enumerate(picks):
        if p.numel():
            index[i] = p[torch.arange(R) % p.numel()]
            valid[i, : p.numel()] = True
    return index, valid


def _pixel_uv(index: torch.Tensor, width: int, device) -> torch.Tensor:
    """Pixel-centre coordinates (T, R, 2) of flat indices (T, R)."""
    index = index.to(device)
    return torch.stack([index % width, index // width], -1).float() + 0.5


class CameraFit:
    """The camera-fit problem of one round: fixed densities (one per training camera, the one
    its pixels are compared with), the fit pixels and their values.

    ``residuals(theta)`` (N, C) and ``jacobian(theta)`` (N, C, 9) over the valid pixels, camera
    by camera; ``row_camera`` (N,) says which training camera each row belongs to.
    """

    def __init__(self, volumes: list[torch.Tensor], grid: VoxelGrid, cams: PinholeCamera,
                 pivot: torch.Tensor, images: torch.Tensor, index: torch.Tensor, valid: torch.Tensor,
                 step: float):
        self.volumes = [v.detach() for v in volumes]
        self.grid, self.cams, self.pivot, self.step = grid, cams, pivot, step
        device = self.volumes[0].device
        W = int(cams.width[0])
        self.uv = _pixel_uv(index, W, device)
        self.valid = valid.to(device)
        C = images.shape[1]
        flat = images.reshape(images.shape[0], C, -1).to(device)
        values = torch.gather(flat, 2, index.to(device)[:, None, :].expand(-1, C, -1))  # (T, C, R)
        self.target = values.permute(0, 2, 1)[self.valid]  # (N, C)
        T, R = index.shape
        self.row_camera = torch.arange(T, device=device)[:, None].expand(T, R)[self.valid]
        counts = self.valid.sum(1).tolist()
        self.rows = [slice(a - n, a) for a, n in zip(torch.tensor(counts).cumsum(0).tolist(), counts)]
        self.boxes = [support_box(grid, v.abs().sum(0).reshape(-1).nonzero().squeeze(1)) for v in self.volumes]

    def rays(self, theta: torch.Tensor) -> torch.Tensor:
        """Origins and directions (T, R, 6) of the fit pixels under ``theta`` (T, 9)."""
        origins, directions = pixel_rays(corrected_cameras(self.cams, theta, self.pivot), self.uv)
        return torch.cat([origins, directions], -1)

    def render(self, rays: torch.Tensor) -> torch.Tensor:
        """Line integrals (N, C) along the valid rays (N, 6), each camera's rows through its
        own density."""
        return torch.cat([
            integrate_dense(v, self.grid, Rays(rays[sl, :3], rays[sl, 3:]), self.step, box)
            for v, sl, box in zip(self.volumes, self.rows, self.boxes)
        ])

    def residuals(self, theta: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.render(self.rays(theta)[self.valid]) - self.target

    def jacobian(self, theta: torch.Tensor, active: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """(residuals (N, C), Jacobian (N, C, 9)): d pixel / d ray (one backward pass per
        channel) times d ray / d theta (analytic: :func:`ray_tangents`)."""
        theta = theta.detach()
        tangents = ray_tangents(self.cams, theta, self.pivot, self.uv, active).to(theta.dtype)  # (T, R, 6, 9)
        rays = self.rays(theta)[self.valid].detach().requires_grad_(True)
        with torch.enable_grad():
            pixels = self.render(rays)
            C = pixels.shape[1]
            d_ray = [torch.autograd.grad(pixels[:, c].sum(), rays, retain_graph=c < C - 1)[0]
                     for c in range(C)]
        J = torch.einsum("cnj,njp->ncp", torch.stack(d_ray), tangents[self.valid])
        return pixels.detach() - self.target, J


def camera_step(fit: CameraFit | JointFit, theta: torch.Tensor, sizes: torch.Tensor, basis: torch.Tensor,
                active: list[int], iterations: int) -> tuple[torch.Tensor, dict]:
    """Levenberg-Marquardt from ``theta`` (T, 9) on ``0.5 |r|^2 / s2 + 0.5 |z|^2`` over the
    gauge-fixed scaled corrections ``z = theta / sizes = basis @ psi`` (``s2``: the mean
    squared residual at the start). Returns the new theta and {rms_before, rms_after, iterations}."""
    T = theta.shape[0]
    s = sizes.reshape(-1)
    psi = basis.T @ (theta.double().cpu().reshape(-1) / s)

    def theta_of(p: torch.Tensor) -> torch.Tensor:
        return ((basis @ p) * s).reshape(T, N_PARAMS).to(theta)

    r, J = fit.jacobian(theta_of(psi), active)
    s2 = max(float((r.double() ** 2).mean()), 1e-30)
    rms_before = math.sqrt(s2)

    def objective(res: torch.Tensor, p: torch.Tensor) -> float:
        return 0.5 * float((res.double() ** 2).sum()) / s2 + 0.5 * float(p @ p)

    cost = objective(r, psi)
    mu, done, at_psi = 1e-3, 0, r  # at_psi: the residuals at psi, for rms_after
    for done in range(1, iterations + 1):
        interrupt.check()
        H = torch.zeros(T * N_PARAMS, T * N_PARAMS, dtype=torch.float64)
        g = torch.zeros(T * N_PARAMS, dtype=torch.float64)
        Jd, rd = J.double().cpu(), r.double().cpu()
        cam = fit.row_camera.cpu()
        for i in range(T):
            Ji = Jd[cam == i].reshape(-1, N_PARAMS)
            sl = slice(i * N_PARAMS, (i + 1) * N_PARAMS)
            H[sl, sl] = Ji.T @ Ji
            g[sl] = Ji.T @ rd[cam == i].reshape(-1)
        Hp = basis.T @ (s[:, None] * H * s[None, :]) @ basis / s2 + torch.eye(basis.shape[1], dtype=torch.float64)
        gp = basis.T @ (s * g) / s2 + psi
        improved = False
        for _ in range(8):
            delta = torch.linalg.solve(Hp + mu * torch.diag(torch.diagonal(Hp)), -gp)
            trial = psi + delta
            trial_res = fit.residuals(theta_of(trial))
            trial_cost = objective(trial_res, trial)
            if trial_cost < cost:
                improved = True
                break
            mu *= 10.0
        if not improved:
            break
        gain = (cost - trial_cost) / max(cost, 1e-30)
        psi, cost, mu, at_psi = trial, trial_cost, max(mu / 10.0, 1e-7), trial_res
        if gain < 1e-6 or done == iterations:
            break
        r, J = fit.jacobian(theta_of(psi), active)
    rms_after = math.sqrt(float((at_psi.double() ** 2).mean()))
    return theta_of(psi), {"rms_before": rms_before, "rms_after": rms_after, "iterations": done}


def with_cameras(cameras: PinholeCamera, index: list[int], replaced: PinholeCamera) -> PinholeCamera:
    """``cameras`` (B) with the cameras at ``index`` replaced by ``replaced`` (len(index))."""
    K4, E = cameras.intrinsics.clone(), cameras.extrinsics.clone()
    idx = torch.as_tensor(index, dtype=torch.long, device=K4.device)
    K4[idx] = replaced.intrinsics.detach().to(K4)
    E[idx] = replaced.extrinsics.detach().to(E)
    return PinholeCamera(K4, E, cameras.height.clone(), cameras.width.clone())


Solve = Callable[[list[int], PinholeCamera, torch.Tensor | None], torch.Tensor]


@dataclass
class CalibrationFrame:
    """One frame of the camera fit: ``images`` (B, C, H, W) and silhouettes ``masks`` (B, H, W)
    bool of every camera of the scene, and ``solve(views, cams, start)``: the density (C, nz,
    ny, nx) fitted to this frame's views ``views`` seen by the cameras ``cams`` (len(views)),
    from ``start`` (a density of the same box, the frame's previous one) with
    ``solve_iterations`` iterations, or from zero with ``first_iterations`` (``start`` None)."""

    images: torch.Tensor
    masks: torch.Tensor
    solve: Solve


class JointFit:
    """Several frames' :class:`CameraFit` as one problem: the same cameras and corrections,
    each frame's rows compared with its own densities; rows stacked frame after frame."""

    def __init__(self, fits: list[CameraFit]):
        self.fits = fits
        self.row_camera = torch.cat([f.row_camera for f in fits])

    def residuals(self, theta: torch.Tensor) -> torch.Tensor:
        return torch.cat([f.residuals(theta) for f in self.fits])

    def jacobian(self, theta: torch.Tensor, active: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        parts = [f.jacobian(theta, active) for f in self.fits]
        return torch.cat([r for r, _ in parts]), torch.cat([J for _, J in parts])


def refine(cameras: PinholeCamera, train: list[int], frames: list[CalibrationFrame], grid: VoxelGrid,
           options: RefineOptions, step: float = 0.5) -> Refinement:
    """Refine the training cameras ``train`` of ``cameras`` (B) against ``frames`` (one or
    more frames of the capture, see :class:`CalibrationFrame`). First each frame's density
    with the unrefined cameras (``initial_volume``: the first frame's), then ``options.rounds``
    times: the densities the cameras are fitted to (see ``fit_against``), one per frame, and
    one :func:`camera_step` over every frame's pixels (``max_rays`` per camera shared among
    the frames). Held-out cameras are never changed; with ``refine=none`` nothing is fitted."""
    if not frames:
        raise ValueError("refine: no frame to fit the cameras to")
    device = frames[0].images.device
    base = camera_subset(cameras, train)
    base = PinholeCamera(base.intrinsics.to(device), base.extrinsics.to(device),
                         base.height.to(device), base.width.to(device))
    T = len(train)
    pivot = 0.5 * (grid.lo(device) + grid.hi(device))
    theta = torch.zeros(T, N_PARAMS, device=device)
    active = options.active
    sizes = prior_sizes(base, pivot, options)
    basis = gauge_basis(base, pivot, sizes, active)
    generator = torch.Generator().manual_seed(int(options.seed))
    fitted_at_all = bool(active) and basis.shape[1] > 0
    progress = Progress("camera fit", 1 + (options.rounds if fitted_at_all else 0))
    initial = [frame.solve(list(train), base, None) for frame in frames]
    progress.step(f"the density of {len(frames)} frame(s) with the capture's cameras")
    history = []
    if not fitted_at_all:
        return Refinement(with_cameras(cameras, train, base), theta, initial[0], history)
    others = options.fit_against == "others" and T >= 3
    rays_per_frame = max(1, int(options.max_rays) // len(frames))
    latest = list(initial)  # each frame's latest density (fit_against=all): the next solve's start
    for r in range(options.rounds):
        current = corrected_cameras(base, theta, pivot)
        fits = []
        for k, (frame, first) in enumerate(zip(frames, initial)):
            interrupt.check()
            if others:
                rest = [[j for j in range(T) if j != i] for i in range(T)]
                volumes = [frame.solve([train[j] for j in js], camera_subset(current, js), None).detach()
                           for js in rest]
            else:
                latest[k] = first if r == 0 else frame.solve(list(train), current, latest[k]).detach()
                volumes = [latest[k]] * T
            index, valid = fit_pixels(frame.masks[train], options.band_px, rays_per_frame, generator)
            fits.append(CameraFit(volumes, grid, base, pivot, frame.images[train], index, valid, step))
        stepped, info = camera_step(JointFit(fits), theta, sizes, basis, active, options.iterations)
        record = {**info, "rays": int(sum(int(f.valid.sum()) for f in fits))}
        history.append(record)
        if r == 0 and round_gain(record) < options.min_gain:  # nothing to correct: stop here
            record.update(kept=True, stopped=f"round 1 lowered the residual by {100 * round_gain(record):.2f}%, "
                                             f"under calibration.min_gain {100 * options.min_gain:g}%")
            progress.step("nothing to correct: the capture's cameras kept")
            return Refinement(with_cameras(cameras, train, base), theta, initial[0], history)
        theta = stepped
        progress.step(f"round {r + 1}: cameras fitted")
    fitted = corrected_cameras(base, theta, pivot)
    if options.gauge == "similarity":
        fitted = align_similarity(fitted, base, pivot)
    return Refinement(with_cameras(cameras, train, fitted), theta.detach(), initial[0], history)


def correction_report(cameras: PinholeCamera, refined: PinholeCamera, grid: VoxelGrid) -> list[dict]:
    """Per camera of ``cameras`` / ``refined`` (same T), what the refinement changed, read off
    the cameras themselves (so a calibration read from a file is reported alike):
    ``rotation_deg`` (angle of the relative rotation), ``translation`` (camera centre shift,
    world units), ``focal_scale`` (fx after / before), ``principal_point_px`` [du, dv] and
    ``box_px``, the mean shift of the box corners' projections in pixels."""
    corners = grid.corners().to(cameras.extrinsics.device)
    before, _ = project_points(cameras, corners)
    after, _ = project_points(refined, corners)
    shift = (after - before).norm(dim=-1).mean(-1)
    moved = (camera_centers(refined) - camera_centers(cameras)).norm(dim=-1)
    M = cameras.extrinsics[:, :3, :3].double().transpose(1, 2) @ refined.extrinsics[:, :3, :3].double()
    axis = torch.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], -1)
    angle = torch.atan2(0.5 * axis.norm(dim=-1), 0.5 * (M.diagonal(dim1=1, dim2=2).sum(-1) - 1))
    K0, K1 = K_of(cameras).double().cpu(), K_of(refined).double().cpu()
    return [
        {"rotation_deg": math.degrees(float(angle[i])), "translation": float(moved[i]),
         "focal_scale": float(K1[i, 0, 0] / K0[i, 0, 0]), "principal_point_px": (K1[i, :2, 2] - K0[i, :2, 2]).tolist(),
         "box_px": float(shift[i])}
        for i in range(cameras.batch_size)
    ]
