"""Results that look like runs but mean little, said as warnings: an empty density, saturated
views, float images outside [0, 1], an all-black held-out view, a held-out PSNR below the
all-black floor. Each warning is ``{"code", "message"}``; the message names the setting to
change. The run (metrics.json's ``warnings``, the log, the summary's block),
``scripts/evaluate.py`` and ``fr.score`` all take them from :func:`result_warnings`."""

from __future__ import annotations

import math

import torch

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
    peak = float(volume.detach().abs().max()) if volume.numel() else 0.0
    gains = [s["psnr"] - s["psnr_black"] for s in train.values()
             if math.isfinite(s["psnr"]) and math.isfinite(s["psnr_black"])]
    gain = sum(gains) / len(gains) if gains else 0.0
    if peak > 0 and abs(gain) >= EMPTY_GAIN_DB:
        return []
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


def result_warnings(scene, volume: torch.Tensor, metrics: dict, views: list[int], l1: float,
                    l1_rel: float | None) -> list[dict]:
    """Every warning about a density scored in ``metrics``: :func:`image_warnings` of ``views``
    (the scored ones), :func:`score_warnings` and :func:`empty_density` (``l1``, ``l1_rel``:
    the weights it was solved with)."""
    return (image_warnings(scene, views) + score_warnings(metrics["heldout"])
            + empty_density(volume, metrics["train"], l1, l1_rel))


def penalty_of(solver: dict, l1: float) -> tuple[float, float | None]:
    """(absolute L1 weight, the relative one it came from or None) of ``solver`` options as a
    dict (``l1``, ``l1_rel``: an absolute ``l1`` wins) solved with the absolute weight ``l1``."""
    rel = solver.get("l1_rel") if solver.get("l1") is None else None
    return float(l1 or 0.0), None if rel is None else float(rel)
