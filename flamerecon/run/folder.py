"""The run folder, written and read back: density.npz, cameras.json, metrics.json, renders/
and the final TensorBoard entries of a :class:`~flamerecon.fit.reconstruct.Reconstruction`;
:func:`load_run` turns a finished CLI run folder back into objects, :func:`evaluate` re-scores
it in place."""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from flamerecon.arguments import fields, instance, tensor, value
from flamerecon.device import resolve_device
from flamerecon.errors import ConfigError, RunFolderError, output_error
from flamerecon.evaluate.result_warnings import penalty_of, result_warnings
from flamerecon.evaluate.scores import native_scores, score, write_renders
from flamerecon.evaluate.uncertainty import (
    Confidence,
    capture_sigma,
    predicted_psnr,
    save_confidence,
    training_noise,
)
from flamerecon.fit.build import scene_grid, split_views
from flamerecon.fit.checks import check_density_fits
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.pose_uncertainty import offsets_of
from flamerecon.fit.reconstruct import Reconstruction, mean_of
from flamerecon.geometry.cameras import camera_subset
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.outputs.atomic import is_temporary, update_json_atomic, write_json_atomic
from flamerecon.outputs.cameras_file import camera_records, cameras_from_records
from flamerecon.outputs.export import FORMATS, UNCERTAINTY_FILE, load_density, save_density
from flamerecon.outputs.figures import heldout_figure, top_view
from flamerecon.outputs.sweep import FAILED_FILE
from flamerecon.plain import json_value
from flamerecon.rules import integer, list_of
from flamerecon.run.cli import one_line
from flamerecon.run.guard import StopSolve
from flamerecon.run.hook import log_pictures
from flamerecon.run.summary import flat_metrics
from flamerecon.run.tensorboard import RunWriter
from flamerecon.scenes import Scene, load_scene

CONFIG_FILE = Path(".hydra") / "config.yaml"
RUN_LAYER_KEYS = ("scene", "temporal", "debug", "resume", "overwrite", "log", "checkpoint", "export", "hydra",
                  "leave_one_out")
#: what a run writes into its folder (besides TensorBoard's ``events.out.tfevents.*`` and the
#: atomic writers' stale temporaries): what ``overwrite=true`` removes before a new run there
RUN_ENTRIES = frozenset({
    ".hydra", "train.log", "density.npz", "cameras.json", "metrics.json", "renders", "checkpoint.pt", "FAILED",
    "leave_one_out",
    "frames", "multirun.yaml", "density.raw.json", *(f"density.{fmt}" for fmt in FORMATS)})
#: the folders and the log a run writes into (through a symbolic link it would write elsewhere)
RUN_SUBFOLDERS = (".hydra", "renders", "frames", "train.log")
EVENTS_PREFIX = "events.out.tfevents."


def run_entries(folder: Path) -> list[Path]:
    """The entries of ``folder`` a run wrote (:data:`RUN_ENTRIES`, TensorBoard's events, stale
    temporaries of the atomic writers), sorted."""
    return sorted(p for p in folder.iterdir() if p.name in RUN_ENTRIES or p.name.startswith(EVENTS_PREFIX)
                  or is_temporary(p))


def clear_run(folder: Path) -> list[str]:
    """Remove the entries of the run in ``folder`` (:func:`run_entries`; a symbolic link is
    removed, never followed), keeping every other file; returns their names."""
    removed = []
    for entry in run_entries(folder):
        try:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        except OSError as err:
            raise output_error(entry, err) from err
        removed.append(entry.name)
    return removed


def cameras_record(scene: Scene, train: list[int],
                   photometry: dict[str, tuple[float, float]] | None = None) -> list[dict]:
    """cameras.json content (:func:`~flamerecon.outputs.cameras_file.camera_records`): every
    camera of ``scene``; after calibration refinement K and world_to_camera are the refined ones
    and ``K_calibrated``, ``world_to_camera_calibrated`` the scene's own."""
    return camera_records(scene.views, scene.cameras, train, photometry, scene.meta.get("calibrated_cameras"))


def scores(scene: Scene, volume: torch.Tensor, grid: VoxelGrid, train: list[int], holdout: list[int],
           step: float, silhouette: dict, photometry: dict[str, tuple[float, float]] | None = None,
           native_scene: Mapping | None = None, calibration: dict | None = None, *,
           penalty: tuple[float, float | None],
           train_pixels: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[dict, torch.Tensor]:
    """metrics.json's scores of a density (C, nz, ny, nx) and the held-out renders (V, C, H, W).
    With ``native_scene`` (the scene's options) the held-out views are also scored at the
    capture's native resolution (when the run works below it). ``calibration`` (see
    :func:`~flamerecon.fit.reconstruct.calibrated_scene`) is recorded with
    ``train_psnr_after``, this density's training PSNR, and with the cameras' pose offsets
    (:mod:`flamerecon.fit.pose_uncertainty`) the camera whose pose error cost its images most
    (``limiting_camera``, ``limiting_lost_db``). ``warnings``: see
    :func:`~flamerecon.evaluate.result_warnings.result_warnings` (``penalty``: its L1 weights).
    ``train_pixels``: see :func:`~flamerecon.evaluate.scores.score`."""
    metrics, held_imgs = score(scene, volume, grid, train, holdout, step, silhouette, photometry, train_pixels)
    H, W = scene.image_size
    metrics["resolution"] = {"working": [W, H]}
    metrics["scene"] = {"up": scene.up, "up_source": scene.up_source, "unit": scene.unit,
                        "frame_rate": scene.frame_rate}
    if native_scene is not None:
        found = native_scores(native_scene, volume, grid, [scene.views[v] for v in holdout], step)
        if found is not None:
            per_view, size = found
            for name, values in per_view.items():
                metrics["heldout"][name].update(values)
            metrics["resolution"]["native"] = list(size)
    if calibration:
        metrics["calibration"] = {**calibration, "train_psnr_after": mean_of(metrics["train"], "psnr")}
        offsets = offsets_of(calibration)
        if offsets:  # the camera whose pose error cost its images most: the calibration to distrust first
            worst = max(offsets, key=lambda name: offsets[name].lost_db)
            metrics["calibration"].update(limiting_camera=worst, limiting_lost_db=offsets[worst].lost_db)
    metrics["warnings"] = result_warnings(scene, volume, metrics, train + holdout, *penalty, train=train, step=step,
                                          bbox=(grid.bbox_min, grid.bbox_max))
    return metrics, held_imgs


def write_scores(run_dir: Path, metrics: dict, held_imgs: torch.Tensor, scene: Scene, holdout: list[int],
                 sigma: torch.Tensor | None = None) -> None:
    """renders/ (the held-out renders, with their confidence images ``sigma`` when given) and
    metrics.json."""
    write_renders(run_dir, held_imgs, scene, holdout, sigma)
    write_json_atomic(run_dir / "metrics.json", metrics)


def write_confidence(run_dir: Path, conf: Confidence, rec: Reconstruction, held_imgs: torch.Tensor,
                     metrics: dict, writer: RunWriter) -> torch.Tensor:
    """uncertainty.npz (:func:`~flamerecon.evaluate.uncertainty.save_confidence`), each held-out
    view's ``psnr_predicted`` in ``metrics`` (its pose uncertainty and the sensor noise the training
    images show included, :func:`~flamerecon.evaluate.uncertainty.capture_sigma`), its ``uncertainty``
    record (members, scale, shift, noise, seconds; with the cameras' pose uncertainty, ``poses`` per
    camera) and the TensorBoard images ``uncertainty/<view>`` (render |
    captured | error | predicted sigma); returns the held-out confidence images (V, C, H, W), in
    image units."""
    scene, setup = rec.scene, rec.setup
    clock = time.perf_counter()
    save_confidence(run_dir / UNCERTAINTY_FILE, conf, [scene.views[i] for i in setup.train])
    sigma = (conf.image(camera_subset(scene.cameras, setup.holdout), [scene.views[v] for v in setup.holdout]).cpu()
             if setup.holdout else torch.zeros_like(held_imgs))
    noise = training_noise(scene, setup.train)
    against = capture_sigma(scene, held_imgs, sigma, noise)  # the error against the capture: spread and noise
    for k, v in enumerate(setup.holdout):
        metrics["heldout"][scene.views[v]]["psnr_predicted"] = predicted_psnr(against[k])
        scores = metrics["heldout"][scene.views[v]]
        figure = heldout_figure(held_imgs[k], scene.images[v], scene.views[v], scores["psnr"], scores["psnr_black"],
                                sigma[k])
        writer.image(f"uncertainty/{scene.views[v]}", figure, rec.fit.result.iterations, "HWC")
    metrics["uncertainty"] = {"members": conf.labels, "scale": conf.scale, "shift_voxels": conf.shift_voxels,
                              "noise": noise.record(), "seconds": conf.seconds + time.perf_counter() - clock}
    if conf.poses is not None:
        metrics["uncertainty"]["poses"] = conf.poses.records()
    return sigma


def solver_record(rec: Reconstruction, stopped: StopSolve | None) -> dict:
    """metrics.json's ``solver``: name, weights, iterations and time (the solve's and its
    photometry refits' together), status and the records of the grid levels, weight
    selection, photometry (iterations per refit) and debiasing."""
    fit, result = rec.fit, rec.fit.result
    iterations = result.iterations
    if fit.photometry is not None:
        iterations = fit.photometry.solve_iterations + sum(fit.photometry.iterations)
    info = {
        "name": fit.options.solver.name, "l1": fit.l1, "iterations": iterations,
        "seconds": result.seconds, "objective": result.objective, "converged": result.converged,
        "status": "finished" if stopped is None else "diverged", "device": str(result.x.device),
    }
    gaps = [h["rel_gap"] for h in result.history if "rel_gap" in h]
    if gaps:
        info["rel_gap"] = gaps[-1]
    if stopped is not None:
        info["stopped"] = {"iteration": stopped.iteration, "reason": stopped.detail}
    if rec.levels:
        info["levels"] = rec.levels
    info.update({k: v for k, v in (("selection", fit.selection), ("debias", fit.debias)) if v is not None})
    if fit.photometry is not None:
        info["photometry"] = {"rounds": len(fit.photometry.iterations), "iterations": fit.photometry.iterations}
    return info


def write_outputs(run_dir: Path, rec: Reconstruction, scene_options: Mapping, writer: RunWriter,
                  stopped: StopSolve | None = None, confidence: Confidence | None = None) -> dict:
    """density.npz, cameras.json, metrics.json, renders/ and the final TensorBoard entries of
    ``rec``; with its ``confidence`` also uncertainty.npz, the held-out views' predicted PSNR
    and confidence images (see :func:`write_confidence`). Returns the metrics."""
    setup, options, scene = rec.setup, rec.options, rec.scene
    volume = rec.density
    info = solver_record(rec, stopped)
    per_view = rec.fit.photometry.per_view(setup) if rec.fit.photometry is not None else None
    save_density(
        run_dir / "density.npz", volume.cpu(), setup.grid.bbox_min, setup.grid.bbox_max,
        [scene.views[i] for i in setup.train], solver=json.dumps(info), frame=int(scene_options.get("frame", 0)),
    )
    write_json_atomic(run_dir / "cameras.json", {"cameras": cameras_record(scene, setup.train, per_view)})
    metrics, held_imgs = scores(scene, volume, setup.grid, setup.train, setup.holdout, setup.step,
                                options.silhouette.as_dict(), per_view, calibration=rec.calibration,
                                penalty=penalty_of(options.solver.as_dict(), rec.fit.l1),
                                train_pixels=setup.training_pixels(volume))
    metrics["solver"] = info
    sigma = None if confidence is None else write_confidence(run_dir, confidence, rec, held_imgs, metrics, writer)
    write_scores(run_dir, metrics, held_imgs, scene, setup.holdout, sigma)
    for name, values in (rec.calibration or {}).get("cameras", {}).items():
        writer.scalars(0, {k: v for k, v in values.items() if k != "principal_point_px"}, f"calibration/{name}")
    if rec.calibration:
        writer.scalars(0, {k: metrics["calibration"][k] for k in ("train_psnr_before", "train_psnr_after")
                           if k in metrics["calibration"]}, "calibration")
    log_pictures(writer, setup, rec.fit.result.iterations, volume, held_imgs)  # the final renders, not again
    writer.scalars(rec.fit.result.iterations, {f"heldout_{k}": mean_of(metrics["heldout"], k) for k in (
        "detail", "detail_silhouette") if k in next(iter(metrics["heldout"].values()), {})}, "eval")
    writer.image("images/hull_top_view", top_view(setup.hull[None].float(), setup.grid.bbox_min,
                                                  setup.grid.bbox_max, scene.up), 0, "HWC")
    solver = options.solver
    writer.hparams(
        {"scene": scene_options["name"], "solver": solver.name, "l1": rec.fit.l1,
         "grid": str(setup.grid.resolution), "grid_levels": str(list(options.grid.levels)),
         "holdout": ",".join(scene.views[i] for i in setup.holdout),
         **{k: float(solver.params[k]) for k in ("smooth", "tv") if solver.params.get(k) is not None}},
        flat_metrics(metrics),
    )
    return metrics


def run_config(run_dir: str | Path):
    """The config a run folder was made with (``.hydra/config.yaml``, an OmegaConf node)."""
    from omegaconf import OmegaConf

    cfg_path = Path(run_dir) / CONFIG_FILE
    if not cfg_path.is_file():
        raise RunFolderError(f"{cfg_path}: not found; is {run_dir} a flamerecon run folder?")
    return OmegaConf.load(cfg_path)


def run_options(run_dir: str | Path) -> tuple[ReconstructionOptions, dict]:
    """A run folder's :class:`~flamerecon.fit.options.ReconstructionOptions` and its scene options
    (a plain dict), from ``.hydra/config.yaml``."""
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(run_config(run_dir), resolve=True)
    return ReconstructionOptions.from_dict(plain, ignore=RUN_LAYER_KEYS), plain["scene"]


def run_json(path: Path) -> dict:
    """The JSON object of a run's file (cameras.json, metrics.json); {} where it is absent, a
    :class:`~flamerecon.errors.RunFolderError` naming it where it cannot be read."""
    if not path.is_file():
        return {}
    try:
        data = json_value(path.read_text())
    except (OSError, ValueError) as err:
        raise RunFolderError(f"{path}: not a readable JSON file ({one_line(err)}); evaluate a run folder that "
                             "flamerecon wrote whole") from None
    if not isinstance(data, dict):
        raise RunFolderError(f"{path}: top level must be an object, as flamerecon writes it")
    return data


def run_cameras(run_dir: Path, scene: Scene) -> list[dict]:
    """cameras.json's camera records of a run, one for each view of ``scene`` ([] without
    the file); a :class:`~flamerecon.errors.RunFolderError` naming a view it lacks."""
    path = run_dir / "cameras.json"
    cams = run_json(path).get("cameras", [])
    if not isinstance(cams, list) or not all(isinstance(c, dict) and isinstance(c.get("name"), str) for c in cams):
        raise RunFolderError(f"{path}: field 'cameras' must be a list of camera records with a 'name'")
    names = {c["name"] for c in cams}
    missing = [v for v in scene.views if v not in names] if cams else []
    if missing:
        raise RunFolderError(f"{path}: no camera '{missing[0]}' (scene '{scene.name}' has {scene.views}): the file "
                             "does not come from this run; evaluate the folder it was written in")
    return cams


def read_photometry(run_dir: Path, scene: Scene) -> dict[str, tuple[float, float]] | None:
    """{view: (gain, offset)} from a run's cameras.json, None when it has none."""
    cams = run_cameras(run_dir, scene)
    if not cams:
        return None
    return {c["name"]: (float(c.get("gain", 1.0)), float(c.get("offset", 0.0))) for c in cams}


def recorded_calibration(run_dir: Path, scene: Scene) -> tuple[Scene, dict | None]:
    """``scene`` with the refined cameras of a run that refined its calibration (cameras.json's
    K and world_to_camera where it also holds ``K_calibrated``), and metrics.json's
    ``calibration`` record; ``(scene, None)`` for a run without refinement."""
    path = run_dir / "cameras.json"
    cams = run_cameras(run_dir, scene)
    if not cams or "K_calibrated" not in cams[0]:
        return scene, None
    try:
        cameras = cameras_from_records(cams, scene.views, scene.cameras.height, scene.cameras.width, str(path))
    except ConfigError as err:
        raise RunFolderError(str(err)) from None
    record = run_json(run_dir / "metrics.json").get("calibration")
    return replace(scene, cameras=cameras, meta={**scene.meta, "calibrated_cameras": scene.cameras}), record


@dataclass
class Run:
    """A finished run folder as objects (:func:`load_run`)."""

    folder: Path
    options: ReconstructionOptions
    scene_options: dict
    scene: Scene  # with the run's refined cameras when it refined its calibration
    grid: VoxelGrid
    density: torch.Tensor  # (C, nz, ny, nx)
    train: list[int]
    holdout: list[int]
    photometry: dict[str, tuple[float, float]] | None  # {view: (gain, offset)}
    calibration: dict | None
    solver: dict  # density.npz's record of the solve
    metrics: dict  # metrics.json as written ({} when absent)

    def __post_init__(self) -> None:
        fields(self)
        tensor("Run.density", self.density, "(C, nz, ny, nx) on the grid", shape=(None, *self.grid.shape))
        views = list_of(integer(0, self.scene.num_views - 1), what="a list of the scene's view indices")
        for name in ("train", "holdout"):
            value(f"Run.{name}", getattr(self, name), views)

    def score(self, native: bool = False) -> dict:
        """The run's metrics recomputed from its density (as metrics.json has them, less
        ``solver``); with ``native`` also at the capture's native resolution."""
        metrics, _ = self.scores(native)
        return metrics

    def scores(self, native: bool = False) -> tuple[dict, torch.Tensor]:
        return scores(self.scene, self.density, self.grid, self.train, self.holdout,
                      float(self.options.projector.step), self.options.silhouette.as_dict(),
                      self.photometry, self.scene_options if native else None, self.calibration,
                      penalty=penalty_of(self.options.solver.as_dict(), self.solver.get("l1", 0.0)))


def load_run(run_dir: str | Path, device: str = "auto", failed: bool = False) -> Run:
    """A finished CLI run folder (``.hydra/config.yaml``, density.npz, cameras.json,
    metrics.json) back as a :class:`Run`: its options, scene, density and scores. A run that
    failed (its ``FAILED`` file) is a :class:`~flamerecon.errors.RunFolderError` unless
    ``failed`` (a diverged run's density.npz holds its last good iterate)."""
    instance("load_run.run_dir", run_dir, (str, os.PathLike), "the path of a run folder")
    instance("load_run.device", device, (str, torch.device), "a device name (auto, cpu, cuda, cuda:N)")
    instance("load_run.failed", failed, bool, "True or False")
    device = resolve_device(device, "load_run.device")
    run_dir = Path(run_dir)
    if (run_dir / FAILED_FILE).is_file() and not failed:
        lines = (run_dir / FAILED_FILE).read_text(errors="replace").splitlines()
        again = "resume it or run it again" if (run_dir / "checkpoint.pt").is_file() else "run it again"
        raise RunFolderError(f"{run_dir}: the run failed ({lines[0] if lines else 'FAILED'}), it did not finish: "
                             f"{again} (load_run(..., failed=True) loads what it wrote)")
    options, scene_options = run_options(run_dir)
    saved = load_density(run_dir / "density.npz")
    scene, calibration = recorded_calibration(run_dir, load_scene(scene_options))
    train, holdout = split_views(scene, options)
    lo, hi = tuple(saved.bbox_min.tolist()), tuple(saved.bbox_max.tolist())
    nz, ny, nx = saved.density.shape[1:]
    grid = VoxelGrid(lo, hi, (nx, ny, nz))
    check_density_fits(run_dir / "density.npz", saved, scene, scene_grid(options.grid, scene), run_dir / CONFIG_FILE)
    volume = torch.from_numpy(saved.density).to(device)
    with np.load(run_dir / "density.npz") as f:
        solver = json.loads(str(f["solver"])) if "solver" in f.files else {}
    metrics = run_json(run_dir / "metrics.json")
    return Run(run_dir, options, scene_options, scene, grid, volume, train, holdout, read_photometry(run_dir, scene),
               calibration, solver, metrics)


def evaluate(run_dir: str | Path, device: str = "auto", native: bool = True) -> dict:
    """Re-render the views of a finished run from its saved ``density.npz`` and config,
    rewrite the scores in ``metrics.json`` (its other fields, such as the run's ``timing``,
    kept) and ``renders/``; returns the metrics. With ``native`` the held-out
    views are also scored at the capture's native resolution (``scene.downscale=1``)."""
    run = load_run(run_dir, device, failed=True)  # re-scoring what a failed run wrote is asked for by name
    metrics, held_imgs = run.scores(native)
    metrics["solver"] = run.solver
    write_renders(run.folder, held_imgs, run.scene, run.holdout)
    return update_json_atomic(run.folder / "metrics.json", metrics)  # keeps the run's timing
