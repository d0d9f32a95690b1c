"""``scene.frames=[first,last]``: the run layer of the joint frame solve (the method:
:mod:`flamerecon.fit.joint_frames`; the ``temporal:`` node is its
:class:`~flamerecon.fit.joint_frames.JointFramesOptions`).

The run folder holds ``frames/NNNNNN/`` per frame with ``density.npz`` (its ``frame`` field
set), ``cameras.json``, ``metrics.json`` and ``renders/``, which
:func:`~flamerecon.outputs.sequence.assemble_sweep` (``scripts/assemble.py RUN_DIR/frames``) reads
like a multirun over frames; the run folder's own ``metrics.json`` holds every frame's views
keyed ``NNNNNN/<view>`` and the joint solve's record.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from flamerecon.errors import ConfigError, FlameReconError
from flamerecon.evaluate.result_warnings import penalty_of
from flamerecon.fit.joint_frames import (
    JointFrame,
    JointFramesOptions,
    check_joint,
    reconstruct_frames,
)
from flamerecon.fit.reconstruct import SolveHook
from flamerecon.outputs.atomic import make_subfolder, write_json_atomic
from flamerecon.outputs.export import save_density
from flamerecon.run.config import options_from_config, start_run
from flamerecon.run.folder import cameras_record, scores, write_scores
from flamerecon.run.hook import announce
from flamerecon.run.tensorboard import RunWriter
from flamerecon.scenes import load_scene
from flamerecon.solvers.temporal import JointResult

FRAMES_FOLDER = "frames"


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


def joint_frames_options(cfg: DictConfig) -> JointFramesOptions:
    """The ``temporal:`` node as typed options (absent keys keep their defaults)."""
    node = OmegaConf.to_container(cfg.temporal, resolve=True) if cfg.get("temporal") is not None else {}
    try:
        return JointFramesOptions(**node)
    except FlameReconError:
        raise
    except TypeError as err:  # an unknown key
        raise ConfigError(f"temporal: {err}; the keys are l2, tv, tol, motion, max_shift") from None


class LoggingHook(SolveHook):
    """The joint solve with its scalars logged to TensorBoard at every check."""

    def __init__(self, writer: RunWriter, announce: str | None = None) -> None:
        self.writer, self.announce = writer, announce

    def begin(self) -> None:
        announce(self.announce)

    def joint(self, setups, solve):
        return solve(lambda it, xs, info: self.writer.scalars(
            it, {k: v for k, v in info.items() if isinstance(v, float)}))


def run_frames(cfg: DictConfig, run_dir: str | Path, resume: bool = False, announce: str | None = None) -> dict:
    """Reconstruct every frame of ``scene.frames`` jointly and write the run folder (module
    doc); returns the combined metrics (views keyed ``NNNNNN/<view>``). ``announce`` is printed
    once every frame's checks have passed."""
    if resume:
        raise ConfigError("resume: a joint solve over scene.frames keeps no checkpoint; run it again")
    options = options_from_config(cfg)
    check_joint(options)
    joint = joint_frames_options(cfg)
    run_dir, device = start_run(cfg, run_dir)
    numbers = frame_range(cfg)
    configs = [frame_config(cfg, t) for t in numbers]
    scenes = [load_scene(fcfg.scene) for fcfg in configs]
    writer = RunWriter(str(run_dir))
    try:
        rec = reconstruct_frames(scenes, options, joint, LoggingHook(writer, announce), device)
        rec.record["frames"] = [numbers[0], numbers[-1]]
        combined: dict = {"heldout": {}, "train": {}, "frames": {}, "warnings": []}
        for t, fcfg, frame in zip(numbers, configs, rec.frames):
            key = f"{t:06d}"
            folder = make_subfolder(make_subfolder(run_dir, FRAMES_FOLDER), key)
            combined["frames"][key] = write_frame(fcfg, folder, frame, rec.result, rec.record)
            for part in ("heldout", "train"):
                for view, values in combined["frames"][key][part].items():
                    combined[part][f"{key}/{view}"] = values
            combined["warnings"] += [{**w, "message": f"frame {t}: {w['message']}"}
                                     for w in combined["frames"][key]["warnings"]]
            writer.scalars(t, {"heldout_psnr": float(np.mean(
                [v["psnr"] for v in combined["frames"][key]["heldout"].values()] or [np.nan]))},
                prefix="eval/frame")
    finally:
        writer.close()
    result = rec.result
    combined["solver"] = {
        "name": f"{cfg.solver.name}+temporal", "l1": float(np.mean([f.l1 for f in rec.frames])),
        "iterations": result.iterations, "seconds": result.seconds, "objective": result.objective,
        "converged": result.converged, "status": "finished", "device": str(device), "temporal": rec.record,
    }
    combined["resolution"] = next(iter(combined["frames"].values()))["resolution"]
    write_json_atomic(run_dir / "metrics.json", combined)
    return combined


def write_frame(cfg: DictConfig, folder: Path, frame: JointFrame, result: JointResult, temporal: dict) -> dict:
    """One frame's density.npz, cameras.json, metrics.json and renders/ in ``folder`` (made)."""
    options = options_from_config(cfg)
    setup, volume = frame.setup, frame.density
    info = {"name": cfg.solver.name, "l1": frame.l1, "iterations": result.iterations,
            "seconds": result.seconds, "objective": result.objective,
            "converged": result.converged, "status": "finished", "device": str(frame.x.device),
            "temporal": temporal, "debias": frame.debias}
    scene = setup.scene
    save_density(folder / "density.npz", volume.cpu(), setup.grid.bbox_min, setup.grid.bbox_max,
                 [scene.views[i] for i in setup.train], frame=int(cfg.scene.frame),
                 solver=json.dumps(info))
    write_json_atomic(folder / "cameras.json", {"cameras": cameras_record(scene, setup.train)})
    metrics, held_imgs = scores(scene, volume, setup.grid, setup.train, setup.holdout, setup.step,
                                options.silhouette.as_dict(), calibration=frame.calibration,
                                penalty=penalty_of(options.solver.as_dict(), frame.l1))
    metrics["solver"] = info
    write_scores(folder, metrics, held_imgs, scene, setup.holdout)
    return metrics
