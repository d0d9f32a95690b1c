"""The run layer's reconstruction: ``reconstruct(cfg, run_dir)`` converts the Hydra config to
:class:`~flamerecon.fit.options.ReconstructionOptions` once, runs the core's one path
(:func:`flamerecon.fit.reconstruct.reconstruct`) through the run folder's hook
(:class:`~flamerecon.run.hook.RunHook`: TensorBoard, checkpoints, resume, divergence guard)
and writes the run folder (:mod:`flamerecon.run.folder`).

The functions below :func:`reconstruct_in` take a config where the core takes options: thin
adapters for the scripts and tools that hold a Hydra config (leave-one-out, joint frames).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from flamerecon.device import resolve_device
from flamerecon.errors import ConfigError, SolveDiverged
from flamerecon.fit import reconstruct as core
from flamerecon.fit.build import Setup, build
from flamerecon.fit.ensemble import confidence
from flamerecon.fit.option_rules import check_options
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import Photometry, mean_of
from flamerecon.fit.refine_cameras import RefineOptions
from flamerecon.machine import peak_memory
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.outputs.export import check_exporters, export_run
from flamerecon.outputs.mesh import DEFAULT_ISO
from flamerecon.run.checkpoint import CHECKPOINT_FILE, load_checkpoint
from flamerecon.run.config import options_from_config, start_run
from flamerecon.run.folder import (
    cameras_record,
    evaluate,
    run_config,
    write_outputs,
)
from flamerecon.run.hook import RunHook, RunOptions, Watch
from flamerecon.run.lock import run_lock
from flamerecon.run.summary import flat_metrics, summary_table
from flamerecon.run.tensorboard import RunWriter
from flamerecon.scenes import Scene, load_scene
from flamerecon.solvers import Problem, Solver, SolveResult

log = logging.getLogger(__name__)

__all__ = ["Photometry", "Setup", "calibrated_scene", "cameras_record", "choose_weights", "evaluate",
           "flat_metrics", "make_problem", "mean_of", "options_from_config", "prepare", "reconstruct", "refine_options",
           "resolve_device", "run_config", "solve", "solver_options", "summary_table", "warm_start"]


def solver_options(cfg: DictConfig) -> dict:
    """The solver's own keyword options of a config (``solver.*`` less name and weights)."""
    return dict(options_from_config(cfg).solver.params)


def refine_options(cfg: DictConfig) -> RefineOptions:
    """The ``calibration:`` node of a config as :class:`~flamerecon.fit.refine_cameras.RefineOptions`."""
    return options_from_config(cfg).calibration


def run_options(cfg: DictConfig) -> RunOptions:
    """The ``log:`` and ``checkpoint:`` nodes as :class:`~flamerecon.run.hook.RunOptions` (an
    absent key keeps its default there)."""
    log, ck = cfg.get("log") or {}, cfg.get("checkpoint") or {}
    where = {"eval_every": (log, "eval_every"), "eval_share": (log, "eval_share"),
             "checkpoint_every": (ck, "every"), "divergence_factor": (ck, "divergence_factor")}
    return RunOptions(**{field: node[key] for field, (node, key) in where.items() if key in node})


def reconstruct(cfg: DictConfig, run_dir: str | Path, resume: bool = False, watch: Watch | None = None,
                announce: str | None = None) -> dict:
    """:func:`reconstruct_in` after checking every option of ``cfg``
    (:func:`~flamerecon.fit.option_rules.check_options`), holding ``run_dir``'s lock
    (:func:`~flamerecon.run.lock.run_lock`: a second writer is refused)."""
    check_options(OmegaConf.to_container(cfg, resolve=True))
    check_exporters(cfg.get("export", {}).get("formats", []))
    with run_lock(run_dir):
        return reconstruct_in(cfg, run_dir, resume, watch, announce)


def reconstruct_in(cfg: DictConfig, run_dir: str | Path, resume: bool = False, watch: Watch | None = None,
                   announce: str | None = None) -> dict:
    """Run the whole reconstruction for ``cfg`` and write the run folder; returns metrics.json's
    dict.

    With ``grid.levels`` the coarse grids are solved first, each logged to TensorBoard under
    the tag prefix ``level<i>/`` and recorded in metrics.json's ``solver.levels``; the final
    grid logs under the usual tags. With ``resume`` the reconstruction continues from
    ``run_dir/checkpoint.pt``, in the solve it was written in (a coarse level, the final grid
    or a photometry refit). Raises :class:`~flamerecon.errors.Interrupted` after
    checkpointing on SIGINT/SIGTERM, and :class:`~flamerecon.errors.SolveDiverged` after
    writing the last good iterate's outputs (a coarse level that diverges writes none).
    ``watch``: see :class:`~flamerecon.run.hook.RunHook`; ``announce``: printed once the
    checks made before any work have passed (the runner's composed config).
    """
    if cfg.scene.get("frames") is not None:  # consecutive frames solved jointly (time as a prior)
        from flamerecon.run.joint_frames import run_frames

        if cfg.get("uncertainty", {}).get("enabled"):
            raise ConfigError("uncertainty.enabled: the confidence is computed for one frame's reconstruction, "
                              "not for scene.frames solved jointly; run the frames one by one, or leave it off")

        return logged(run_frames(cfg, run_dir, resume, announce))
    options = in_sweep(options_from_config(cfg))
    core.check_solver_name(options.solver.name)
    run_dir, device = start_run(cfg, run_dir)
    ckpt = load_checkpoint(run_dir) if resume else None
    clock = time.perf_counter()
    scene = load_scene(cfg.scene)
    timing = {"scene": time.perf_counter() - clock}
    plan = [level.plan_entry() for level in core.levels_of(scene, options)]
    writer = RunWriter(str(run_dir))
    try:
        hook = RunHook(run_dir, writer, run_options(cfg), plan, ckpt, watch, announce)
        rec = core.reconstruct(scene, options, hook, device)
        timing.update(rec.timing)
        if "solve" in timing:
            timing["solve"] -= hook.monitor_seconds
        timing["monitoring"] = hook.monitor_seconds
        conf = None
        if options.uncertainty.enabled and hook.stop is None:
            clock = time.perf_counter()
            conf = confidence(rec.setup, rec.options, rec.fit.result.x)
            timing["uncertainty"] = time.perf_counter() - clock
        clock = time.perf_counter()
        metrics = write_outputs(run_dir, rec, cfg.scene, writer, hook.stop, conf)
        timing["outputs"] = time.perf_counter() - clock
    finally:
        writer.close()
    if hook.stop is not None:
        raise SolveDiverged(
            f"{run_dir}: the solve {hook.stop}; density.npz and metrics.json hold the last good "
            f"iterate (iteration {rec.fit.result.iterations}); try a smaller step (solver.lr) or another solver"
        )
    (run_dir / CHECKPOINT_FILE).unlink(missing_ok=True)  # finished: nothing left to resume
    formats = cfg.get("export", {}).get("formats", [])
    if formats:
        clock = time.perf_counter()
        export_run(run_dir, list(formats), float(cfg.export.get("iso", DEFAULT_ISO)))
        timing["export"] = time.perf_counter() - clock
    if cfg.get("leave_one_out"):
        clock = time.perf_counter()
        metrics["leave_one_out"] = cross_check(cfg, run_dir, rec)
        timing["leave_one_out"] = time.perf_counter() - clock
    metrics["timing"] = {**timing, "total": sum(v for k, v in timing.items() if k != "assembly")}
    metrics["memory"] = {**peak_memory(device), "bound": rec.memory_bound / 2**30}
    write_json_atomic(run_dir / "metrics.json", metrics)
    return logged(metrics)


def in_sweep(options: ReconstructionOptions) -> ReconstructionOptions:
    """``options`` for a run of a Hydra multirun (``-m scene.frame=...``: frames of a sequence):
    ``projector.reuse=auto`` becomes ``true``, so that its runs share their capture's region
    operator (:mod:`~flamerecon.fit.capture_operator`)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if options.projector.reuse != "auto" or not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return options
    return options.replace(projector=replace(options.projector, reuse=True))


def cross_check(cfg: DictConfig, run_dir: Path, rec) -> dict:
    """``leave_one_out=true``: each camera the run fitted left out in turn, the others fitted as
    the run was (the held-out views, if any, stay out of every fold), scored
    (:func:`~flamerecon.run.leave_one_out.leave_one_out`, into ``run_dir/leave_one_out/``);
    returns its ``mean``, per-view scores and protocol for metrics.json."""
    from flamerecon.run.leave_one_out import leave_one_out

    scene = rec.scene
    record = leave_one_out(cfg, run_dir / "leave_one_out", [scene.views[v] for v in rec.setup.train],
                           [scene.views[v] for v in rec.setup.holdout], scene=load_scene(cfg.scene))
    keep = ("psnr", "ssim", "detail", "psnr_black")
    return {"mean": {k: record["mean"][k] for k in keep}, "protocol": record["protocol"],
            "views": {name: {k: row[k] for k in keep} for name, row in record["views"].items()}}


def logged(metrics: dict) -> dict:
    """``metrics``, its ``warnings`` logged (WARNING, one line each)."""
    for w in metrics["warnings"]:
        log.warning("%s: %s", w["code"], w["message"])
    return metrics


def prepare(cfg: DictConfig, scene: Scene, device: torch.device, grid=None) -> Setup:
    """:func:`flamerecon.fit.build.build` with a config's options."""
    return build(scene, options_from_config(cfg), device, grid)


def make_problem(cfg: DictConfig, setup: Setup) -> tuple[Problem, Solver, float]:
    """:func:`flamerecon.fit.build.make_problem` with a config's solver."""
    from flamerecon.fit.build import make_problem as make

    return make(options_from_config(cfg).solver, setup)


def solve(cfg: DictConfig, setup: Setup, x0: torch.Tensor | None = None
          ) -> tuple[SolveResult, float, Photometry | None]:
    """:func:`flamerecon.fit.reconstruct.fit` with a config's options, without a run folder:
    (result, absolute l1 weight, fitted photometry or None)."""
    found = core.fit(setup, options_from_config(cfg), x0)
    return found.result, found.l1, found.photometry


def choose_weights(cfg: DictConfig, setup: Setup) -> tuple[DictConfig, dict | None]:
    """:func:`flamerecon.fit.reconstruct.choose_weights` with a config: the config with the
    chosen solver weights, and the selection's record (``cfg`` and None when off)."""
    chosen, record = core.choose_weights(options_from_config(cfg), setup)
    if record is None:
        return cfg, None
    return OmegaConf.merge(cfg, {"solver": chosen.solver.as_dict()}), record


def calibrated_scene(cfg: DictConfig, scene: Scene, device: torch.device) -> tuple[Scene, dict | None]:
    """:func:`flamerecon.fit.reconstruct.calibrated_scene` with a config's options."""
    return core.calibrated_scene(scene, options_from_config(cfg), device)


def warm_start(cfg: DictConfig, scene: Scene, device: torch.device, setup: Setup) -> torch.Tensor | None:
    """:func:`flamerecon.fit.reconstruct.warm_start` with a config's options."""
    return core.warm_start(scene, options_from_config(cfg), device, setup)
