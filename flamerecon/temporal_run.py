"""``scene.frames=[first,last]``: the run layer of the joint frame solve (:mod:`.temporal`).

Each frame is prepared as a single-frame run would be (its own silhouettes, hull, operator
and weights ``solver.l1_rel`` / ``solver.tv`` relative to its own max(A^T P)), then all are
solved together with the temporal weights of the ``temporal:`` node, relative like the
solver's: w2 = ``temporal.l2`` * mean_t ||A_t||^2 (squared coupling against the data's
curvature), w1 = ``temporal.tv`` * mean_t max(A_t^T P_t) (L1 coupling on the scale of l1).

The run folder holds ``frames/NNNNNN/`` per frame with ``density.npz`` (its ``frame`` field
set), ``cameras.json``, ``metrics.json`` and ``renders/``, which
:func:`~flamerecon.sequence.assemble_sweep` (``scripts/assemble.py RUN_DIR/frames``) reads
like a multirun over frames; the run folder's own ``metrics.json`` holds every frame's views
keyed ``NNNNNN/<view>`` and the joint solve's record.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from .atomic import write_json_atomic
from .debias import debias
from .discretization import Setup
from .errors import ConfigError
from .export import save_density
from .pipeline import calibrated_scene, make_problem, options_from_config, prepare, start_run
from .run_folder import cameras_record, scores, write_scores
from .scenes import load_scene
from .solvers import lambda_max
from .solvers.base import power_norm_sq
from .tb_logging import RunWriter
from .temporal import FrameProblem, JointOptions, JointResult, estimate_shift, solve_joint

FRAMES_FOLDER = "frames"
JOINT_SOLVERS = ("tv", "fista")  # the per-frame objectives the joint solve extends


def frame_range(cfg: DictConfig) -> list[int]:
    """The frames of ``scene.frames=[first,last]`` (inclusive), checked."""
    value = cfg.scene.frames
    items = OmegaConf.to_container(value) if OmegaConf.is_list(value) else value
    if not isinstance(items, list) or len(items) != 2 or not all(isinstance(v, int) for v in items):
        raise ConfigError(f"scene.frames: expected [first, last] (two whole frame numbers), got {items!r}")
    first, last = items
    if last < first or first < 0:
        raise ConfigError(f"scene.frames: need 0 <= first <= last, got [{first}, {last}]")
    return list(range(first, last + 1))


def frame_config(cfg: DictConfig, frame: int) -> DictConfig:
    """``cfg`` for one frame: ``scene.frame`` set, ``scene.frames`` removed."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    plain["scene"].pop("frames", None)
    plain["scene"]["frame"] = frame
    return OmegaConf.create(plain)


def check_supported(cfg: DictConfig) -> None:
    """Refuse what the joint solve does not do (each is one line naming the field)."""
    if cfg.solver.name not in JOINT_SOLVERS:
        raise ConfigError(f"solver.name: scene.frames solves frames jointly with solver=tv or fista "
                          f"(got '{cfg.solver.name}'); use one of them, or one run per scene.frame")
    if list(cfg.grid.get("levels") or []):
        raise ConfigError("grid.levels: not supported with scene.frames; leave grid.levels=[]")
    if cfg.get("init"):
        raise ConfigError("init: not supported with scene.frames; drop init=")
    if (cfg.get("photometry") or {}).get("fit_gain"):
        raise ConfigError("photometry.fit_gain: not supported with scene.frames; set it false")
    if (cfg.get("select") or {}).get("auto"):
        raise ConfigError("select.auto: not supported with scene.frames (one set of weights for all "
                          "frames); set select.auto=false, or choose weights on a single frame")


def joint_options(cfg: DictConfig, frames: list[FrameProblem], norms_sq: list[float]) -> JointOptions:
    """Absolute temporal weights (module doc) and the solver's iteration budget."""
    t = cfg.get("temporal") or {}
    l2, tv = float(t.get("l2", 0.0)), float(t.get("tv", 0.0))
    if l2 < 0 or tv < 0:
        raise ConfigError(f"temporal: weights must be >= 0, got l2={l2}, tv={tv}")
    scale = float(np.mean([lambda_max(f.A, f.b) for f in frames]))
    s = cfg.solver
    step = s.get("dual_step")
    return JointOptions(
        l2=l2 * float(np.mean(norms_sq)), tv=tv * scale, max_iters=int(s.get("max_iters", 300)),
        tol=float(t.get("tol", 1e-5)), check_every=int(s.get("check_every", 10)),
        dual_step=float(step) if step is not None else max(0.1, (float(s.get("tv", 0.0)) / 1e-3) ** 0.5),
        max_seconds=s.get("max_seconds"),
    )


@dataclass
class PreparedFrames:
    """Every frame of ``scene.frames`` built as a single-frame run would be (one entry each)."""

    numbers: list[int]
    configs: list[DictConfig]
    setups: list[Setup]
    problems: list[FrameProblem]
    l1s: list[float]
    norms_sq: list[float]  # ||A_t||^2 by power iteration
    calibrations: list[dict | None]  # each frame's calibration.refine record (None when off)


def prepare_frames(cfg: DictConfig, device: torch.device) -> PreparedFrames:
    """Scene, silhouettes, hull, operator and absolute weights of each frame (same grid box)."""
    numbers = frame_range(cfg)
    configs = [frame_config(cfg, t) for t in numbers]
    setups, frames, l1s, calibrations = [], [], [], []
    for fcfg in configs:
        scene, calibration = calibrated_scene(fcfg, load_scene(fcfg.scene), device)
        calibrations.append(calibration)
        setup = prepare(fcfg, scene, device)
        if setups and (setup.grid.resolution != setups[0].grid.resolution
                       or setup.grid.bbox_min != setups[0].grid.bbox_min
                       or setup.grid.bbox_max != setups[0].grid.bbox_max):
            raise ConfigError(f"scene.frames: frame {fcfg.scene.frame} has another grid box than frame "
                              f"{numbers[0]}; set grid.bbox to one box for all frames")
        _, _, l1 = make_problem(fcfg, setup)
        mu = float(fcfg.solver.get("tv", 0.0) or 0.0) * lambda_max(setup.operator, setup.pixels) \
            if cfg.solver.name == "tv" else 0.0
        frames.append(FrameProblem(setup.operator, setup.pixels, l1, mu, setup.grid.shape, setup.voxel_index))
        setups.append(setup)
        l1s.append(l1)
    norms_sq = [power_norm_sq(f.A, int(f.voxel_index.numel()), device, f.b.dtype) for f in frames]
    return PreparedFrames(numbers, configs, setups, frames, l1s, norms_sq, calibrations)


def solve_frames(prepared: PreparedFrames, opts: JointOptions, motion: str = "none",
                 max_shift: int = 3, callback=None) -> tuple[JointResult, list[tuple[int, int, int]] | None]:
    """The joint solve; with ``motion="shift"`` first the uncoupled solve, then one whole-cell
    shift per neighbouring pair estimated from its densities (:func:`~.temporal.estimate_shift`),
    then the coupled solve along those shifts from the uncoupled solution. Returns the result
    (seconds: both solves) and the shifts (None without motion)."""
    if motion == "none":
        return solve_joint(prepared.problems, opts, norms_sq=prepared.norms_sq, callback=callback), None
    if motion != "shift":
        raise ConfigError(f"temporal.motion: unknown '{motion}'; use none or shift")
    free = solve_joint(prepared.problems, replace(opts, l2=0.0, tv=0.0), norms_sq=prepared.norms_sq)
    volumes = [s.volume(x).mean(0) for s, x in zip(prepared.setups, free.xs)]
    shifts = [estimate_shift(a, b, max_shift) for a, b in pairwise(volumes)]
    result = solve_joint(prepared.problems, opts, x0=free.xs, norms_sq=prepared.norms_sq,
                         callback=callback, shifts=shifts)
    result.seconds += free.seconds
    return result, shifts


def reconstruct_frames(cfg: DictConfig, run_dir: str | Path, resume: bool = False) -> dict:
    """Prepare every frame of ``scene.frames``, solve them jointly, write the run folder (module
    doc); returns the combined metrics (views keyed ``NNNNNN/<view>``)."""
    if resume:
        raise ConfigError("resume: a joint solve over scene.frames keeps no checkpoint; run it again")
    check_supported(cfg)
    run_dir, device = start_run(cfg, run_dir)
    prepared = prepare_frames(cfg, device)
    numbers, configs, setups, frames = prepared.numbers, prepared.configs, prepared.setups, prepared.problems
    l1s, norms_sq = prepared.l1s, prepared.norms_sq
    opts = joint_options(cfg, frames, norms_sq)
    writer = RunWriter(str(run_dir))
    try:
        t_cfg = cfg.get("temporal") or {}
        result, shifts = solve_frames(
            prepared, opts, str(t_cfg.get("motion", "none")), int(t_cfg.get("max_shift", 3)),
            lambda it, xs, info: writer.scalars(it, {k: v for k, v in info.items() if isinstance(v, float)}))
        temporal = {"frames": [numbers[0], numbers[-1]], "l2": opts.l2, "tv": opts.tv,
                    "l2_rel": float((cfg.get("temporal") or {}).get("l2", 0.0)),
                    "tv_rel": float((cfg.get("temporal") or {}).get("tv", 0.0)),
                    "coupled_on": "pairwise intersection of neighbouring frames' hulls",
                    "shifts": shifts}
        combined: dict = {"heldout": {}, "train": {}, "frames": {}}
        for t, fcfg, setup, x, l1, calibration in zip(numbers, configs, setups, result.xs, l1s,
                                                      prepared.calibrations):
            combined["frames"][f"{t:06d}"] = write_frame(
                fcfg, run_dir / FRAMES_FOLDER / f"{t:06d}", setup, x, l1, result, temporal, calibration)
            for part in ("heldout", "train"):
                for view, values in combined["frames"][f"{t:06d}"][part].items():
                    combined[part][f"{t:06d}/{view}"] = values
            writer.scalars(t, {"heldout_psnr": float(np.mean(
                [v["psnr"] for v in combined["frames"][f"{t:06d}"]["heldout"].values()] or [np.nan]))},
                prefix="eval/frame")
    finally:
        writer.close()
    combined["solver"] = {
        "name": f"{cfg.solver.name}+temporal", "l1": float(np.mean(l1s)), "iterations": result.iterations,
        "seconds": result.seconds, "objective": result.objective, "converged": result.converged,
        "status": "finished", "device": str(device), "temporal": temporal,
    }
    combined["resolution"] = next(iter(combined["frames"].values()))["resolution"]
    write_json_atomic(run_dir / "metrics.json", combined)
    return combined


def write_frame(cfg: DictConfig, folder: Path, setup: Setup, x: torch.Tensor, l1: float,
                result: JointResult, temporal: dict, calibration: dict | None = None) -> dict:
    """One frame's density.npz, cameras.json, metrics.json and renders/ in ``folder``, after the
    run's ``debias`` step (each frame its own gain); ``calibration``: the frame's refinement."""
    folder.mkdir(parents=True, exist_ok=True)
    options = options_from_config(cfg)
    x, debiased = debias(options.debias, setup.operator, setup.pixels, x)
    volume = setup.volume(x)
    info = {"name": cfg.solver.name, "l1": l1, "iterations": result.iterations,
            "seconds": result.seconds, "objective": result.objective,
            "converged": result.converged, "status": "finished", "device": str(x.device),
            "temporal": temporal, "debias": debiased}
    scene = setup.scene
    save_density(folder / "density.npz", volume.cpu(), setup.grid.bbox_min, setup.grid.bbox_max,
                 [scene.views[i] for i in setup.train], frame=int(cfg.scene.frame),
                 solver=json.dumps(info))
    write_json_atomic(folder / "cameras.json", {"cameras": cameras_record(scene, setup.train)})
    metrics, held_imgs = scores(scene, volume, setup.grid, setup.train, setup.holdout, setup.step,
                                options.silhouette.as_dict(), calibration=calibration)
    metrics["solver"] = info
    write_scores(folder, metrics, held_imgs, scene, setup.holdout)
    return metrics
