"""The fitted velocities checked against physics nobody here wrote: a buoyant plume simulated by
PhiFlow, rendered emission-only into ScalarFlow's five cameras by an independent ray marcher,
reconstructed by flamerecon, its flow and its simulator fitted, and both compared with the truth.

    python scripts/simulated_plume.py --out plume.json [--frames 44] [--pairs 14 28] [--cache DIR] \
        [--window 4] [--cells 64 96 64] [scene=scalarflow, train.py overrides] [flow.KEY=VALUE ...] \
        [simulation.KEY=VALUE ...]

The truth: PhiFlow (``pip install phiflow``, a bench extra; its NumPy backend and conjugate
gradient pressure solve) simulates smoke on 64 x 96 x 64 cells (``--cells``) filling the scene's
box (ScalarFlow's by default: metres, y up; closed sides and floor, open top), dt = 1/30 s (one step a frame at 30 frames per second):
semi-Lagrangian velocity, MacCormack density, buoyancy 3 m/s^2 per unit of density along +y,
and a flickering Gaussian source near the floor (its rate varies frame to frame, so the column
carries puffs). Each frame's density is rendered into the scene's cameras (ScalarFlow's five at
1/4 resolution, 480 x 270, the capture's own calibration: exact cameras) by a ray marcher written
here with SciPy (rays through pixel centres, trilinear samples every half cell, not flamerecon's
projector), scaled once so that the last frame's brightest pixel is 0.8, plus sensor noise.

flamerecon then reconstructs every frame (the train.py config of the overrides, by default
``scene=scalarflow``'s, its camera refinement and ladder off, the scene's held-out camera: train02)
and fits the velocity of each frame pair in PAIRS (``fr.estimate_flow``'s
fit, warm-started, ``flow.*`` options) and the simulator of issue 37 (``simulation.*``
options, by default the physical simulator: ``incompressible``, ``self_advection``,
``fit_buoyancy`` and ``start=assimilated``; the window of ``--window`` frames before each pair's
first frame). Each velocity (cells
per frame) is compared with PhiFlow's at the cell centres, interpolated onto the reconstruction
grid, over the smoke (where the true density exceeds 5 % of its peak): relative L2 error and
mean angle, beside zero velocity (relative L2 1) and the best uniform upward velocity fitted to
the truth there (least squares). Frames predicted k = 1, 5, 10 ahead (the flow's and the
simulator's) are compared with the simulated ones: the volume's relative L2 error and the
held-out camera's PSNR. Prints the table, time and peak memory; ``--out`` writes it as JSON.
``--cache DIR`` keeps the PhiFlow simulation (``plume_phiflow.npz``) for the next call; every
call times one step of PhiFlow and of flamerecon's simulator (forward, and with its gradient) on
the last simulated frame, and ``--speed`` stops there.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import math
import os
import resource
import sys
import time

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np
import torch

from flamerecon.run.cli import (
    at_least,
    compose_train,
    output_file,
    output_folder,
    run_script,
    script_parser,
)
from flamerecon.run.flow import flow_options, parse_with_overrides, section_options
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene

FPS = 30.0
SUBSTEPS = 1
BUOYANCY = 3.0  # m/s^2 per unit of density
SEED = 3
#: the simulator as physics has it (its prediction defaults are chosen on ScalarFlow instead)
PHYSICAL = ("incompressible=true", "self_advection=true", "fit_buoyancy=true", "start=assimilated")


def _phiflow():
    """PhiFlow's ``phi.flow`` on its NumPy backend, with phiml 1.16's sparse matrix build made to
    ravel indices in int64 (in int32 it overflows above about 46,000 cells)."""
    try:
        from phi import flow as phi
        from phiml.backend._numpy_backend import NumPyBackend
    except ImportError as err:
        raise ImportError("simulated_plume.py needs PhiFlow: pip install phiflow") from err
    ravel = NumPyBackend.ravel_multi_index
    if not getattr(ravel, "int64", False):
        def int64_ravel(self, index, shape, mode="undefined"):
            return ravel(self, np.asarray(index, np.int64), shape, mode)

        int64_ravel.int64 = True
        NumPyBackend.ravel_multi_index = int64_ravel
    return phi


def _phi_grids(phi, box_min, box_max, cells):
    """PhiFlow's domain: (bounds, the velocity's boundary: closed sides and floor, open top)."""
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    bounds = phi.Box(x=(lo[0], hi[0]), y=(lo[1], hi[1]), z=(lo[2], hi[2]))
    return bounds, phi.extrapolation.combine_sides(x=0, y=(0, phi.extrapolation.ZERO_GRADIENT), z=0)


def _phi_step(phi, smoke, velocity, pressure, mask, rate: float, dt: float):
    """One PhiFlow step (module doc): MacCormack density and the source, buoyancy,
    semi-Lagrangian velocity, the pressure projection by conjugate gradients."""
    smoke = phi.advect.mac_cormack(smoke, velocity, dt) + rate * dt * mask
    force = phi.resample(smoke * (0, BUOYANCY, 0), to=velocity)
    velocity = phi.advect.semi_lagrangian(velocity, velocity, dt) + force * dt
    velocity, pressure = phi.fluid.make_incompressible(
        velocity, (), phi.Solve("scipy-CG", 1e-3, 1e-3, max_iterations=3000, x0=pressure, rank_deficiency=0))
    return smoke, velocity, pressure


def simulate_phiflow(box_min, box_max, frames: int, cells: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """PhiFlow's plume (module doc) on ``cells`` (x, y, z): densities (F, nz, ny, nx) and
    cell-centre velocities (F, 3, nz, ny, nx) in m/s, frames 0 .. F-1 at :data:`FPS`."""
    phi = _phiflow()
    nx, ny, nz = cells
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    bounds, closed = _phi_grids(phi, box_min, box_max, cells)
    velocity = phi.StaggeredGrid(0, closed, bounds, x=nx, y=ny, z=nz)
    smoke = phi.CenteredGrid(0, phi.extrapolation.ZERO_GRADIENT, bounds, x=nx, y=ny, z=nz)
    pressure = None
    centre = (lo + hi) / 2
    radius = 0.05 * float(hi[0] - lo[0])
    middle = phi.vec(x=centre[0], y=lo[1] + 0.07 * (hi[1] - lo[1]), z=centre[2])
    mask = phi.CenteredGrid(lambda p: phi.math.exp(-phi.math.squared_norm(p - middle) / (2 * radius ** 2)),
                            phi.extrapolation.ZERO_GRADIENT, bounds, x=nx, y=ny, z=nz)  # a Gaussian ball
    rng = np.random.default_rng(SEED)
    dt = 1.0 / (FPS * SUBSTEPS)
    densities, velocities = [], []
    for f in range(frames):
        rate = 4.0 * (0.6 + 0.8 * rng.random())  # density per second, flickering frame to frame
        for _ in range(SUBSTEPS):
            smoke, velocity, pressure = _phi_step(phi, smoke, velocity, pressure, mask, rate, dt)
        densities.append(smoke.values.numpy("z,y,x"))
        velocities.append(np.moveaxis(velocity.at_centers().values.numpy("z,y,x,vector"), -1, 0))
        print(f"phiflow: frame {f + 1}/{frames}, peak density {densities[-1].max():.3f}, peak speed "
              f"{np.linalg.norm(velocities[-1], axis=0).max():.3f} m/s", flush=True)
    return np.stack(densities).astype(np.float32), np.stack(velocities).astype(np.float32)


def phiflow_step_seconds(density: np.ndarray, velocity: np.ndarray, box_min, box_max, steps: int = 3) -> float:
    """Median seconds of one PhiFlow step (as :func:`simulate_phiflow` takes them, the pressure
    solve started from zero) from a frame's density (nz, ny, nx) and velocity (3, nz, ny, nx)."""
    phi = _phiflow()
    nz, ny, nx = density.shape
    bounds, closed = _phi_grids(phi, box_min, box_max, (nx, ny, nz))
    smoke = phi.CenteredGrid(phi.math.tensor(density.transpose(2, 1, 0), phi.spatial("x,y,z")),
                             phi.extrapolation.ZERO_GRADIENT, bounds)
    centred = phi.CenteredGrid(phi.math.tensor(velocity.transpose(3, 2, 1, 0), phi.spatial("x,y,z"),
                                               phi.channel(vector="x,y,z")), 0, bounds)
    flow = phi.StaggeredGrid(centred, closed, bounds, x=nx, y=ny, z=nz)
    seconds = []
    for _ in range(steps):
        clock = time.perf_counter()
        smoke, flow, _ = _phi_step(phi, smoke, flow, None, smoke * 0, 0.0, 1.0 / (FPS * SUBSTEPS))
        seconds.append(time.perf_counter() - clock)
    return float(np.median(seconds))


def our_step_seconds(density: np.ndarray, velocity: np.ndarray, cells_per_second: np.ndarray, steps: int = 3
                     ) -> tuple[float, float]:
    """Seconds of one step of flamerecon's simulator (semi-Lagrangian, buoyancy, projection) on
    PhiFlow's last frame, (forward, forward and backward through autograd), medians of ``steps``."""
    from flamerecon.dynamics.simulation import Smoke

    x = torch.from_numpy(density[None]).double()
    u = torch.from_numpy(velocity / (cells_per_second.reshape(3, 1, 1, 1) * FPS)).double()
    smoke = Smoke(tuple(density.shape), "+y", 0.05, float(density.max()) or 1.0, pad=8)
    forward, both = [], []
    for _ in range(steps):
        clock = time.perf_counter()
        with torch.no_grad():
            smoke.step(x, u)
        forward.append(time.perf_counter() - clock)
        clock = time.perf_counter()
        leaf = u.clone().requires_grad_(True)
        x_next, _ = smoke.step(x, leaf)
        x_next.sum().backward()
        both.append(time.perf_counter() - clock)
    return float(np.median(forward)), float(np.median(both))


def march(density: np.ndarray, box_min, box_max, K: np.ndarray, world_to_camera: np.ndarray, height: int,
          width: int) -> np.ndarray:
    """(H, W): the integral of the trilinearly interpolated ``density`` (nz, ny, nx), cell
    values at cell centres of the box, along each pixel centre's ray (world units); written
    here with SciPy, independently of flamerecon's projector."""
    from scipy.ndimage import map_coordinates

    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    shape = np.array(density.shape[::-1], float)  # nx, ny, nz
    cell = (hi - lo) / shape
    step = 0.5 * cell.min()
    kji = np.argwhere(density > 1e-4 * density.max())  # below it: under 1e-4 of the peak, left out
    if not kji.size:
        return np.zeros((height, width))
    inner_lo = lo + (kji.min(0)[::-1] - 1).clip(min=0) * cell  # rays are marched through the smoke's box only
    inner_hi = lo + (kji.max(0)[::-1] + 2).clip(max=shape) * cell
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    v, u = np.mgrid[0:height, 0:width]
    pixels = np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)], -1).reshape(-1, 3)
    directions = pixels @ np.linalg.inv(K).T @ R  # R^T d for each row d
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origin = -R.T @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (inner_lo - origin) / directions, (inner_hi - origin) / directions
    near = np.nanmax(np.minimum(a, b), axis=1).clip(min=0)
    far = np.nanmin(np.maximum(a, b), axis=1)
    image = np.zeros(len(pixels))
    hit = np.flatnonzero(far > near)
    count = math.ceil(float((far[hit] - near[hit]).max()) / step) if hit.size else 0
    for chunk in np.array_split(hit, max(1, hit.size // 20000)):
        s = near[chunk, None] + (np.arange(count) + 0.5) * step  # (P, S)
        inside = s < far[chunk, None]
        points = origin + s[..., None] * directions[chunk, None, :]  # (P, S, 3) world
        index = (points - lo) / cell - 0.5  # cell-centre coordinates (x, y, z)
        values = map_coordinates(density, [index[..., 2].ravel(), index[..., 1].ravel(), index[..., 0].ravel()],
                                 order=1, mode="constant", cval=0.0).reshape(s.shape)
        image[chunk] = (values * inside).sum(1) * step
    return image.reshape(height, width)


def cameras_of(scene) -> list[tuple[np.ndarray, np.ndarray]]:
    """(K 3x3, world_to_camera 4x4) of each camera of a flamerecon scene."""
    K = scene.cameras.intrinsics[:, :3, :3].double().numpy()
    E = scene.cameras.extrinsics.double().numpy()
    return list(zip(K, E))


def velocity_errors(u: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """Relative L2 ||u - truth|| / ||truth|| and mean angle (degrees) over ``mask``."""
    e, t, v = (u - truth)[:, mask].double(), truth[:, mask].double(), u[:, mask].double()
    cos = (v * t).sum(0) / (v.norm(dim=0) * t.norm(dim=0)).clamp_min(1e-12)
    return {"rel_l2": float(e.norm() / t.norm().clamp_min(1e-12)),
            "angle_deg": float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).mean())}


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON here")
    parser.add_argument("--frames", type=at_least(2), default=44, help="frames simulated (default 44)")
    parser.add_argument("--pairs", type=at_least(0), nargs=2, default=[14, 28], metavar=("FIRST", "LAST"),
                        help="frame pairs compared: FIRST -> FIRST+1 .. LAST -> LAST+1 (default 14 28)")
    parser.add_argument("--window", type=at_least(1), default=4, help="the simulator's window (default 4)")
    parser.add_argument("--cache", type=output_folder, default=None, help="keep PhiFlow's simulation here")
    parser.add_argument("--speed", action="store_true",
                        help="time one step of PhiFlow and of flamerecon's simulator on the last frame, then stop")
    parser.add_argument("--cells", type=at_least(4), nargs=3, default=[64, 96, 64], metavar=("NX", "NY", "NZ"),
                        help="PhiFlow's cells (default 64 96 64)")
    parser.add_argument("overrides", nargs="*",
                        help="train.py overrides (default scene=scalarflow), flow.KEY=VALUE and simulation.KEY=VALUE")
    args = parse_with_overrides(parser, argv)
    first, last = args.pairs
    if not first <= last or last + 10 >= args.frames or first < args.window:
        parser.error(f"argument --pairs: {first} {last}; give WINDOW <= FIRST <= LAST and LAST + 10 < --frames "
                     f"({args.frames})")

    def run() -> None:
        import dataclasses

        import flamerecon as fr
        from flamerecon.dynamics.assimilation import SimulationOptions, assimilate
        from flamerecon.dynamics.flow import advect, estimate_velocity
        from flamerecon.evaluate.metrics import psnr
        from flamerecon.evaluate.scores import render_scene_views
        from flamerecon.geometry.grid import VoxelGrid
        from flamerecon.operators.warp import sample_points

        flow = flow_options([o for o in args.overrides if o.startswith("flow.")])
        physical = [f"simulation.{key}" for key in PHYSICAL]  # the defaults here; overrides after them win
        simulation = dataclasses.replace(section_options(
            SimulationOptions, "simulation", [*physical, *(o for o in args.overrides if o.startswith("simulation."))]),
            window=args.window)
        given = [o for o in args.overrides if not o.startswith(("flow.", "simulation."))]
        cfg = compose_train([*given, "calibration.refine=none", "ladder.rungs=[]"])
        options = options_from_config(cfg)
        base = load_scene({**cfg.scene, "frame": 0})
        box_min, box_max = base.bbox_min, base.bbox_max
        cells = tuple(args.cells)
        load = os.getloadavg()[0]
        print(f"load average {load:.1f} on {os.cpu_count()} CPUs at the start; PhiFlow {cells} cells in "
              f"{cfg.scene.name}'s box, {args.frames} frames", flush=True)
        started = time.perf_counter()
        cached = args.cache / "plume_phiflow.npz" if args.cache is not None else None
        if cached is not None and cached.is_file():
            with np.load(cached) as f:
                densities, velocities = f["density"], f["velocity"]
        else:
            densities, velocities = simulate_phiflow(box_min, box_max, args.frames, cells)
            if cached is not None:
                np.savez(cached, density=densities, velocity=velocities)
        simulated_s = time.perf_counter() - started
        phi_step = phiflow_step_seconds(densities[-1], velocities[-1], box_min, box_max)
        cell_size = (np.asarray(box_max, float) - np.asarray(box_min, float)) / np.asarray(cells, float)
        ours, ours_grad = our_step_seconds(densities[-1], velocities[-1], cell_size)
        print(f"one step on {cells} cells: PhiFlow {phi_step:.2f} s (NumPy, CG pressure solve); flamerecon's "
              f"simulator {ours:.2f} s, {ours_grad:.2f} s with its gradient (load average {os.getloadavg()[0]:.1f})",
              flush=True)
        if args.speed:
            return
        H, W = base.image_size
        cams = cameras_of(base)
        clock = time.perf_counter()
        needed = range(first - args.window, last + 11)
        clean = {t: np.stack([march(densities[t], box_min, box_max, K, E, H, W) for K, E in cams]) for t in needed}
        scale = 0.8 / max(float(clean[last + 10].max()), 1e-12)
        rng = np.random.default_rng(SEED)
        images = {}
        for t, c in clean.items():
            c = c * scale
            images[t] = np.clip(c + 0.005 * np.sqrt(1 + 4 * c) * rng.standard_normal(c.shape), 0, 1)
        rendered_s = (time.perf_counter() - clock) / len(clean)
        def scene(t: int):
            stack = torch.from_numpy(images[t][:, None]).float().expand(-1, base.images.shape[1], -1, -1)
            return dataclasses.replace(base, name="phiflow_plume", images=stack.contiguous(), masks=None,
                                       response=None, recorded_images=None, source=f"PhiFlow plume frame {t}",
                                       meta={"frame": t, "frame_rate": FPS})

        recs, times = {}, []
        for t in needed:
            clock = time.perf_counter()
            recs[t] = fr.reconstruct(scene(t), options)
            times.append(time.perf_counter() - clock)
            print(f"reconstructed frame {t} in {times[-1]:.1f} s", flush=True)
        grid: VoxelGrid = recs[first].grid
        size = grid.voxel_size().double()
        centres = grid.centers().double()  # (nz, ny, nx, 3) world

        def truth_on_grid(t: int) -> tuple[torch.Tensor, torch.Tensor]:
            """PhiFlow's density (nz, ny, nx) and velocity (3, ...) in cells per frame on the grid."""
            lo = torch.tensor(box_min, dtype=torch.float64)
            cell = (torch.tensor(box_max, dtype=torch.float64) - lo) / torch.tensor(cells, dtype=torch.float64)
            points = ((centres.reshape(-1, 3) - lo) / cell - 0.5).T  # (3, P) in PhiFlow's cells (x, y, z)
            rho = sample_points(torch.from_numpy(densities[t][None]).double(), points, "border")
            u = sample_points(torch.from_numpy(velocities[t]).double(), points, "border")
            u = u / (size[:, None] * FPS)
            return rho.reshape(grid.shape), u.reshape(3, *grid.shape)

        rows, previous = [], None
        clock = time.perf_counter()
        for t in range(first, last + 1):
            rho, truth = truth_on_grid(t)
            mask = rho > 0.05 * rho.max()
            up = truth[1][mask].mean()  # the best uniform upward velocity in least squares
            uniform = torch.zeros_like(truth)
            uniform[1] = up
            pair = estimate_velocity(recs[t].density, recs[t + 1].setup, flow, previous, t)
            previous = pair.control if flow.warm_start else None
            fitted = assimilate([recs[s].density for s in range(t - args.window, t + 1)],
                                [recs[s].setup for s in range(t - args.window + 1, t + 1)], simulation,
                                init=None)
            row = {"frame": t, "flow": velocity_errors(pair.u.double(), truth, mask),
                   "simulation": velocity_errors(fitted.velocity().double(), truth, mask),
                   "uniform": velocity_errors(uniform, truth, mask), "zero_rel_l2": 1.0,
                   "uniform_speed_m_s": float(up * size[1] * FPS),
                   "mean_speed_truth_m_s": float((truth * (size * FPS)[:, None, None, None])[:, mask].norm(dim=0).mean()),
                   "mean_speed_flow_m_s": float((pair.u.double() * (size * FPS)[:, None, None, None])[:, mask]
                                                .norm(dim=0).mean())}
            predictions = {"flow": {k: advect(recs[t].density, pair.u, k) for k in (1, 5, 10)},
                           "simulation": dict(zip((1, 5, 10), [d for n, d in enumerate(
                               fitted.predict(recs[t].density, 10), 1) if n in (1, 5, 10)])),
                           "persistence": {k: recs[t].density for k in (1, 5, 10)}}
            row["predicted"] = {}
            for method, found in predictions.items():
                for k, d in found.items():
                    target, _ = truth_on_grid(t + k)
                    held = recs[t + k].setup.holdout[0]
                    image = render_scene_views(d.float(), grid, recs[t + k].scene, [held], recs[t + k].setup.step)[0]
                    row["predicted"][f"{method}_k{k}"] = {
                        "volume_rel_l2": float((d[0].double() / scale_of(d, target) - target).norm() / target.norm()),
                        "heldout_psnr": float(psnr(image, recs[t + k].scene.images[held]))}
            rows.append(row)
            print(f"pair {t} -> {t + 1}: relative L2 / angle: flow {row['flow']['rel_l2']:.3f} / "
                  f"{row['flow']['angle_deg']:.1f}, simulation {row['simulation']['rel_l2']:.3f} / "
                  f"{row['simulation']['angle_deg']:.1f}, uniform {row['uniform']['rel_l2']:.3f} / "
                  f"{row['uniform']['angle_deg']:.1f} deg", flush=True)
        fitted_s = (time.perf_counter() - clock) / len(rows)
        summary = {m: {k: float(np.mean([r[m][k] for r in rows])) for k in ("rel_l2", "angle_deg")}
                   for m in ("flow", "simulation", "uniform")}
        summary["predicted"] = {key: {s: float(np.mean([r["predicted"][key][s] for r in rows]))
                                      for s in ("volume_rel_l2", "heldout_psnr")} for key in rows[0]["predicted"]}
        print(f"{'velocity':<12} {'relative L2':>11} {'mean angle':>10}   (over the smoke, {len(rows)} frame pairs)")
        print(f"{'zero':<12} {1.0:11.3f} {'-':>10}")
        for m in ("uniform", "flow", "simulation"):
            print(f"{m:<12} {summary[m]['rel_l2']:11.3f} {summary[m]['angle_deg']:10.1f}")
        for key, s in summary["predicted"].items():
            print(f"predicted {key:<16} volume relative L2 {s['volume_rel_l2']:.3f}, held-out {s['heldout_psnr']:.2f} dB")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
        timing = {"phiflow_s": simulated_s, "phiflow_step_s": phi_step, "ours_step_s": ours,
                  "ours_step_with_gradient_s": ours_grad, "render_s_per_frame": rendered_s,
                  "reconstruction_s_per_frame": float(np.mean(times)), "fits_s_per_pair": fitted_s,
                  "peak_rss_gb": peak}
        print(f"PhiFlow {simulated_s:.0f} s ({args.frames} frames), ray marcher {rendered_s:.1f} s per frame, "
              f"reconstruction {timing['reconstruction_s_per_frame']:.1f} s per frame, flow and simulator "
              f"{fitted_s:.1f} s per pair; peak memory {peak:.2f} GB; load average {load:.1f} at the start, "
              f"{os.getloadavg()[0]:.1f} at the end")
        if args.out is not None:
            from flamerecon.outputs.atomic import write_json_atomic

            write_json_atomic(args.out, {"summary": summary, "pairs": rows, "timing": timing,
                                         "frames": args.frames, "window": args.window,
                                         "flow_options": flow.as_dict(), "simulation_options": simulation.as_dict(),
                                         "load_average_start": load})
            print(f"written: {args.out}")

    return run_script(run, args.debug)


def scale_of(density: torch.Tensor, truth: torch.Tensor) -> float:
    """The factor between a reconstructed density and the truth's units: least squares over the grid."""
    d = density[0].double()
    return float((d * truth).sum() / truth.pow(2).sum().clamp_min(1e-30))


if __name__ == "__main__":
    sys.exit(main())
