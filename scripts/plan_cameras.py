"""Where to put the next camera (README, "What the cameras determine").

    python scripts/plan_cameras.py RUN_DIR [--orbit N] [--cameras FILE.json] [--noise S]
    python scripts/plan_cameras.py --check-synthetic [train.py overrides ...]
    python scripts/plan_cameras.py --check-loo --frames 65,72 [train.py overrides ...]

RUN_DIR (any run: every camera fitted, or some held out): ranks candidate cameras by the
predicted reduction of the run's confidence volume's variance
(:mod:`flamerecon.evaluate.camera_planning`; the confidence read from the run's uncertainty.npz,
else solved now): ``--orbit N`` cameras evenly around the box at the rig's mean distance and
elevation (default 24, at most 360), or the cameras of ``--cameras`` (a cameras.json), each with
the first camera's intrinsics and image size. Each candidate is placed in world azimuth and
elevation about the scene's up axis (azimuth 0 and 90 named in what it prints), with the
density's relative error the confidence predicts once it is added (now: printed first), and the
fitted cameras and better-ranked candidates it nearly duplicates: ``beside`` one (within 20
degrees of its line of sight) or its ``mirror`` (facing it: an emission-only camera then sees
nearly the same line integrals, mirrored). Writes RUN_DIR/camera_plan.json and
RUN_DIR/renders/camera_plan.png (top view with its world axes: the rig and the ranked
candidates). ``--noise``: the one-sigma noise of a new camera's pixels (default: the run's
training residual inside the silhouettes, from its training PSNR there).

``--check-synthetic``: the synthetic flame (overrides on top, e.g. ``scene.n_cameras=12
holdout=[...]``): the run's held-out cameras are the candidates; each is added to the fit in
turn and the density's relative L2 error against the truth measured; prints every candidate's
predicted and measured gain, the top-ranked one's against the median.
``--check-loo``: per frame of a real capture (scene=scalarflow by default), each camera held out
in turn: its predicted value (the variance it would remove from the other cameras' fit) against
its measured contribution (the mean squared error of that fit on it); prints the rank
correlation over the cameras per frame.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import math
import sys
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np
import torch

import flamerecon as fr
from flamerecon.evaluate.camera_planning import (
    alike,
    orbit_candidates,
    sight_lines,
    total_variance,
    variance_reduction,
    volume_error,
)
from flamerecon.evaluate.uncertainty import spearman
from flamerecon.fit.ensemble import confidence
from flamerecon.fit.reconstruct import mean_of, reconstruct
from flamerecon.geometry.axes import ground_frame, up_vector, world_angles
from flamerecon.geometry.cameras import camera_centers, camera_subset, make_cameras
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.outputs.camera_plan import axis_name_of, camera_plan_figure
from flamerecon.outputs.cameras_file import read_camera_file
from flamerecon.outputs.figures import write_png
from flamerecon.progress import Progress
from flamerecon.run.cli import at_least, compose_train, frame_list, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene

#: the noise of a new camera's pixels when a run has no training PSNR inside the silhouettes
DEFAULT_NOISE = 0.01
#: the most orbit candidates: one a degree (each costs a render of every ensemble member)
MAX_ORBIT = 360


def noise_of(metrics: dict) -> float:
    """A run's training residual, one sigma per pixel inside the silhouettes, from its metrics."""
    train = metrics.get("train", {})
    if train and "psnr_silhouette" in next(iter(train.values())):
        return 10 ** (-mean_of(train, "psnr_silhouette") / 20)
    return DEFAULT_NOISE


def ranked(reductions: torch.Tensor) -> list[int]:
    return sorted(range(len(reductions)), key=lambda b: -float(reductions[b]))


def plan_run(run_dir: Path, orbit: int, cameras_file: Path | None, noise: float | None) -> None:
    run = fr.load_run(run_dir)
    conf = fr.confidence(run)
    noise = noise if noise is not None else noise_of(run.metrics)
    rig = camera_subset(run.scene.cameras, run.train)
    up = np.asarray(up_vector(run.scene.up))
    centre = conf.grid.lo().double() * 0.5 + conf.grid.hi().double() * 0.5
    if cameras_file is not None:
        records = read_camera_file(cameras_file, "--cameras")["cameras"]
        K = rig.intrinsics[:1, :3, :3].expand(len(records), 3, 3)
        w2c = torch.tensor(np.array([r["world_to_camera"] for r in records]), dtype=torch.float32)
        cams = make_cameras(K, w2c, int(rig.height[0]), int(rig.width[0]))
        names = [r.get("name", f"camera{k}") for k, r in enumerate(records)]
    else:
        cams, _ = orbit_candidates(rig, centre, orbit, up)
        names = [f"orbit{k:02d}" for k in range(orbit)]
    azimuths, elevations = world_angles(camera_centers(cams).double().numpy() - centre.numpy(), up)
    total = total_variance(conf)
    progress = Progress("camera plan", cams.batch_size, unit="candidate")
    reductions = variance_reduction(conf, cams, noise, rig, lambda b: progress.update(b + 1, names[b]))
    order = ranked(reductions)
    lines = sight_lines(cams, centre.numpy())
    fitted_names = [run.scene.views[v] for v in run.train]
    near_fitted = alike(lines, sight_lines(rig, centre.numpy()))
    near_better = alike(lines, lines)
    rank_of = {b: rank for rank, b in enumerate(order, 1)}
    now = volume_error(conf, total)
    print(f"{run_dir}: {len(names)} candidates, azimuth about {run.scene.up} (0 deg: "
          f"{axis_text(ground_frame(up)[0])}, 90 deg: {axis_text(ground_frame(up)[1])}); pixel noise {noise:.4g}")
    print(f"the confidence predicts the density's relative error now at {now:.4f} (total variance {total:.4g})")
    print(f"{'rank':>4} {'camera':<12} {'azimuth':>8} {'elev.':>6} {'removes':>8} {'error after':>11}  like")
    rows = []
    for rank, b in enumerate(order, 1):
        after = volume_error(conf, total - float(reductions[b]))
        like = [f"{how} {fitted_names[m]}" for m, how in near_fitted[b]]
        like += [f"{how} {names[m]} (rank {rank_of[m]})" for m, how in near_better[b] if rank_of[m] < rank]
        print(f"{rank:4d} {names[b]:<12} {azimuths[b]:7.1f}° {elevations[b]:5.1f}° "
              f"{100 * float(reductions[b]) / total:7.2f}% {after:11.4f}  {', '.join(like) or '-'}")
        rows.append({"name": names[b], "rank": rank, "azimuth_deg": float(azimuths[b]),
                     "elevation_deg": float(elevations[b]), "variance_removed": float(reductions[b]),
                     "share": float(reductions[b]) / total if total > 0 else 0.0, "volume_error_after": after,
                     "alike": like, "world_to_camera": cams.extrinsics[b].tolist()})
    distinct = [r for r in rows if not r["alike"]]
    if distinct and distinct[0]["rank"] != 1:
        print(f"the best candidate unlike any fitted camera or better candidate: {distinct[0]['name']} "
              f"(rank {distinct[0]['rank']})")
    centres = camera_centers(cams).numpy()
    fitted = {run.scene.views[v]: camera_centers(camera_subset(run.scene.cameras, [v]))[0].numpy() for v in run.train}
    held = {run.scene.views[v]: camera_centers(camera_subset(run.scene.cameras, [v]))[0].numpy() for v in run.holdout}
    shares = (reductions / total).numpy() if total > 0 else np.zeros(len(names))
    figure = camera_plan_figure(up, conf.grid.corners().numpy(), fitted, held, centres, shares,
                                f"next camera for {run_dir.name}: share of the variance removed")
    write_png(run_dir / "renders" / "camera_plan.png", figure)
    write_json_atomic(run_dir / "camera_plan.json", {
        "noise": noise, "total_variance": total, "up": run.scene.up, "volume_error_now": now,
        "azimuth_zero": ground_frame(up)[0].tolist(), "candidates": rows})
    print(f"written: {run_dir / 'camera_plan.json'}, {run_dir / 'renders' / 'camera_plan.png'}")


def axis_text(direction: np.ndarray) -> str:
    """A world direction as its axis name where it lies along one (``+z``), else its components."""
    return axis_name_of(direction) or "(" + ", ".join(f"{v:.2f}" for v in direction) + ")"


def check_synthetic(overrides: list[str]) -> None:
    """Each held-out camera of the synthetic run added in turn: predicted against measured."""
    cfg = compose_train(overrides, default_scene=None)
    options = options_from_config(cfg)
    scene = load_scene(cfg.scene)
    if scene.truth is None:
        raise ValueError("--check-synthetic: the scene has no ground truth; use scene=synthetic")
    rec = reconstruct(scene, options)
    base = rec.score()["volume"]["rel_l2"]
    conf = confidence(rec.setup, rec.options, rec.fit.result.x)
    noise = noise_of(rec.score())
    candidates = list(rec.setup.holdout)
    if len(candidates) < 3:
        raise ValueError(f"--check-synthetic: {len(candidates)} held-out cameras; hold out at least 3 to rank "
                         "(e.g. scene.n_cameras=12 and holdout=[...])")
    cams = camera_subset(rec.scene.cameras, candidates)
    predicted = variance_reduction(conf, cams, noise, camera_subset(rec.scene.cameras, rec.setup.train))
    total = total_variance(conf)
    measured = []
    progress = Progress("adding each candidate", len(candidates), unit="reconstruction")
    for k, v in enumerate(candidates):
        rest = tuple(scene.views[c] for c in candidates if c != v)
        added = reconstruct(scene, options.replace(holdout=rest))
        measured.append(base - added.score()["volume"]["rel_l2"])
        progress.update(k + 1, scene.views[v])
    print(f"fitted {[scene.views[v] for v in rec.setup.train]}: volume rel. L2 {base:.4f}; noise {noise:.3g}")
    print(f"{'rank':>4} {'camera':<8} {'predicted':>10} {'rel L2 after':>12} {'gain':>8}")
    order = ranked(predicted)
    for rank, k in enumerate(order, 1):
        print(f"{rank:4d} {scene.views[candidates[k]]:<8} {100 * float(predicted[k]) / total:9.2f}% "
              f"{base - measured[k]:12.4f} {measured[k]:8.4f}")
    median = float(np.median(measured))
    top = measured[order[0]]
    print(f"top-ranked {scene.views[candidates[order[0]]]} lowers the volume error by {top:.4f}, the median "
          f"candidate by {median:.4f}: {'better' if top > median else 'NOT better'}; rank correlation of predicted "
          f"and measured gains {spearman(predicted, torch.tensor(measured)):.3f}")


def check_loo(frames: list[int], overrides: list[str]) -> None:
    """Per frame, each camera held out: its predicted value against its measured contribution."""
    for frame in frames:
        cfg = compose_train([*overrides, f"scene.frame={frame}"])
        options = options_from_config(cfg)
        scene = load_scene(cfg.scene)
        predicted, measured = [], []
        for v, name in enumerate(scene.views):
            rec = reconstruct(scene, options.replace(holdout=(name,)))
            conf = confidence(rec.setup, rec.options, rec.fit.result.x)
            metrics = rec.score()
            fitted = camera_subset(rec.scene.cameras, rec.setup.train)
            cam = camera_subset(rec.scene.cameras, [v])
            share = float(variance_reduction(conf, cam, noise_of(metrics), fitted)[0]) / total_variance(conf)
            psnr = metrics["heldout"][name]["psnr"]
            predicted.append(share)
            measured.append(10 ** (-psnr / 10))
            print(f"  frame {frame} {name:<8} predicted {100 * share:6.2f}% of the variance; measured: the other "
                  f"cameras' fit predicts it to {psnr:.2f} dB (MSE {measured[-1]:.3g})", flush=True)
        rho = spearman(torch.tensor(predicted), torch.tensor(measured))
        print(f"frame {frame}: rank correlation of predicted value and measured contribution over "
              f"{len(predicted)} cameras: {rho:.3f}", flush=True)
        if math.isnan(rho):
            print("  (undefined: constant)")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("target", nargs="*", help="RUN_DIR, or with --check-*: train.py overrides")
    parser.add_argument("--orbit", type=at_least(3, MAX_ORBIT), default=24,
                        help=f"candidates evenly around the box (3 to {MAX_ORBIT}: one a degree)")
    parser.add_argument("--cameras", type=Path, help="a cameras.json whose cameras are the candidates")
    parser.add_argument("--noise", type=float, help="one-sigma noise of a new camera's pixels (image units)")
    parser.add_argument("--check-synthetic", action="store_true", help="check the ranking on the synthetic flame")
    parser.add_argument("--check-loo", action="store_true", help="check it by leave-one-view-out on a capture")
    parser.add_argument("--frames", type=frame_list, help="with --check-loo: comma-separated scene.frame values")
    args = parser.parse_args(argv)
    if args.check_synthetic and args.check_loo:
        parser.error("--check-synthetic and --check-loo: choose one")
    if args.check_loo and not args.frames:
        parser.error("--check-loo needs --frames")
    if not (args.check_synthetic or args.check_loo) and len(args.target) != 1:
        parser.error("give one RUN_DIR (or --check-synthetic / --check-loo with train.py overrides)")
    if args.noise is not None and not args.noise > 0:
        parser.error(f"--noise: got {args.noise}; give a number > 0")

    def run() -> None:
        if args.check_synthetic:
            check_synthetic(args.target)
        elif args.check_loo:
            check_loo(args.frames, args.target)
        else:
            plan_run(Path(args.target[0]), args.orbit, args.cameras, args.noise)

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
