"""How well each camera's pose is known, measured from the data by leave-one-camera-out
consistency. A camera's *pose offset* is the correction ``theta`` (:mod:`flamerecon.fit.refine_cameras`:
rotation about the box centre, translation; with ``pose+intrinsics`` also focal scale and
principal point) that fits its images to the density solved from the *other* training cameras
(a held-out camera: from all of them), Levenberg-Marquardt from its own pose; the pose itself
is not changed. With the offset come the full-frame mean squared errors of its render before
and after the offset (``before``, ``after``), the render's mean squared change when moved by
plus and minus the offset (``change``), and the fit's curvature at the offset (Gauss-Newton
``s2 (J^T J)^-1``, ``s2`` the mean squared residual there). The ``share`` ``(before - after) /
change`` (in [0, 1]) is how much of that change the images confirm, the rest being the
density's own freedom along poorly determined directions (an orbit about a plume looks alike
from nearby angles).

A camera's pose uncertainty is then, by the protocol: a camera whose pose the camera fit
refined has the curvature of its offset's fit (the data pinned its pose; the offset itself
measures the density of the fewer other cameras as much as the camera); any other camera (a
held-out one, under the strict protocol) has its offset, to its share (nothing refined it: it is
as far off as its images say). Why (against the offsets of the fitted cameras, and the prior
that the fit's corrections of the training cameras imply) and how it predicts held-out errors:
docs/results.md, "Cameras in the confidence". A capture's offsets are measured once, on its
calibration frames, and kept in its calibration file (:mod:`flamerecon.fit.capture_calibration`):
a held-out camera's images of those frames (never of a scored frame) measure its offset, as
they would calibrate a rig; its pose stays as the capture's calibration gives it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.liegroup import So3

from flamerecon.errors import FlameReconError
from flamerecon.evaluate.pose_spread import PoseSpread
from flamerecon.fit.build import build, make_problem, scene_grid, scene_masks
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.refine_cameras import (
    N_PARAMS,
    CalibrationFrame,
    CameraFit,
    JointFit,
    RefineOptions,
    camera_step,
    corrected_cameras,
    fit_pixels,
    prior_sizes,
    with_cameras,
)
from flamerecon.geometry.cameras import K_of, camera_subset, cameras_to, project_points
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.progress import Progress
from flamerecon.scenes import Scene

#: Levenberg-Marquardt iterations of an offset's fit
ITERATIONS = 10
#: solver iterations of a density an offset is fitted against outside a camera fit (the offset
#: needs the density's structure, not its last digits, as the camera fit's first solves do)
SOLVE_ITERATIONS = 30


@dataclass
class PoseOffset:
    """One camera's pose offset ``theta`` (9,) float64 and its figures on the frames it was
    measured on (mean squared errors, full frame, images in [0, 1]): ``before`` / ``after``
    the offset, the render's ``change`` when moved by plus and minus it; ``source``: how;
    ``curvature`` (9, 9) float64: the covariance of ``theta`` the fit's curvature gives."""

    theta: torch.Tensor
    before: float
    after: float
    change: float
    source: str
    curvature: torch.Tensor

    @property
    def share(self) -> float:
        """The part of the render's change that the images confirmed, in [0, 1]."""
        return min(1.0, max(0.0, (self.before - self.after) / self.change)) if self.change > 0 else 0.0

    @property
    def lost_db(self) -> float:
        """The PSNR (dB) the offset gains its images: what the camera's pose error cost them."""
        return 10.0 * math.log10(self.before / self.after) if self.before > self.after > 0 else 0.0

    def record(self) -> dict:
        return {"theta": self.theta.tolist(), "before": self.before, "after": self.after, "change": self.change,
                "source": self.source, "curvature": self.curvature.tolist()}

    @classmethod
    def from_record(cls, record: dict) -> PoseOffset:
        return cls(torch.tensor(record["theta"], dtype=torch.float64), float(record["before"]),
                   float(record["after"]), float(record["change"]), str(record["source"]),
                   torch.tensor(record["curvature"], dtype=torch.float64))


def mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.clamp(0, 1).double() - b.double()).pow(2).mean())


def measure_offset(volumes: Sequence[torch.Tensor], grid: VoxelGrid, cam: PinholeCamera,
                   images: Sequence[torch.Tensor], masks: Sequence[torch.Tensor], step: float, pivot: torch.Tensor,
                   options: RefineOptions, source: str) -> PoseOffset:
    """The :class:`PoseOffset` of the one camera ``cam`` whose images ``images`` (C, H, W each,
    silhouettes ``masks`` (H, W)) are compared with the densities ``volumes`` (C, nz, ny, nx, one
    per frame): ``options.active`` parameters, its pixels as the camera fit draws them
    (``band_px``, ``max_rays`` shared among the frames, ``seed``), prior sizes as it has them."""
    generator = torch.Generator().manual_seed(int(options.seed))
    per_frame = max(1, int(options.max_rays) // len(volumes))
    fits = []
    for volume, image, mask in zip(volumes, images, masks):
        index, valid = fit_pixels(mask[None], options.band_px, per_frame, generator)
        fits.append(CameraFit([volume], grid, cam, pivot, image[None], index, valid, step))
    active = options.active or list(range(6))
    basis = torch.eye(N_PARAMS, dtype=torch.float64)[:, active]  # one camera: no gauge to hold
    joint = JointFit(fits)
    theta, _ = camera_step(joint, torch.zeros(1, N_PARAMS, device=volumes[0].device),
                           prior_sizes(cam, pivot, options), basis, active, ITERATIONS)
    residuals, J = joint.jacobian(theta, active)
    J = J.double().reshape(-1, N_PARAMS)[:, active].cpu()
    curvature = torch.zeros(N_PARAMS, N_PARAMS, dtype=torch.float64)
    where = torch.tensor(active)
    curvature[where[:, None], where[None, :]] = float(residuals.double().pow(2).mean()) * torch.linalg.pinv(J.T @ J)
    before = after = change = 0.0
    for volume, image in zip(volumes, images):
        base = render_image(volume, grid, cam, step)[0]
        plus, minus = (render_image(volume, grid, corrected_cameras(cam, sign * theta, pivot), step)[0]
                       for sign in (1, -1))
        before += mse(base, image) / len(volumes)
        after += mse(plus, image) / len(volumes)
        change += 0.5 * (mse(plus, base.clamp(0, 1)) + mse(minus, base.clamp(0, 1))) / len(volumes)
    return PoseOffset(theta[0].detach().double().cpu(), before, after, change, source, curvature)


def capture_offsets(frames: Sequence[CalibrationFrame], cameras: PinholeCamera, train: list[int], grid: VoxelGrid,
                    options: RefineOptions, step: float, frame_numbers: Sequence[int]) -> dict[int, PoseOffset]:
    """{camera index: :class:`PoseOffset`} for every camera of ``cameras`` (B, the training
    ones as fitted) on ``frames``: a training camera against the densities of the others, any
    other camera against the densities of every training camera (``frame.solve`` each, from
    zero)."""
    device = frames[0].images.device
    pivot = 0.5 * (grid.lo(device) + grid.hi(device))
    cams = PinholeCamera(*(t.to(device) for t in (cameras.intrinsics, cameras.extrinsics, cameras.height,
                                                   cameras.width)))
    groups = {j: [i for i in train if i != j] for j in train} if len(train) > 1 else {}
    held = [v for v in range(cams.batch_size) if v not in train]
    where = f"frames {list(frame_numbers)}"
    progress = Progress("cameras' pose offsets", len(groups) + (1 if held else 0), "step")
    found = {}
    for j, others in [*groups.items(), *([(None, list(train))] if held else [])]:
        volumes = [f.solve(others, camera_subset(cams, others), None).detach() for f in frames]
        for v in ([j] if j is not None else held):
            what = "the other training cameras'" if j is not None else "the training cameras'"
            found[v] = measure_offset(volumes, grid, camera_subset(cams, [v]), [f.images[v] for f in frames],
                                      [f.masks[v] for f in frames], step, pivot, options,
                                      f"{what} density on {where}")
        progress.step("" if j is None else f"without camera {j}")
    return found


def spread(cameras: PinholeCamera, views: list[str], offsets: dict[str, PoseOffset], grid: VoxelGrid,
           fitted: set[str] | frozenset[str] = frozenset()) -> PoseSpread:
    """The :class:`~flamerecon.evaluate.pose_spread.PoseSpread` of the cameras named in
    ``offsets`` among ``cameras`` (B, named ``views``), about the box centre of ``grid``: a
    camera in ``fitted`` (its pose refined by the camera fit) moved by plus and minus the
    principal axis of its offset's curvature, with share 1; any other by its offset, to its
    share (the module's docstring)."""
    names = [v for v in views if v in offsets]
    index = [views.index(v) for v in names]
    pivot = 0.5 * (grid.lo() + grid.hi())
    cams = cameras_to(camera_subset(cameras, index), "cpu")
    steps, shares = [], []
    for v in names:
        if v in fitted:
            values, vectors = torch.linalg.eigh(offsets[v].curvature)
            steps.append(vectors[:, -1] * values[-1].clamp_min(0).sqrt())
            shares.append(1.0)
        else:
            steps.append(offsets[v].theta)
            shares.append(offsets[v].share)
    step = torch.stack(steps) if names else torch.zeros(0, N_PARAMS, dtype=torch.float64)
    share = torch.tensor(shares, dtype=torch.float64)
    moved = [corrected_cameras(cams, sign * step.float(), pivot) for sign in (1, -1)]
    corners = grid.corners()
    at, _ = project_points(cams, corners)
    shifts = torch.stack([(project_points(m, corners)[0] - at).double().norm(dim=-1).pow(2).mean(-1)
                          for m in moved]).mean(0)
    sigma = torch.stack([offsets[v].curvature[:3, :3].trace().clamp_min(0).sqrt() if v in fitted
                         else offsets[v].theta[:3].norm() * offsets[v].share ** 0.5 for v in names]) if names \
        else torch.zeros(0, dtype=torch.float64)
    return PoseSpread(names, torch.stack([K_of(m) for m in moved], 1), torch.stack([m.extrinsics for m in moved], 1),
                      share.float(), torch.rad2deg(sigma).float(), (shifts.sqrt() * share.sqrt()).float(),
                      torch.tensor([offsets[v].lost_db for v in names], dtype=torch.float32),
                      [("the curvature of its fit to " if v in fitted else "its offset to ") + offsets[v].source
                       for v in names])


def scene_offsets(scene: Scene, options: ReconstructionOptions, device: torch.device | str = "cpu"
                  ) -> dict[str, PoseOffset]:
    """{name: :class:`PoseOffset`} of every camera of ``scene`` (its own cameras, as its
    calibration gives them) against the density the others give on its frame (a plain solve of
    ``options``' solver on its grid, at most :data:`SOLVE_ITERATIONS` iterations, no weight
    selection or debiasing): which camera's calibration the others disagree with, before any
    camera fit."""
    device = torch.device(device)
    grid = scene_grid(options.grid, scene)
    images = scene.images.to(device)
    if "max_iters" in options.solver.params:
        options = options.replace(solver=options.solver.with_values(
            max_iters=min(int(options.solver.params["max_iters"]), SOLVE_ITERATIONS)))

    def solve(views: list[int], cams: PinholeCamera, start: torch.Tensor | None) -> torch.Tensor:
        fold = options.replace(holdout=tuple(n for i, n in enumerate(scene.views) if i not in views))
        setup = build(replace(scene, cameras=with_cameras(scene.cameras, views, cams)), fold, device, grid)
        problem, solver, _ = make_problem(fold.solver, setup)
        return setup.volume(solver.solve(problem).x)

    frame = CalibrationFrame(images, scene_masks(scene, images, options), solve)
    found = capture_offsets([frame], scene.cameras, list(range(scene.num_views)), grid,
                            replace(options.calibration, refine="pose"), float(options.projector.step),
                            [scene.meta.get("frame", 0)])
    return {scene.views[v]: offset for v, offset in found.items()}


def pose_report(scene: Scene, options: ReconstructionOptions) -> list[str]:
    """Lines that say each camera's pose uncertainty (:func:`scene_offsets`) and the camera
    least certain; one line saying why when it cannot be measured."""
    try:
        offsets = scene_offsets(scene, options, options.device if options.device != "auto" else "cpu")
    except FlameReconError as err:
        return [f"pose uncertainty: not measured ({err})"]
    grid = scene_grid(options.grid, scene)
    found = spread(scene.cameras, list(scene.views), offsets, grid)
    lines = [("pose uncertainty (each camera fitted to the density of the others, this frame; one sigma, and the "
             "PSNR its pose error costs its image):"),
             f"{'camera':10} {'degrees':>8} {'px at box':>10} {'costs dB':>9}"]
    lines += [f"{name:10} {r['pose_sigma_deg']:8.3f} {r['pose_sigma_box_px']:10.2f} {r['pose_lost_db']:9.2f}"
              for name, r in found.records().items()]
    worst = found.limiting()
    if worst is not None:
        lines.append(f"least certain: {worst} (its pose error costs its image "
                     f"{float(found.lost_db[found.views.index(worst)]):.2f} dB); a camera fit "
                     "(calibration.refine=pose) corrects the training cameras")
    return lines


def offsets_of(calibration: dict | None) -> dict[str, PoseOffset]:
    """The pose offsets, by camera name, that a reconstruction's calibration record holds
    (``poses``, :func:`~flamerecon.fit.reconstruct.calibrated_scene`); {} without."""
    return {name: PoseOffset.from_record(r) for name, r in ((calibration or {}).get("poses") or {}).items()}


def corrections_between(calibrated: PinholeCamera, refined: PinholeCamera, pivot: torch.Tensor) -> torch.Tensor:
    """The corrections ``theta`` (T, 9) float64 that turn ``calibrated`` (T) into ``refined``
    (T) about ``pivot`` (3,) (:func:`~flamerecon.fit.refine_cameras.corrected_cameras`), read off
    the cameras themselves."""
    E0, E1 = calibrated.extrinsics.double().cpu(), refined.extrinsics.double().cpu()
    G = torch.linalg.solve(E1, E0)  # E1 = E0 G^-1: G = E1^-1 E0, the world motion x -> R x + t
    R, t = G[:, :3, :3], G[:, :3, 3]
    p = pivot.double().cpu()
    theta = torch.zeros(calibrated.batch_size, N_PARAMS, dtype=torch.float64)
    theta[:, :3] = So3.from_matrix(R).log()
    theta[:, 3:6] = t - p + (R @ p[:, None]).squeeze(-1)
    K0, K1 = K_of(calibrated).double().cpu(), K_of(refined).double().cpu()
    theta[:, 6] = torch.log(K1[:, 0, 0] / K0[:, 0, 0])
    theta[:, 7:9] = K1[:, :2, 2] - K0[:, :2, 2]
    return theta


def rotation_deg(theta: torch.Tensor) -> torch.Tensor:
    """(T,) the rotation angle in degrees of corrections ``theta`` (T, 9)."""
    return torch.rad2deg(theta[:, :3].norm(dim=-1))

