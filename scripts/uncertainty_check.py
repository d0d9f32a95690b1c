"""Check the confidence images against held-out errors (README, "What the cameras determine").

    python scripts/uncertainty_check.py --frames 60 61 ... --out FILE.json [--loo] [train.py overrides ...]

Per frame (``scene.frame``; scene=scalarflow unless the overrides choose a scene), the run as
train.py's overrides describe it, its confidence (``uncertainty.*``), and per held-out camera:
the Spearman correlation of the predicted spread with the absolute error, per pixel whose ray
meets the visual hull (everywhere else both are 0), beside that of the rendered intensity (the
trivial predictor) and of an oracle that knows the error around each pixel within 2 px (a
diagnosis: what a spread at that resolution could at best do); the coverage of the 1- and
2-sigma bands there (the trivial predictor's with its gain fitted to this very view); the
measured and the predicted full-frame PSNR (the confidence's spread and the sensor noise the
training images show, :func:`~flamerecon.evaluate.uncertainty.capture_sigma`; the spread alone as
``psnr_predicted_spread``), and the prediction *before* the cameras' poses entered it (no pose
spread, no noise; at ``--scale-before``, default ``uncertainty.scale``). ``--loo``
holds out every camera in turn (leave-one-view-out) instead of the run's held-out ones, and
prints per frame the rank correlation of the views' predicted PSNR with their measured one.
With a scene whose cameras were given off from those that rendered it (``scene=synthetic_flame``
with a camera fit), each camera's true pose error against its reported sigma; with one that adds
known sensor noise (the synthetic scenes), the coverage against its noiseless images too. Writes
FILE.json: ``{"frames": {"65": {"spearman", "spearman_trivial", "coverage_1sigma",
"coverage_2sigma", "psnr", "psnr_predicted", "psnr_predicted_before", ..., "views": {view: the
same}}}, "scale_fit", "config"}`` (a frame's figures are the mean over its held-out views), and
prints the table, the cost per frame (the run and the confidence), and ``scale_fit``: the
``uncertainty.scale`` that would make the predicted MSE equal the measured on these frames, the
cameras' pose part kept (their geometric mean: how the scale was chosen on frames that are then
not reported).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import math
import os
import sys
import time
from dataclasses import replace

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import torch

from flamerecon.evaluate.metrics import resample_to
from flamerecon.evaluate.scores import captured_silhouettes, silhouette_union
from flamerecon.evaluate.uncertainty import (
    capture_sigma,
    check_view,
    coverage,
    predicted_psnr,
    recorded_sigma,
    spearman,
    training_noise,
)
from flamerecon.fit.ensemble import confidence
from flamerecon.fit.pose_uncertainty import corrections_between, rotation_deg
from flamerecon.fit.reconstruct import reconstruct
from flamerecon.fit.refine_cameras import camera_frame_points, similarity
from flamerecon.geometry.cameras import K_of, camera_subset, make_cameras, project_points
from flamerecon.operators.projector import render_image
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.run.cli import at_least, compose_train, output_file, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene

#: the columns of the table (and the figures averaged into a frame's entry)
COLUMNS = ("spearman", "spearman_trivial", "spearman_oracle_2px", "coverage_1sigma", "coverage_2sigma",
           "coverage_2sigma_trivial", "psnr", "psnr_predicted_before", "psnr_predicted")


def check_split(scene, options, views: list[int] | None, scale_before: float | None = None
                ) -> tuple[dict[str, dict], dict[str, float]]:
    """Reconstruct ``scene`` holding out ``views`` (None: the options' held-out ones) and check
    its confidence on each held-out view: ({view: figures}, {"run": s, "confidence": s}).
    ``psnr_predicted_before``: the prediction without the cameras' poses (no ``poses`` members,
    no held-out pose spread) at ``scale_before`` (None: the options' scale)."""
    if views is not None:
        options = options.replace(holdout=tuple(scene.views[v] for v in views))
    if options.calibration.frames and options.calibration.refine != "none":  # the pose part, as a run with it has
        options = options.replace(calibration=replace(options.calibration, offsets=True))
    clock = time.perf_counter()
    rec = reconstruct(scene, options)
    run_seconds = time.perf_counter() - clock
    clock = time.perf_counter()
    conf = confidence(rec.setup, rec.options, rec.fit.result.x, calibration=rec.calibration)
    cams = camera_subset(rec.scene.cameras, rec.setup.holdout)
    names = [scene.views[v] for v in rec.setup.holdout]
    parts = {k: v.cpu() for k, v in conf.image_parts(cams).items()}
    zero = torch.zeros(cams.batch_size, conf.x.shape[1], *rec.scene.image_size)
    unscaled = sum((v for k, v in parts.items() if k != "poses"), zero)  # the kinds the scale multiplies
    pose_variance = parts.get("poses", zero)  # measured: the poses members' and the held-out camera's own
    if conf.poses is not None:
        pose_variance = pose_variance + conf.poses.variance(conf.density, conf.grid, cams, names, conf.step).cpu()
    sigma = (float(conf.scale) ** 2 * unscaled + pose_variance).sqrt()
    domain = conf.footprint(cams).cpu()
    confidence_seconds = time.perf_counter() - clock
    before = float(conf.scale if scale_before is None else scale_before) * unscaled.sqrt()
    rendered = render_image(rec.density, rec.grid, cams, rec.setup.step).cpu()
    captured = captured_silhouettes(rec.scene, rec.setup.holdout, options.silhouette.as_dict())
    union = silhouette_union(rendered, captured, options.silhouette.as_dict())
    volume = check_volume(rec, conf)
    noise = training_noise(rec.scene, rec.setup.train)
    out = {}
    for k, v in enumerate(rec.setup.holdout):
        recorded = rec.scene.to_recorded(rendered[k])
        against = capture_sigma(rec.scene, rendered[k], sigma[k], noise)  # the spread and the sensor's noise
        out[scene.views[v]] = {**check_view(recorded, rec.scene.recorded_view(v), against, domain[k], union[k]),
                               "psnr_predicted_spread": predicted_psnr(recorded_sigma(rec.scene, rendered[k], sigma[k])),
                               "noise_variance": float(noise.variance(recorded).double().mean()),
                               "psnr_predicted_before": predicted_psnr(recorded_sigma(rec.scene, rendered[k], before[k])),
                               "unscaled_variance": float(unscaled[k].double().mean()),
                               "pose_variance": float(pose_variance[k].double().mean()),
                               **pose_figures(conf, scene.views[v]), **volume}
    for name, figures in noiseless_figures(rec, rendered, sigma, domain).items():
        out[name].update(figures)
    truth = pose_truth(rec, conf)  # one per fold: the cameras of this run
    if truth:
        out[scene.views[rec.setup.holdout[0]]]["poses_truth"] = truth
    return out, {"run": run_seconds, "confidence": confidence_seconds, "members": conf.seconds}


def noiseless_figures(rec, rendered: torch.Tensor, sigma: torch.Tensor, domain: torch.Tensor) -> dict[str, dict]:
    """With a scene that adds known sensor noise to its images (the synthetic scenes'
    ``scene.noise``), per held-out view (``rendered``, ``sigma`` (V, C, H, W), ``domain`` (V, H,
    W) as :func:`check_split` has them) the 1- and 2-sigma coverage and the PSNR against its
    noiseless images (``*_noiseless``), the same cameras: how much of the miss is the sensor's
    noise, which the confidence does not model (a diagnosis); {} for any other scene."""
    scene = rec.scene
    if not scene.meta.get("noise") or "config" not in scene.meta:
        return {}
    clean = load_scene({**scene.meta["config"], "noise": 0.0})
    if clean.images.shape != scene.images.shape:
        return {}
    out = {}
    for k, v in enumerate(rec.setup.holdout):
        found = check_view(scene.to_recorded(rendered[k]), clean.recorded_view(v),
                           recorded_sigma(scene, rendered[k], sigma[k]), domain[k])
        out[scene.views[v]] = {f"{key}_noiseless": found[key] for key in ("coverage_1sigma", "coverage_2sigma", "psnr")}
    return out


def pose_figures(conf, view: str) -> dict[str, float]:
    """The held-out camera's pose uncertainty as the confidence has it: one-sigma degrees,
    pixels at the box, the share its images confirmed; {} when it has none."""
    if conf.poses is None or view not in conf.poses.views:
        return {}
    r = conf.poses.records()[view]
    return {"pose_sigma_deg": r["pose_sigma_deg"], "pose_sigma_box_px": r["pose_sigma_box_px"],
            "pose_share": r["pose_share"]}


def pose_truth(rec, conf) -> dict[str, dict]:
    """With a scene whose cameras were given off from those that rendered its images (the
    synthetic flame's ``scene.calibration_error``): per camera with a pose offset, its true
    error (the correction that takes the camera as the run has it, refined or not, to the one
    that rendered its images) beside the reported one sigma, in degrees and in pixels at the
    box; {} for any other scene."""
    scene = rec.scene
    if not scene.meta.get("calibration_error") or conf.poses is None:
        return {}
    true = load_scene({**scene.meta["config"], "calibration_error": 0.0}).cameras
    pivot = 0.5 * (rec.grid.lo() + rec.grid.hi())
    train = rec.setup.train
    s, R, t = similarity(camera_frame_points(camera_subset(scene.cameras, train), pivot),
                         camera_frame_points(camera_subset(true, train), pivot))
    E = scene.cameras.extrinsics.double().clone()  # the run's cameras moved as one rig onto the true ones
    E[:, :3, 3] = s * E[:, :3, 3] - (E[:, :3, :3] @ R.T @ t[:, None]).squeeze(-1)
    E[:, :3, :3] = E[:, :3, :3] @ R.T
    rig = make_cameras(K_of(scene.cameras), E.float(), scene.cameras.height, scene.cameras.width)
    reported = conf.poses.records()
    out = {}
    for view in conf.poses.views:
        k = scene.views.index(view)
        out[view] = {**error_figures(camera_subset(scene.cameras, [k]), camera_subset(true, [k]), rec.grid, ""),
                     **error_figures(camera_subset(rig, [k]), camera_subset(true, [k]), rec.grid, "rig_"),
                     "sigma_deg": reported[view]["pose_sigma_deg"], "sigma_box_px": reported[view]["pose_sigma_box_px"],
                     "held_out": k in rec.setup.holdout}
    return out


def error_figures(given, truth, grid, prefix: str) -> dict[str, float]:
    """``<prefix>true_deg`` / ``<prefix>true_box_px``: how far camera ``given`` is from
    ``truth``: the angle between their orientations, the RMS shift of the box's corners."""
    corners = grid.corners()
    error = corrections_between(given, truth, 0.5 * (grid.lo() + grid.hi()))
    shift = (project_points(given, corners)[0] - project_points(truth, corners)[0]).norm(dim=-1).pow(2).mean()
    return {f"{prefix}true_deg": float(rotation_deg(error)[0]), f"{prefix}true_box_px": float(shift.sqrt())}


def check_volume(rec, conf) -> dict[str, float]:
    """With a scene whose truth lies on the run's box (the synthetic flame): how the confidence
    volume predicts the density's error there, over the hull voxels (every channel): the rank
    correlation with |density - truth| (``volume_spearman``; ``volume_spearman_trivial``: the
    density's own), the 1- and 2-sigma coverage; {} without a truth."""
    scene, grid = rec.scene, rec.grid
    if scene.truth is None or scene.truth_grid is None or (scene.truth_grid.bbox_min, scene.truth_grid.bbox_max) != (
            grid.bbox_min, grid.bbox_max):
        return {}
    truth = resample_to(scene.truth, grid.shape)
    density, sigma = rec.density.cpu(), conf.volume().cpu()
    inside = rec.setup.hull.cpu().expand_as(density)
    error = (density - truth).abs()[inside]
    return {"volume_spearman": spearman(sigma[inside], error), "volume_spearman_trivial": spearman(density[inside], error),
            "volume_coverage_1sigma": coverage(error, sigma[inside], 1.0),
            "volume_coverage_2sigma": coverage(error, sigma[inside], 2.0)}


def truth_rates(truths: list[dict]) -> dict[str, float]:
    """The fraction of cameras (each fold's, held-out and training apart) whose true pose error
    lies within 2 reported sigma, in degrees and in pixels at the box; ``rig_``: the error left
    once the run's cameras are moved as one rig (a similarity, fitted to the training cameras)
    onto the true ones, the part no image can tell apart from a moved world."""
    out = {}
    for group, held in (("held_out", True), ("training", False)):
        chosen = [t for t in truths if t["held_out"] == held]
        for frame in ("", "rig_"):
            for unit in ("deg", "box_px"):
                if chosen:
                    out[f"{group}_{frame}{unit}"] = sum(t[f"{frame}true_{unit}"] <= 2 * t[f"sigma_{unit}"]
                                                        for t in chosen) / len(chosen)
    return out


def exact_scale(r: dict) -> float:
    """The ``uncertainty.scale`` that would make view ``r``'s predicted PSNR its measured one
    (a linear camera), its cameras' pose part and the sensor's noise unchanged; 0 where those alone
    predict more error than measured."""
    left = 10 ** (-r["psnr"] / 10) - r["pose_variance"] - r.get("noise_variance", 0.0)
    return math.sqrt(max(left, 0.0) / r["unscaled_variance"]) if r["unscaled_variance"] > 0 else 0.0


def mean_figures(views: dict[str, dict]) -> dict[str, float]:
    """The mean of every figure that each of the views has."""
    keys = set.intersection(*({k for k, x in v.items() if isinstance(x, float)} for v in views.values()))
    return {k: sum(v[k] for v in views.values()) / len(views) for k in keys}


def line(frame, view: str, r: dict, cost: str = "") -> str:
    return (f"{frame!s:>5} {view:<9} " + " ".join(f"{r[k]:8.3f}" if "psnr" not in k else f"{r[k]:8.2f}"
                                                  for k in COLUMNS) + f"  {cost}")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    parser.add_argument("--frames", type=at_least(0), nargs="+", required=True, help="scene.frame values")
    parser.add_argument("--out", type=output_file, required=True, help="the JSON file to write")
    parser.add_argument("--loo", action="store_true", help="hold out every camera in turn")
    parser.add_argument("--scale-before", type=float, help="the scale of the 'before' prediction (the confidence "
                        "without the cameras' poses); default: uncertainty.scale")
    args = parser.parse_args(argv)

    def run() -> None:
        record = {"frames": {}, "config": list(args.overrides), "loo": bool(args.loo)}
        print(f"{'frame':>5} {'view':<9} " + " ".join(f"{k.replace('coverage_', 'cov').replace('spearman', 'rho')[:8]:>8}"
                                                   for k in COLUMNS) + "  seconds (run + confidence)", flush=True)
        fits = []
        for frame in args.frames:
            cfg = compose_train([*args.overrides, f"scene.frame={frame}"])
            options = options_from_config(cfg)
            scene = load_scene(cfg.scene)
            splits = [[v] for v in range(scene.num_views)] if args.loo else [None]
            views, cost = {}, {"run": 0.0, "confidence": 0.0, "members": 0.0}
            for split in splits:
                found, seconds = check_split(scene, options, split, args.scale_before)
                views.update(found)
                cost = {k: cost[k] + seconds[k] for k in cost}
                for name, r in found.items():
                    fits.append(exact_scale(r))
                    print(line(frame, name, r, f"{seconds['run']:.1f} + {seconds['confidence']:.1f}"), flush=True)
                    if "coverage_2sigma_noiseless" in r:
                        print(f"      {name} against its noiseless images: coverage 1/2 sigma "
                              f"{r['coverage_1sigma_noiseless']:.3f}/{r['coverage_2sigma_noiseless']:.3f}, PSNR "
                              f"{r['psnr_noiseless']:.2f}", flush=True)
            entry = {**mean_figures(views), "views": views, "seconds": cost}
            record["frames"][str(frame)] = entry
            if len(views) > 1:
                print(line(frame, "mean", entry), flush=True)
                measured = torch.tensor([r["psnr"] for r in views.values()])
                for key in ("psnr_predicted_before", "psnr_predicted"):
                    entry[f"rank_{key}"] = spearman(torch.tensor([r[key] for r in views.values()]), measured)
                entry["worst_miss"] = max(abs(r["psnr_predicted"] - r["psnr"]) for r in views.values())
                print(f"      the views ranked by predicted PSNR against the measured: rank correlation "
                      f"{entry['rank_psnr_predicted']:.2f} (before: {entry['rank_psnr_predicted_before']:.2f}); "
                      f"largest miss {entry['worst_miss']:.2f} dB", flush=True)
            truths = [t for r in views.values() for t in r.get("poses_truth", {}).values()]
            if truths:
                entry["poses_truth"] = truth_rates(truths)
                print("      cameras' true pose errors within 2 sigma: " + ", ".join(
                    f"{k} {v:.2f}" for k, v in entry["poses_truth"].items()), flush=True)
            if "volume_spearman" in entry:
                print(f"      volume: rank correlation with |density - truth| {entry['volume_spearman']:.3f} (the "
                      f"density's own {entry['volume_spearman_trivial']:.3f}), coverage 1/2 sigma "
                      f"{entry['volume_coverage_1sigma']:.3f}/{entry['volume_coverage_2sigma']:.3f}", flush=True)
            if "coverage_2sigma_noiseless" in entry:
                cover = [r["coverage_2sigma_noiseless"] for r in views.values()]
                print(f"      against the noiseless images (a diagnosis: the sensor's noise taken away): coverage 1/2 "
                      f"sigma {entry['coverage_1sigma_noiseless']:.3f}/{entry['coverage_2sigma_noiseless']:.3f} "
                      f"(2 sigma per view {min(cover):.3f}-{max(cover):.3f}), PSNR "
                      f"{entry['psnr_noiseless']:.2f}", flush=True)
            print(f"      cost of frame {frame}: run {cost['run']:.1f} s, confidence {cost['confidence']:.1f} s "
                  f"({cost['confidence'] / cost['run']:.2f} x the run; members {cost['members']:.1f} s); "
                  f"load average {os.getloadavg()[0]:.2f} (a shared machine's times vary)", flush=True)
        usable = [f for f in fits if f > 0]
        record["scale_fit"] = math.exp(sum(math.log(f) for f in usable) / len(usable)) if usable else math.nan
        print(f"uncertainty.scale that makes the predicted PSNR exact on these frames (geometric mean over "
              f"{len(usable)} of {len(fits)} views; the cameras' pose part kept as it is): "
              f"{record['scale_fit']:.3f} (used: {options.uncertainty.scale:g})")
        write_json_atomic(args.out, record)
        print(f"written: {args.out}")

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
