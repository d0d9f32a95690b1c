"""Results that look like runs but mean little, said as warnings: an empty, near-empty or
non-finite density, saturated views, float images outside [0, 1], an all-black held-out view, a
held-out PSNR below the all-black floor; a geometry that cannot constrain the density (one
training camera, cameras at one pose or on one axis or inside the box, two poses alike with
different images, a held-out camera at a training camera's pose, an absurd skew or principal
point, a view narrower than a voxel, a ray step that skips cells, a grid too coarse to hold a
shape); volume scores that say nothing (a tiny grid, a density no closer to the truth than
zero); a camera fit that could fit nothing. Each warning is
``{"code", "message"}``; the message names the setting to change. Each rule's threshold is a
constant here (``tests/test_result_warnings.py`` tries both sides of it). The run (metrics.json's
``warnings``, the log, the summary's block), ``scripts/evaluate.py`` and ``fr.score`` all take
them from :func:`result_warnings`."""

from __future__ import annotations

import math

import torch

from flamerecon.geometry.cameras import K_of, camera_centers

#: share of a view's pixels at the recorded maximum (1.0: 255 in 8 bits, 65535 in 16) from
#: which the view is called saturated
SATURATED_SHARE = 0.01
#: a density whose training renders score within this of an all-black image (dB, mean over
#: the training views) predicts nothing
EMPTY_GAIN_DB = 0.01
#: a captured view whose brightest value is at most this (one 8-bit step) is all black
BLACK_MAX = 1 / 255
#: metrics.json's ``psnr_undefined`` of a view whose PSNRs are undefined (null)
BLACK_VIEW = "the captured view is all black"
#: a density whose training renders gain less than this over an all-black image (dB, mean over
#: the training views) explains almost nothing of them (the empty rule takes the gains below
#: :data:`EMPTY_GAIN_DB`)
NEAR_EMPTY_GAIN_DB = 1.0
#: training cameras below this leave the depth along their rays unconstrained
MIN_TRAIN_CAMERAS = 2
#: training camera centres closer together than this share of their distance to the box centre
#: stand at one pose
ONE_POSE_SPREAD = 0.01
#: training viewing directions (camera to box centre) within this many degrees of one line (either
#: way along it) look along one axis: they constrain nothing across it
ONE_AXIS_DEG = 5.0
#: two cameras closer than this share of the box diagonal, their rotations within
#: :data:`SAME_ROTATION_DEG`, stand at the same pose
SAME_POSE_SHARE = 1e-3
SAME_ROTATION_DEG = 0.5
#: two views at one pose whose images differ by more than this (mean absolute, [0, 1] units)
#: contradict each other
DIFFERENT_IMAGES = 1 / 255
#: a skew (K[0, 1]) above this share of the focal length is no lens's
MAX_SKEW = 0.1
#: a ray step (projector.step) above this many voxels skips cells between its samples
MAX_STEP_VOXELS = 1.0
#: a grid with fewer cells than this along an axis makes the volume scores (support IoU) coarse
MIN_GRID_CELLS = 8
#: a density at least this far from the truth (relative L2) is no closer to it than zero is
NO_CLOSER_THAN_ZERO = 1.0
#: a grid with fewer cells than this along an axis holds no shape along it (1x1x1: one value)
MIN_SHAPE_CELLS = 4
#: a view whose whole image spans less than this many voxels at the box centre (its field of
#: view narrower than a voxel) sees one value of the density, nothing of its shape
MIN_VIEW_VOXELS = 1.0


def warning(code: str, message: str) -> dict[str, str]:
    return {"code": code, "message": message}


def is_black(image: torch.Tensor) -> bool:
    """Whether a captured view (C, H, W) is all black (:data:`BLACK_MAX`)."""
    return image.numel() == 0 or float(image.max()) <= BLACK_MAX


def image_warnings(scene, views: list[int]) -> list[dict]:
    """Saturated views and values outside [0, 1] (float images), as the cameras recorded them."""
    out = []
    for v in views:
        img, name = scene.recorded_view(v), scene.views[v]
        outside = int(((img < 0) | (img > 1)).sum())
        if outside:
            out.append(warning("image_range", (
                f"view '{name}': {outside} pixel values outside [0, 1] (min {float(img.min()):.3g}, max "
                f"{float(img.max()):.3g}); float images must hold values in [0, 1]: rescale the files, the fit "
                "takes the values as given")))
        share = float((img == 1.0).any(0).float().mean())
        if share >= SATURATED_SHARE:
            out.append(warning("saturated", (
                f"view '{name}': {share:.1%} of its pixels are at the maximum value (1.0, 255 or 65535): the "
                "flame is clipped there and the density will miss its brightest parts; capture with a shorter "
                "exposure, or hold the view out (holdout=)")))
    return out


def score_warnings(heldout: dict[str, dict[str, float]]) -> list[dict]:
    """All-black held-out views (their PSNRs undefined) and held-out PSNRs below the all-black
    floor, from metrics.json's ``heldout`` table."""
    out = []
    for name, s in heldout.items():
        if "psnr_undefined" in s:
            out.append(warning("black_view", (
                f"held-out view '{name}' is all black: its PSNRs are undefined (null in metrics.json); hold "
                "out a view that shows the flame (holdout=)")))
        elif math.isfinite(s["psnr"]) and math.isfinite(s["psnr_black"]) and s["psnr"] < s["psnr_black"]:
            out.append(warning("below_black", (
                f"held-out view '{name}': PSNR {s['psnr']:.2f} dB is below the all-black image's "
                f"{s['psnr_black']:.2f} dB: the render is worse than predicting black; check that camera's "
                "calibration (calibration.refine) and exposure")))
    return out


def empty_density(volume: torch.Tensor, train: dict[str, dict[str, float]], l1: float,
                  l1_rel: float | None) -> list[dict]:
    """The density predicts nothing (every voxel zero, or training renders that score as black
    does, :data:`EMPTY_GAIN_DB`), with the setting that emptied it: ``l1`` the absolute L1
    weight solved with, ``l1_rel`` the relative one it came from (None for an absolute one)."""
    bad = int((~torch.isfinite(volume.detach())).sum()) if volume.numel() else 0
    if bad:
        return [warning("nonfinite_density", (
            f"the density holds {bad} NaN/Inf values, so its scores mean nothing: a damaged density file, or a "
            "solve that diverged without its guard (checkpoint.divergence_factor); rerun it, or try a smaller step "
            "(solver.lr) or solver=fista"))]
    peak = float(volume.detach().abs().max()) if volume.numel() else 0.0
    gain = training_gain(train)
    if peak > 0 and abs(gain) >= EMPTY_GAIN_DB:
        return near_empty(volume, gain, l1, l1_rel)
    if l1_rel is not None and l1_rel >= 1:
        advice = (f"solver.l1_rel={l1_rel:g} is at or above 1, where the L1 weight reaches lambda_max = max(A^T b) "
                  f"= {l1 / l1_rel:.3g} and zero is the best density: use a smaller solver.l1_rel (the presets "
                  "use 0.001-0.1)")
    elif l1 > 0:
        which = f"solver.l1_rel={l1_rel:g}" if l1_rel is not None else f"solver.l1={l1:g}"
        advice = (f"{which} (L1 weight {l1:.3g}) may be too strong: lower it; or a first-order solver diverged "
                  "without its guard firing: try a smaller step (solver.lr) or solver=fista")
    else:
        advice = ("no L1 penalty is set, so the solver likely diverged without its guard firing: try a smaller "
                  "step (solver.lr) or solver=fista")
    state = "every voxel is zero" if peak == 0 else f"peak {peak:.3g}"
    return [warning("empty_density", (
        f"the density is empty ({state}; the training renders score {gain:+.3f} dB against an all-black image), so "
        f"its scores are the black image's: {advice}"))]


def training_gain(train: dict[str, dict[str, float]]) -> float:
    """The mean over training views of their PSNR above the all-black image's (dB; 0 for none)."""
    gains = [s["psnr"] - s["psnr_black"] for s in train.values()
             if s.get("psnr") is not None and s.get("psnr_black") is not None
             and math.isfinite(s["psnr"]) and math.isfinite(s["psnr_black"])]
    return sum(gains) / len(gains) if gains else 0.0


def near_empty(volume: torch.Tensor, gain: float, l1: float, l1_rel: float | None) -> list[dict]:
    """A density not empty but explaining almost nothing (:data:`NEAR_EMPTY_GAIN_DB`)."""
    if not 0 <= gain < NEAR_EMPTY_GAIN_DB:  # below 0: a bad fit, not an empty one (below_black says so)
        return []
    nonzero = int((volume.detach() > 0).any(0).sum())
    which = f"solver.l1_rel={l1_rel:g}" if l1_rel is not None else f"solver.l1={l1:g}"
    return [warning("near_empty", (
        f"the density is all but empty ({nonzero} of {volume[0].numel()} voxels nonzero; the training renders "
        f"score only {gain:+.2f} dB against an all-black image): {which} is likely too strong, lower it (the "
        "presets use 0.001-0.1)"))]


def camera_geometry(scene, train: list[int], holdout: list[int], bbox: tuple | None = None) -> list[dict]:
    """Cameras that cannot constrain the density, or whose scores mean little: fewer than
    :data:`MIN_TRAIN_CAMERAS` training cameras, training cameras at one pose
    (:data:`ONE_POSE_SPREAD`) or looking along one axis (:data:`ONE_AXIS_DEG`), a camera inside
    the box ``bbox`` (the scene's by default), two training views at one pose with different
    images, a held-out camera at a training camera's pose, an absurd skew or principal point."""
    out = []
    cams = scene.cameras
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in (bbox or (scene.bbox_min, scene.bbox_max)))
    centre, diagonal = (lo + hi) / 2, float((hi - lo).norm())
    eyes = camera_centers(cams).double()
    if len(train) < MIN_TRAIN_CAMERAS:
        out.append(warning("one_camera", (
            f"{len(train)} training camera: its rays fix the density's image but not where along them it lies, so "
            "a high training PSNR says nothing of the volume; train on several cameras (holdout= fewer)")))
    elif _spread(eyes[train], centre) < ONE_POSE_SPREAD:
        out.append(warning("one_pose", (
            f"the {len(train)} training cameras stand at one pose (their centres within "
            f"{ONE_POSE_SPREAD:.0%} of their distance to the box): they see one view of the density, "
            "nothing of its depth; check the calibration's poses")))
    elif _axis_spread_deg(eyes[train], centre) < ONE_AXIS_DEG:
        out.append(warning("one_axis", (
            f"the {len(train)} training cameras look along one axis (within {ONE_AXIS_DEG:g} deg): the density "
            "is unconstrained across it; add cameras from other directions, or check their poses")))
    inside = [scene.views[v] for v in range(len(scene.views)) if bool(((eyes[v] > lo) & (eyes[v] < hi)).all())]
    if inside:
        out.append(warning("camera_inside_box", (
            f"camera(s) {inside} stand inside the reconstruction box: the density behind them is invisible to them; "
            "set grid.bbox (or scene.bbox) around the flame only, or check their poses")))
    R = cams.extrinsics[:, :3, :3].double()
    for a, i in enumerate(train):
        for j in train[a + 1:]:
            if _same_pose(eyes, R, i, j, diagonal) and _image_difference(scene, i, j) > DIFFERENT_IMAGES:
                out.append(warning("duplicate_pose", (
                    f"views '{scene.views[i]}' and '{scene.views[j]}' have one pose but different images: the fit "
                    "averages two pictures of one ray set; check their calibration (one of them is likely another "
                    "camera's)")))
    for h in holdout:
        twin = next((t for t in train if _same_pose(eyes, R, h, t, diagonal)), None)
        if twin is not None:
            out.append(warning("heldout_at_training_pose", (
                f"held-out view '{scene.views[h]}' stands at training view '{scene.views[twin]}''s pose: its score is "
                "no novel view's; hold out a camera at a pose of its own")))
    K = K_of(cams).double()
    H, W = scene.image_size
    for v, name in enumerate(scene.views):
        fx, skew, cx, cy = float(K[v, 0, 0]), float(K[v, 0, 1]), float(K[v, 0, 2]), float(K[v, 1, 2])
        if abs(skew) > MAX_SKEW * fx:
            out.append(warning("skew", (
                f"view '{name}': K's skew {skew:.4g} is {abs(skew) / fx:.0%} of its focal length (no lens has one "
                "that large): check the calibration file's K")))
        if not (0 <= cx <= W and 0 <= cy <= H):
            out.append(warning("principal_point", (
                f"view '{name}': the principal point ({cx:.1f}, {cy:.1f}) px lies outside the {W}x{H} image: check "
                "the calibration file's K (cx, cy in pixels of this image; rescaled with scene.downscale?)")))
    return out


def view_warnings(scene, views: list[int], bbox: tuple, grid_cells: tuple[int, ...]) -> list[dict]:
    """Views whose whole image spans less than :data:`MIN_VIEW_VOXELS` voxels at the box centre
    (``bbox``, cut into ``grid_cells`` (nx, ny, nz)): their pixels all fall on one voxel or so."""
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in bbox)
    voxel = float(((hi - lo) / torch.tensor(grid_cells, dtype=torch.float64)).max())
    centre = torch.cat([(lo + hi) / 2, torch.ones(1, dtype=torch.float64)])
    K = K_of(scene.cameras).double()
    H, W = scene.image_size
    out = []
    for v in views:
        depth = float((scene.cameras.extrinsics[v].double() @ centre)[2])
        if depth <= 0:  # the box centre behind it: check_scene's concern
            continue
        span = max(W / float(K[v, 0, 0]), H / float(K[v, 1, 1])) * depth
        if span < MIN_VIEW_VOXELS * voxel:
            out.append(warning("narrow_view", (
                f"view '{scene.views[v]}': its whole image spans {span:.3g} world units at the box centre, less than "
                f"one voxel ({voxel:.3g}): its field of view is too narrow to see the density's shape (focal "
                f"lengths {float(K[v, 0, 0]):.4g}, {float(K[v, 1, 1]):.4g} px for a {W}x{H} image); check its K "
                "(in pixels of this image, rescaled with scene.downscale?), or hold the view out")))
    return out


def _spread(eyes: torch.Tensor, centre: torch.Tensor) -> float:
    """The largest distance between two of ``eyes`` (K, 3) over their mean distance to ``centre``."""
    if eyes.shape[0] < 2:
        return math.inf
    return float(torch.cdist(eyes, eyes).max() / (eyes - centre).norm(dim=1).mean().clamp_min(1e-300))


def _axis_spread_deg(eyes: torch.Tensor, centre: torch.Tensor) -> float:
    """The largest angle (deg) between the line from the first eye to ``centre`` and any
    other's, either way along it."""
    d = centre - eyes
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-300)
    cos = (d @ d[0]).abs().clamp(max=1.0)
    return float(torch.rad2deg(torch.acos(cos.min())))


def _same_pose(eyes: torch.Tensor, R: torch.Tensor, i: int, j: int, diagonal: float) -> bool:
    if float((eyes[i] - eyes[j]).norm()) > SAME_POSE_SHARE * diagonal:
        return False
    cos = ((torch.trace(R[i].T @ R[j]) - 1) / 2).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos))) <= SAME_ROTATION_DEG


def _image_difference(scene, i: int, j: int) -> float:
    a, b = scene.images[i], scene.images[j]
    return float((a - b).abs().mean()) if a.shape == b.shape else math.inf


def setup_warnings(train: list[int], step: float | None, grid_cells: tuple[int, ...] | None,
                   metrics: dict) -> list[dict]:
    """A ray step that skips cells (:data:`MAX_STEP_VOXELS`), a grid too coarse to hold a shape
    (:data:`MIN_SHAPE_CELLS`), volume scores of a tiny grid
    (:data:`MIN_GRID_CELLS`) or of a density no closer to the truth than zero, and a camera fit
    that had one training camera (its zero-mean gauge leaves nothing to fit)."""
    out = []
    if step is not None and step > MAX_STEP_VOXELS:
        out.append(warning("coarse_step", (
            f"projector.step={step:g} voxels: each ray samples every {step:g} cells and skips the density between, "
            "so the fit and its scores miss it; use projector.step=0.5 (the default) to 1")))
    volume = metrics.get("volume")
    if grid_cells is not None and min(grid_cells) < MIN_SHAPE_CELLS:
        cells = "x".join(map(str, grid_cells))
        out.append(warning("coarse_grid", (
            f"a {cells}-cell grid: fewer than {MIN_SHAPE_CELLS} cells along an axis hold no shape along it (1x1x1 is "
            "one value for the whole box), so the density and its renders say little of the flame; use "
            "grid.resolution >= 32 (the presets use 64-128)")))
    if volume and grid_cells is not None and min(grid_cells) < MIN_GRID_CELLS:
        out.append(warning("tiny_grid", (
            f"a {'x'.join(map(str, grid_cells))}-cell grid: its support fills the box, so the support IoU "
            f"({volume['iou']:.2f}) and the volume scores say little; use grid.resolution >= {MIN_GRID_CELLS}")))
    if volume and volume.get("rel_l2") is not None and volume["rel_l2"] >= NO_CLOSER_THAN_ZERO:
        out.append(warning("no_closer_than_zero", (
            f"the density's relative L2 error is {volume['rel_l2']:.2f}: it is no closer to the truth than an empty "
            f"one (error 1), whatever the support IoU ({volume['iou']:.2f}) says")))
    calibration = metrics.get("calibration")
    if calibration and len(train) < MIN_TRAIN_CAMERAS:
        out.append(warning("camera_fit_inert", (
            f"calibration.refine with {len(train)} training camera: its corrections are held to zero mean (the "
            "gauge), so the one camera is left as the capture calibrated it: the fit did nothing; refine with "
            "several training cameras, or set calibration.refine=none")))
    return out


def result_warnings(scene, volume: torch.Tensor, metrics: dict, views: list[int], l1: float,
                    l1_rel: float | None, *, train: list[int] | None = None, step: float | None = None,
                    bbox: tuple | None = None) -> list[dict]:
    """Every warning about a density scored in ``metrics``: :func:`image_warnings` of ``views``
    (the scored ones), :func:`score_warnings`, :func:`empty_density` (``l1``, ``l1_rel``: the
    weights it was solved with), and given ``train`` (the training views among ``views``, the
    rest held out), :func:`camera_geometry` (``bbox``: the grid's box), :func:`view_warnings`
    and :func:`setup_warnings` (``step``: projector.step)."""
    out = (image_warnings(scene, views) + score_warnings(metrics["heldout"])
           + empty_density(volume, metrics["train"], l1, l1_rel))
    if train is not None:
        holdout = [v for v in views if v not in train]
        cells = tuple(volume.shape[1:][::-1])
        out += camera_geometry(scene, train, holdout, bbox)
        out += view_warnings(scene, views, bbox or (scene.bbox_min, scene.bbox_max), cells)
        out += setup_warnings(train, step, cells, metrics)
    if any(w["code"] == "empty_density" for w in out):  # an empty density is no closer than zero: said once
        out = [w for w in out if w["code"] != "no_closer_than_zero"]
    return out


def penalty_of(solver: dict, l1: float) -> tuple[float, float | None]:
    """(absolute L1 weight, the relative one it came from or None) of ``solver`` options as a
    dict (``l1``, ``l1_rel``: an absolute ``l1`` wins) solved with the absolute weight ``l1``."""
    rel = solver.get("l1_rel") if solver.get("l1") is None else None
    return float(l1 or 0.0), None if rel is None else float(rel)
