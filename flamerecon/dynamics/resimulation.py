"""A sequence re-simulated from its first frame, the source re-injected, every frame scored in
every camera.

Frames ``first`` .. ``last`` are reconstructed in turn (:func:`~flamerecon.fit.reconstruct.reconstruct`)
and the velocity of each consecutive pair fitted to the next frame's images
(:func:`~flamerecon.dynamics.flow.estimate_velocity`, warm-started along the sequence). The
re-simulation starts from frame ``first``'s reconstruction and carries it one frame at a time along
these velocities (:meth:`~flamerecon.dynamics.simulation.Smoke.transport`: the velocity projected
divergence-free where ``simulation.incompressible``, the density advected by
``simulation.scheme``), the source re-injected each frame: in the inflow region (the bottom
``simulation.inflow`` of the box along up, where that frame's reconstruction has smoke) the density
becomes the frame's reconstruction there. Nothing else of the later reconstructions enters: what
rises above the source is what the velocities carried there. Each frame is rendered in every
camera and scored against the capture (PSNR, SSIM, detail per view; means over the held-out and
the training views), beside the frame's own reconstruction; ``total`` is each density summed over
the grid (density x cells): how much smoke there is, which a transport alone cannot add to except
through the source.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from flamerecon.device import resolve_device
from flamerecon.dynamics.assimilation import SimulationOptions
from flamerecon.dynamics.conventions import up_of
from flamerecon.dynamics.flow import FlowOptions, estimate_velocity
from flamerecon.dynamics.prediction import Frame, beside_capture, density_series
from flamerecon.dynamics.simulation import Smoke, inflow_region
from flamerecon.evaluate.scores import render_scene_views, score_rendered
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import mean_of, reconstruct
from flamerecon.progress import Progress
from flamerecon.scenes import Scene

METHODS = ("resimulation", "reconstruction")


def camera_scores(density: torch.Tensor, frame: Frame, silhouette: dict) -> dict:
    """``density`` rendered in every camera of ``frame``: {"views": {name: {psnr, ssim,
    detail}}, "heldout_psnr", ..., "train_detail": means over the held-out and training views}."""
    views = frame.train + frame.holdout
    rendered = render_scene_views(density.float(), frame.grid, frame.scene, views, frame.step)
    per_view = score_rendered(rendered, frame.scene, views, silhouette)
    out = {"views": {frame.scene.views[v]: {k: float(per_view[frame.scene.views[v]][k]) for k in ("psnr", "ssim",
                                                                                                   "detail")}
                     for v in views}}
    for side, chosen in (("heldout", frame.holdout), ("train", frame.train)):
        table = {frame.scene.views[v]: per_view[frame.scene.views[v]] for v in chosen}
        out.update({f"{side}_{key}": mean_of(table, key) for key in ("psnr", "ssim", "detail")})
    return out


@dataclass
class ResimulationReport:
    """What :func:`resimulate` found: ``per_frame`` {t: {method: camera scores}}, ``table``
    {method: {score: mean over the frames after the first}}, the flows' records, time and
    memory, and ``kept`` {t: (Frame, resimulated density)} of the frames asked to be kept."""

    per_frame: dict
    table: dict
    flows: list[dict]
    timing: dict
    kept: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"table": self.table, "per_frame": {str(t): row for t, row in self.per_frame.items()},
                "flows": self.flows, "timing": self.timing}


def resimulate(load: Callable[[int], Scene], options: ReconstructionOptions, flow: FlowOptions, first: int,
               last: int, simulation: SimulationOptions | None = None, device: torch.device | str | None = None,
               keep: Callable[[int], bool] = lambda t: False) -> ResimulationReport:
    """Re-simulate frames ``first`` .. ``last`` (module doc); ``load(t)`` gives frame t's scene
    (frame ``last`` is loaded first: a capture too short is refused before any work);
    ``keep(t)``: whether frame t's resimulated density is kept for pictures and files."""
    simulation = simulation or SimulationOptions()
    device = resolve_device(options.device if device is None else str(device))
    load(last)
    silhouette = options.silhouette.as_dict()
    per_frame: dict = {}
    flows, kept = [], {}
    previous_density = resimulated = control = None
    seconds = {"reconstruction": [], "flow": [], "transport": [], "scoring": []}
    progress = Progress("resimulate", last - first + 1, "frame")
    for t in range(first, last + 1):
        clock = time.perf_counter()
        rec = reconstruct(load(t), options, device=device)
        frame = Frame(rec.scene, rec.density.detach(), rec.grid, list(rec.setup.train), list(rec.setup.holdout),
                      rec.setup.step, time.perf_counter() - clock)
        seconds["reconstruction"].append(frame.seconds)
        if previous_density is None:
            resimulated = frame.density
        else:
            pair = estimate_velocity(previous_density, rec.setup, flow, control, t - 1)
            control = pair.control if flow.warm_start else None
            flows.append(pair.record())
            seconds["flow"].append(pair.seconds)
            clock = time.perf_counter()
            up = up_of(rec.scene, simulation.up)
            region = inflow_region(frame.density, up, float(simulation.inflow))
            smoke = Smoke(tuple(frame.grid.shape), up, 0.0, 1.0, region, simulation.scheme, int(simulation.pad),
                          simulation.incompressible)
            with torch.no_grad():
                resimulated = smoke.transport(resimulated, pair.u.to(resimulated), frame.density)
            seconds["transport"].append(time.perf_counter() - clock)
        clock = time.perf_counter()
        per_frame[t] = {name: {**camera_scores(d, frame, silhouette), "total": float(d.sum())}
                        for name, d in (("resimulation", resimulated), ("reconstruction", frame.density))}
        seconds["scoring"].append(time.perf_counter() - clock)
        if keep(t):
            kept[t] = (frame, resimulated)
        previous_density = frame.density
        del rec
        progress.update(t - first + 1, f"frame {t}: held-out {per_frame[t]['resimulation']['heldout_psnr']:.2f} dB "
                                       f"re-simulated, {per_frame[t]['reconstruction']['heldout_psnr']:.2f} dB "
                                       "reconstructed")
    later = [t for t in per_frame if t > first] or list(per_frame)
    table = {m: {s: float(np.mean([per_frame[t][m][s] for t in later]))
                 for s in ("heldout_psnr", "heldout_ssim", "heldout_detail", "train_psnr", "train_ssim", "train_detail")}
             for m in METHODS}
    timing = {f"{k}_s_per_frame": float(np.mean(v)) if v else float("nan") for k, v in seconds.items()}
    timing["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return ResimulationReport(per_frame, table, flows, timing, kept)


def resimulation_pictures(report: ResimulationReport) -> dict[str, np.ndarray]:
    """For each kept frame and held-out view: the view captured, re-simulated and reconstructed
    (:func:`~flamerecon.dynamics.prediction.beside_capture`), by name."""
    out = {}
    for t, (frame, resimulated) in report.kept.items():
        for v in frame.holdout:
            out[f"resimulation_{t:04d}_{frame.scene.views[v]}"] = beside_capture(
                frame, v, t, {"re-simulated": resimulated, "reconstruction": frame.density})
    return out


def resimulation_series(report: ResimulationReport, folder) -> list:
    """``resimulation_fNN.vti`` per kept frame and ``resimulation.pvd`` (time = frame) in ``folder``."""
    if not report.kept:
        return []
    grid = next(iter(report.kept.values()))[0].grid
    return density_series(folder, "resimulation", {t: d for t, (_, d) in report.kept.items()}, grid, "f")
