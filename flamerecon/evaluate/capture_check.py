"""What to check first on a capture of one's own, before any solve: per camera its silhouette,
whether the box stands in front of it and holds its silhouette, and whether its silhouette
agrees with the visual hull carved by the other cameras (a wrong pose or focal length shows as
a low overlap); and one picture of all of it (``scripts/check_capture.py``, docs/own_capture.md).

A camera that does not see the box has its pose read in the other conventions a calibration
comes in (camera->world, OpenGL's axes, MATLAB's postmultiply rotation); the hint names the one
that brings the box into view. What it cannot see: an error the silhouettes do not show, such
as a principal point off by half a pixel or one (a 1-based one, as MATLAB's) at usual sizes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from flamerecon.geometry.cameras import camera_subset, project_points
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import visual_hull
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.operators.projector import render_image
from flamerecon.outputs.figures import montage, overlay_mask, to_display
from flamerecon.scenes import Scene

#: below this overlap of a camera's silhouette with the others' hull, its calibration is suspect
LOW_IOU = 0.5
#: above this share of a silhouette outside the box's outline, the box is too small
OUTSIDE_SHARE = 0.05
POSE_HINT = ("are its R and t world->camera (x_cam = R x_world + t)? A camera->world pose must be inverted, a "
             "MATLAB one (x_cam = x_world*R + t) only its R transposed (convert_capture.py does both)")
#: the conventions a pose may have been written in by mistake: (what it was, what to do, the
#: world->camera 4x4 it gives from the file's (4, 4) matrix M read as world->camera)
MISREAD = (
    ("camera->world (Blender, NeRF without their axes)", "invert it: R' = R^T, t' = -R^T t",
     torch.linalg.inv),
    ("camera->world with OpenGL's axes (y up, z backwards: NeRF, Blender)",
     "invert it and flip its y and z axes (scene=nerf reads these)",
     lambda M: torch.linalg.inv(M @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=M.dtype)))),
    ("MATLAB's postmultiply rotation (x_cam = x_world*R + t)",
     "transpose R only, t as it is (convert_capture.py matlab does it)",
     lambda M: torch.cat([torch.cat([M[:3, :3].T, M[:3, 3:]], 1), M[3:]], 0)),
)
_EDGES = [(p, q) for p in range(8) for q in range(p + 1, 8) if (p ^ q).bit_count() == 1]


@dataclass
class CameraCheck:
    """One camera's check: ``silhouette`` share of the image, share of it ``outside_box`` (its
    projected outline), ``hull_iou`` of it with the hull the other cameras carve, the box
    corners ``behind`` it, and ``problems``: what to do, one line each."""

    name: str
    silhouette: float
    outside_box: float
    hull_iou: float
    behind: int
    problems: list[str] = field(default_factory=list)


def box_corners(bbox_min, bbox_max) -> torch.Tensor:
    """The box's 8 corners (8, 3), corner p has bit 0/1/2 set for the max of x/y/z."""
    lo, hi = torch.as_tensor(bbox_min, dtype=torch.float32), torch.as_tensor(bbox_max, dtype=torch.float32)
    return torch.stack([torch.where(torch.tensor([(p >> a) & 1 for a in range(3)], dtype=torch.bool), hi, lo)
                        for p in range(8)])


def check_capture(scene: Scene, silhouette: dict, bbox=None, resolution: int = 48
                  ) -> tuple[list[CameraCheck], torch.Tensor, torch.Tensor]:
    """Check every camera of ``scene`` (silhouettes by ``silhouette``, the options of
    ``silhouette:``, unless the scene has masks; ``bbox`` [min, max], default the scene's, which
    the loader may have estimated from the silhouettes itself: then a silhouette outside it is
    put down to that estimate, not to a box the user gave): the checks, the silhouettes
    (B, H, W) and each camera's footprint of the others' hull (B, H, W)."""
    masks = scene.masks if scene.masks is not None else silhouettes(scene.images, **silhouette)
    lo, hi = (bbox[0], bbox[1]) if bbox is not None else (scene.bbox_min, scene.bbox_max)
    estimated = bbox is None and scene.meta.get("bbox_source") == "silhouette cones"
    grid = VoxelGrid.from_box(tuple(map(float, lo)), tuple(map(float, hi)), resolution)
    uv, depth = project_points(scene.cameras, box_corners(lo, hi))
    H, W = scene.image_size
    checks, footprints = [], []
    for v, name in enumerate(scene.views):
        others = [o for o in range(scene.num_views) if o != v]
        hull = visual_hull(grid, camera_subset(scene.cameras, others), masks[others], 0) if others else (
            torch.ones(grid.shape, dtype=torch.bool))
        # pixels whose ray runs at least half a cell through the hull
        chord = render_image(hull[None].float(), grid, camera_subset(scene.cameras, [v]))[0, 0]
        footprint = chord > 0.5 * float(grid.voxel_size().min())
        footprints.append(footprint)
        mask = masks[v]
        outline = np.zeros((H, W), np.uint8)
        if bool((depth[v] > 0).all()):
            cv2.fillConvexPoly(outline, cv2.convexHull(uv[v].numpy().round().astype(np.int32)), 1)
        area = int(mask.sum())
        union = int((mask | footprint).sum())
        check = CameraCheck(name, area / (H * W), float((mask.numpy() & (outline == 0)).sum() / max(area, 1)),
                            float((mask & footprint).sum()) / union if union else 0.0, int((depth[v] <= 0).sum()))
        sees_box = bool(outline[: H, : W].any())
        inside = 0.0 if check.behind or not sees_box else 1.0 - check.outside_box
        misread = misreading(scene, v, lo, hi, mask, inside) if area and (
            inside < 1.0 - OUTSIDE_SHARE or check.hull_iou < LOW_IOU) else None
        if check.behind or not sees_box:
            seen = (f"{check.behind} of the box's corners are behind it" if check.behind
                    else "it does not see the box")
            check.problems.append(f"{seen}: {misread or POSE_HINT}"
                                  + ("" if check.behind or misread else "; or the box (grid.bbox) is elsewhere"))
        if area == 0:
            check.problems.append("its silhouette is empty: lower silhouette.threshold, or check the image")
        elif check.outside_box > OUTSIDE_SHARE and sees_box and not check.behind:
            share = f"{100 * check.outside_box:.0f}% of its silhouette lies outside the box's outline"
            check.problems.append(
                f"{share}: {misread}" if misread else
                f"{share}: the box the loader estimated (from scene.silhouette's masks) is narrower than the "
                "silhouettes the fit uses (silhouette:); give the box (bbox in the calibration file, or "
                "grid.bbox), or set scene.silhouette as silhouette" if estimated else
                f"{share}: enlarge the box (grid.bbox, or bbox in the calibration file)")
        if area and check.hull_iou < LOW_IOU:
            check.problems.append(f"its silhouette and the hull of the other cameras overlap by IoU "
                                  f"{check.hull_iou:.2f}: check its pose and focal length (or theirs)")
        checks.append(check)
    return checks, masks, torch.stack(footprints)


def misreading(scene: Scene, view: int, lo, hi, mask: torch.Tensor, inside: float) -> str | None:
    """What to do about camera ``view``'s pose when it is one of :data:`MISREAD`'s: the
    misreading that, undone, puts the box in front of the camera and at least 80% of its
    silhouette ``mask`` (H, W) inside the box's outline, a quarter more than ``inside`` (the
    share as given); None when none does."""
    H, W = scene.image_size
    corners = box_corners(lo, hi).double()
    given = scene.cameras.extrinsics[view].double()
    K = scene.cameras.intrinsics[view, :3, :3].double()
    best, best_share = None, max(0.8, inside + 0.25)
    for what, fix, read in MISREAD:
        w2c = read(given)
        cam = corners @ w2c[:3, :3].T + w2c[:3, 3]
        if not bool((cam[:, 2] > 0).all()):
            continue
        uv = (cam @ K.T)[:, :2] / cam[:, 2:]
        outline = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(outline, cv2.convexHull(uv.numpy().round().astype(np.int32)), 1)
        share = float((mask.numpy() & (outline > 0)).sum() / max(int(mask.sum()), 1))
        if share >= best_share:
            best, best_share = (what, fix), share
    if best is None:
        return None
    return (f"its pose looks written as {best[0]}: read that way, {100 * best_share:.0f}% of its silhouette falls "
            f"inside the box; {best[1]} (OpenCV's R and t: x_cam = R x_world + t)")


def check_figure(scene: Scene, checks: list[CameraCheck], masks: torch.Tensor, footprints: torch.Tensor,
                 bbox=None, width: int = 320, columns: int = 4) -> np.ndarray:
    """Each camera's image (scaled to ``width`` px) with its silhouette tinted green, the others'
    hull outlined cyan and the box's edges yellow, labelled with its name and IoU: a montage
    (H, W, 3) uint8, with a legend line below."""
    lo, hi = (bbox[0], bbox[1]) if bbox is not None else (scene.bbox_min, scene.bbox_max)
    uv, depth = project_points(scene.cameras, box_corners(lo, hi))
    H, W = scene.image_size
    scale = width / W
    size = (width, round(H * scale))
    tiles = []
    for v, check in enumerate(checks):
        image = (to_display(scene.recorded_view(v)).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
        image = cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)
        mask = cv2.resize(masks[v].numpy().astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        tile = overlay_mask(image, mask, (0, 255, 0), 0.3)
        hull = cv2.resize(footprints[v].numpy().astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(hull, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(tile, contours, -1, (0, 220, 255), 1)
        if bool((depth[v] > 0).all()):
            points = (uv[v].numpy() * scale).round().astype(int)
            for p, q in _EDGES:
                cv2.line(tile, tuple(map(int, points[p])), tuple(map(int, points[q])), (255, 220, 0), 1, cv2.LINE_AA)
        if check.problems:
            cv2.rectangle(tile, (0, 0), (size[0] - 1, size[1] - 1), (255, 40, 40), 2)
        tiles.append(tile)
    sheet = montage(tiles, min(columns, len(tiles)),
                    [f"{c.name}  IoU {c.hull_iou:.2f}" + ("  CHECK" if c.problems else "") for c in checks])
    legend = np.zeros((22, sheet.shape[1], 3), np.uint8)
    cv2.putText(legend, "green: silhouette   cyan: hull of the other cameras   yellow: the box   red frame: a "
                "problem (printed)", (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([sheet, legend])
