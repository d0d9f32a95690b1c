"""Future frames predicted from a reconstructed sequence and scored in the cameras.

Frames ``first - 1`` .. ``last + max(horizons)`` of a capture are reconstructed in turn
(:func:`~flamerecon.fit.reconstruct.reconstruct`), the velocity of each consecutive pair fitted
to the next frame's images (:func:`~flamerecon.dynamics.flow.estimate_velocity`, warm-started along
the sequence). From each frame t in [first, last], frame t+k is predicted for every horizon k
by

- ``flow``: frame t's density carried k frames by u_t, the velocity fitted from t to t+1
  (:func:`~flamerecon.dynamics.flow.advect`);
- ``flow_causal``: the same with u_{t-1}, fitted from t-1 to t: a prediction that uses nothing
  after frame t (only where frame t-1 is in the capture);
- ``persistence``: frame t's density unchanged;
- ``shift``: frame t's density moved up by k times one speed fitted to the whole stretch of
  frames reconstructed (the speed, cells per frame, whose uniform shift explains the next
  frames' images best summed over every pair, searched on ``speeds``);
- ``simulation``: frame t carried k frames by the buoyant, incompressible smoke simulator fitted
  to the images of frames t - W + 1 .. t (:func:`~flamerecon.dynamics.assimilation.assimilate`,
  W = ``simulation.window``, started from the flow of frames t - W -> t - W + 1), its source
  held at frame t's: as ``flow_causal``, nothing after frame t is used;
- ``reconstruction``: frame t+k's own reconstruction (what the cameras allow, not a prediction);
- ``flow:<name>``: ``flow`` with other options (``variants``), to compare settings,

and each is rendered in every camera of frame t+k and scored against what it captured: PSNR,
SSIM and detail correlation, means over the held-out views (``heldout_*``) and over the
training views (``train_*``), :mod:`flamerecon.evaluate.scores`.
"""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from flamerecon.device import resolve_device
from flamerecon.dynamics.assimilation import Assimilation, SimulationOptions, assimilate
from flamerecon.dynamics.conventions import up_of
from flamerecon.dynamics.flow import (
    FlowOptions,
    PairFlow,
    advect,
    estimate_velocity,
    shift_residuals,
    smoke_mask,
    uniform_velocity,
)
from flamerecon.evaluate.scores import render_scene_views, score_rendered
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import mean_of, reconstruct
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.progress import Progress
from flamerecon.scenes import Scene

METHODS = ("flow", "flow_causal", "simulation", "persistence", "shift", "reconstruction")
SCORES = ("heldout_psnr", "heldout_ssim", "heldout_detail", "train_psnr", "train_ssim", "train_detail")
#: the uniform shifts searched, cells per frame
SPEEDS = tuple(round(0.05 * i, 2) for i in range(61))


@dataclass
class Frame:
    """One reconstructed frame: its scene (calibrated cameras), density (C, nz, ny, nx) on
    ``grid``, training and held-out view indices, and the seconds it took."""

    scene: Scene
    density: torch.Tensor
    grid: VoxelGrid
    train: list[int]
    holdout: list[int]
    step: float
    seconds: float


def view_scores(density: torch.Tensor, frame: Frame, silhouette: dict) -> dict[str, float]:
    """:data:`SCORES` of ``density`` rendered in every camera of ``frame`` (means over its
    held-out and its training views)."""
    views = frame.train + frame.holdout
    rendered = render_scene_views(density.float(), frame.grid, frame.scene, views, frame.step)
    per_view = score_rendered(rendered, frame.scene, views, silhouette)
    held = {frame.scene.views[v]: per_view[frame.scene.views[v]] for v in frame.holdout}
    train = {frame.scene.views[v]: per_view[frame.scene.views[v]] for v in frame.train}
    return {f"{side}_{key}": mean_of(table, key) for side, table in (("heldout", held), ("train", train))
            for key in ("psnr", "ssim", "detail")}


def velocity_error(u: torch.Tensor, truth: torch.Tensor, density: torch.Tensor) -> dict[str, float]:
    """``rel_l2`` ||u - truth|| / ||truth|| and the mean angle between them (``angular_deg``)
    over the smoke of ``density`` (1 % of its peak), both (3, nz, ny, nx)."""
    mask = smoke_mask(density).to(u.device)
    e, t, v = (u - truth)[:, mask].double(), truth[:, mask].double(), u[:, mask].double()
    cos = (v * t).sum(0) / (v.norm(dim=0) * t.norm(dim=0)).clamp_min(1e-12)
    return {"rel_l2": float(e.norm() / t.norm().clamp_min(1e-12)),
            "angular_deg": float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).mean())}


@dataclass
class PredictionReport:
    """What :func:`predict_sequence` found: ``table`` {k: {method: {score: mean over frames}}},
    ``per_frame`` {t: {k: {method: scores}}}, the uniform ``shift`` speed (cells per frame),
    the flows' records, the velocity errors against a known truth, and time and memory."""

    table: dict
    per_frame: dict
    shift: float
    flows: list[dict]
    velocity_errors: list[dict] = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    first: dict = field(default_factory=dict)  # frame ``first``: its Frame, velocity u (cells/frame), predictions
    simulations: list[dict] = field(default_factory=list)  # each start frame's assimilation record
    simulation_velocity_errors: list[dict] = field(default_factory=list)  # its velocity at the start frame

    def as_dict(self) -> dict:
        """The JSON ``scripts/predict.py`` writes: ``horizons`` {"k": {method: {score: value}}}
        and the rest beside it."""
        out = {"horizons": {str(k): v for k, v in self.table.items()}, "shift_cells_per_frame": self.shift,
               "per_frame": {str(t): {str(k): v for k, v in row.items()} for t, row in self.per_frame.items()},
               "flows": self.flows, "simulations": self.simulations, "timing": self.timing}
        for key, errors in (("velocity_error", self.velocity_errors),
                            ("simulation_velocity_error", self.simulation_velocity_errors)):
            if errors:
                out[key] = {"rel_l2": float(np.mean([e["rel_l2"] for e in errors])),
                            "angular_deg": float(np.mean([e["angular_deg"] for e in errors])), "per_pair": errors}
        return out


def predict_sequence(load: Callable[[int], Scene], options: ReconstructionOptions, flow: FlowOptions,
                     first: int, last: int, horizons: Sequence[int], device: torch.device | str | None = None,
                     true_velocity: Callable[[VoxelGrid], torch.Tensor] | None = None,
                     speeds: Sequence[float] = SPEEDS, variants: Mapping[str, FlowOptions] | None = None,
                     simulation: SimulationOptions | None = None,
                     simulation_variants: Mapping[str, SimulationOptions] | None = None) -> PredictionReport:
    """Predictions from frames ``first`` .. ``last`` (module doc); ``load(t)`` gives frame t's
    scene (frame ``last`` + the longest horizon is loaded first, so that a capture too short is
    refused before any reconstruction); ``true_velocity(grid)`` (cells per frame), when the
    truth is known, is compared with every fitted velocity; ``variants`` {name: options}: more
    flows, each its own method ``flow:<name>`` (the same frames, baselines and scores: a
    comparison of settings); ``simulation``: the simulator's options (None: no ``simulation``
    method), ``simulation_variants`` {name: options}: more, each its own method
    ``simulation:<name>``. Progress is logged per frame."""
    device = resolve_device(options.device if device is None else str(device))
    horizon = max(horizons)
    sims = {} if simulation is None else {"simulation": simulation, **{
        f"simulation:{name}": o for name, o in (simulation_variants or {}).items()}}
    window = max([int(o.window) for o in sims.values()], default=0)
    start = max(first - max(window, 1), 0)
    load(last + horizon)  # the capture's end, before any work
    frames: dict[int, Frame] = {}
    chains = {"flow": flow, **{f"flow:{name}": o for name, o in (variants or {}).items()}}
    fitted: dict[str, dict[int, PairFlow]] = {name: {} for name in chains}
    pairs = fitted["flow"]
    curves: list[list[float]] = []
    errors: list[dict] = []
    simulated_errors: list[dict] = []
    setups: dict[int, object] = {}  # the last ``window`` frames' setups, while a simulation may start there
    fits: dict[str, dict[int, Assimilation]] = {name: {} for name in sims}
    progress = Progress("predict: reconstructions and flows", last + horizon - start + 1, "frame")
    previous: dict[str, torch.Tensor | None] = dict.fromkeys(chains)
    up = up_of(None, flow.up)
    for t in range(start, last + horizon + 1):
        clock = time.perf_counter()
        rec = reconstruct(load(t), options, device=device)
        setup = rec.setup
        up = up_of(rec.scene, flow.up)
        frames[t] = Frame(rec.scene, rec.density.detach(), rec.grid, list(setup.train), list(setup.holdout),
                          setup.step, time.perf_counter() - clock)
        if t - 1 in frames:
            source = frames[t - 1].density
            if t - 1 <= last:  # the velocities the predictions use (and their warm-start chain)
                for name, chosen in chains.items():
                    pair = estimate_velocity(source, setup, chosen, previous[name], t - 1)
                    fitted[name][t - 1], previous[name] = pair, (pair.control if chosen.warm_start else None)
                pair = pairs[t - 1]
                if true_velocity is not None:
                    errors.append({"frame": t - 1, **velocity_error(pair.u, true_velocity(rec.grid).to(pair.u),
                                                                    source)})
            curves.append(shift_residuals(source, setup, speeds, up))
        if sims and t <= last:
            setups[t] = setup
            setups.pop(t - window, None)
            for name, chosen in sims.items():
                span = min(int(chosen.window), t - start)
                if t >= first and span >= 1:  # frames t - span .. t: nothing after t
                    init = pairs[t - span].control if t - span in pairs else None
                    fits[name][t] = assimilate([frames[s].density for s in range(t - span, t + 1)],
                                               [setups[s] for s in range(t - span + 1, t + 1)],
                                               replace(chosen, window=span), init)
            if true_velocity is not None and t in fits["simulation"]:
                simulated_errors.append({"frame": t, **velocity_error(
                    fits["simulation"][t].velocity().float(), true_velocity(rec.grid).to(pairs[t - 1].u),
                    frames[t].density)})
        del rec, setup
        seconds = sum(f[t].record["seconds"] for f in fits.values() if t in f)
        progress.update(t - start + 1, f"frame {t}: {frames[t].seconds:.1f} s"
                        + (f", flow {pairs[t - 1].seconds:.1f} s" if t - 1 in pairs else "")
                        + (f", simulations {seconds:.1f} s" if seconds else ""))
    setups.clear()
    shift = float(speeds[int(np.argmin(np.sum(curves, 0)))])
    methods = [*METHODS, *list(chains)[1:], *list(sims)[1:]]
    table: dict = {k: {m: {s: [] for s in SCORES} for m in methods} for k in horizons}
    per_frame: dict = {}
    first_frame: dict = {}
    silhouette = options.silhouette.as_dict()
    scoring = Progress("predict: scoring", last - first + 1, "frame")
    simulated_seconds = []
    for n, t in enumerate(range(first, last + 1)):
        x = frames[t].density
        per_frame[t] = {}
        simulated: dict[str, dict[int, torch.Tensor]] = {}
        latest = pairs[t - 1].u if t - 1 in pairs else None  # the latest flow: nothing after t
        for name, found_fits in fits.items():
            if t in found_fits:
                clock = time.perf_counter()
                simulated[name] = {k + 1: d for k, d in enumerate(found_fits[t].predict(x, horizon, latest))
                                   if k + 1 in horizons}
                simulated_seconds.append((time.perf_counter() - clock) / horizon)
        for k in horizons:
            shape = tuple(x.shape[1:])
            found = {"flow": advect(x, pairs[t].u, k), "persistence": x,
                     "shift": advect(x, uniform_velocity(shape, shift, up, x.device), k),
                     "reconstruction": frames[t + k].density}
            if t - 1 in pairs:
                found["flow_causal"] = advect(x, pairs[t - 1].u, k)
            found.update({name: ahead[k] for name, ahead in simulated.items()})
            found.update({name: advect(x, fitted[name][t].u, k) for name in list(chains)[1:]})
            per_frame[t][k] = {m: view_scores(d, frames[t + k], silhouette) for m, d in found.items()}
            if t == first:
                first_frame.setdefault("predictions", {})[k] = found
            for m, scores in per_frame[t][k].items():
                for s, v in scores.items():
                    table[k][m][s].append(v)
        if t == first:
            first_frame.update({"frame": frames[t], "u": pairs[t].u, "targets": {k: frames[t + k] for k in horizons}})
        scoring.update(n + 1, f"frame {t}")
    means = {k: {m: {s: float(np.mean(v)) for s, v in row.items()} for m, row in rows.items() if row["heldout_psnr"]}
             for k, rows in table.items()}
    cold = [p.seconds for p in pairs.values() if not p.warm]
    warm = [p.seconds for p in pairs.values() if p.warm]
    timing = {"reconstruction_s_per_frame": float(np.mean([f.seconds for f in frames.values()])),
              "flow_s_per_pair_warm": float(np.mean(warm)) if warm else math.nan,
              "flow_s_per_pair_cold": float(np.mean(cold)) if cold else math.nan,
              "simulation_fit_s_per_start_frame": (float(np.mean([f.record["seconds"] for f in fits["simulation"].values()]))
                                                   if fits.get("simulation") else math.nan),
              "simulation_s_per_frame_ahead": float(np.mean(simulated_seconds)) if simulated_seconds else math.nan,
              "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}
    records = [{**pairs[t].record(), **{f"{name}:residual": fitted[name][t].residual for name in list(chains)[1:]},
                **{f"{name}:relative_divergence": fitted[name][t].relative_divergence for name in list(chains)[1:]}}
               for t in sorted(pairs)]
    simulations = [{"method": name, "frame": t, **found[t].record} for name, found in fits.items() for t in sorted(found)]
    return PredictionReport(means, per_frame, shift, records, errors, timing, first_frame, simulations,
                            simulated_errors)


def prediction_pictures(report: PredictionReport, frame_rate: float | None, speed_unit: str = "world units/s",
                        length_unit: str = "units") -> dict[str, np.ndarray]:
    """The pictures of the first frame of ``report`` (H, W, 3) uint8 by name: its velocity's
    slices and streamlines (``speed_unit`` at ``frame_rate``, else cells per frame), and for
    each horizon and held-out view, the view captured beside every prediction (one brightness
    scale, the capture's peak white; each prediction titled with its PSNR)."""
    from flamerecon.dynamics.flow import cells_to_world
    from flamerecon.outputs.flow_figures import streamlines_figure, velocity_slices_figure

    found = report.first
    frame = found["frame"]
    t = int(frame.scene.meta.get("frame", 0))
    world = frame_rate is not None
    u = cells_to_world(found["u"], frame.grid, frame_rate) if world else found["u"]
    unit = f" ({speed_unit})" if world else " (cells, per frame)"
    args = (frame.density.cpu().numpy(), u.cpu().numpy(), frame.grid.bbox_min, frame.grid.bbox_max)
    up = frame.scene.up
    out = {f"velocity_slices_{t:04d}": velocity_slices_figure(*args, f"frame {t} -> {t + 1}{unit}", length_unit,
                                                              up=up),
           f"streamlines_{t:04d}": streamlines_figure(*args, f"frame {t}{unit}", length_unit, up=up)}
    for k, predictions in found["predictions"].items():
        target = found["targets"][k]
        named = {(m if m == "reconstruction" else f"{m}, {k} ahead"): d for m, d in predictions.items()}
        for v in target.holdout:
            out[f"predictions_{t:04d}_k{k:02d}_{target.scene.views[v]}"] = beside_capture(target, v, t + k, named)
    return out


def beside_capture(target: Frame, view: int, number: int, densities: Mapping[str, torch.Tensor]) -> np.ndarray:
    """(H, W, 3) uint8: camera ``view`` of frame ``target`` (frame ``number``) as captured,
    then each of ``densities`` {label: (C, nz, ny, nx)} rendered there, one brightness scale
    (the capture's peak white), each titled with its label and PSNR."""
    from flamerecon.evaluate.metrics import psnr
    from flamerecon.outputs.figures import montage, to_rgb8

    captured = target.scene.images[view]
    top = float(captured.max().clamp_min(1e-6))
    tiles = [to_rgb8(captured, top)]
    labels = [f"captured {target.scene.views[view]}, frame {number} (peak = white)"]
    for label, density in densities.items():
        image = render_scene_views(density.float(), target.grid, target.scene, [view], target.step)[0]
        tiles.append(to_rgb8(image, top))
        labels.append(f"{label}: {psnr(target.scene.to_recorded(image), target.scene.recorded_view(view)):.2f} dB")
    return montage(tiles, len(tiles), labels)


def prediction_series(report: PredictionReport, folder, method: str = "simulation") -> list:
    """``.vti`` files of the first frame's ``method`` prediction and the reconstruction at each
    horizon (``{method}_k{k}.vti``, ``reconstruction_k{k}.vti``) and a ``.pvd`` index per
    method (time = frames ahead) in ``folder``; the paths written."""
    found, written = report.first, []
    for name in (method, "reconstruction"):
        entries = {k: p[name] for k, p in found["predictions"].items() if name in p}
        written += density_series(folder, name, entries, found["frame"].grid, "k")
    return written


def density_series(folder, name: str, densities: Mapping[int, torch.Tensor], grid: VoxelGrid, tag: str) -> list:
    """``{name}_{tag}{n:02d}.vti`` per density (C, nz, ny, nx) of ``densities`` {n: density} and
    their ``{name}.pvd`` index (time = n) in ``folder``; the paths written ([] for none)."""
    from pathlib import Path

    from flamerecon.outputs.export import write_pvd, write_vti

    folder, written, entries = Path(folder), [], []
    for n, density in densities.items():
        file = write_vti(folder / f"{name}_{tag}{n:02d}.vti", density.cpu().numpy(), grid.bbox_min, grid.bbox_max)
        entries.append((n, file.name))
        written.append(file)
    return [*written, write_pvd(folder / f"{name}.pvd", entries)] if entries else []
