"""Every public name of ``flamerecon.__all__`` checks its arguments at the door: None, a wrong
type, a wrong shape and an out-of-range value each end in the documented exception
(:class:`~flamerecon.errors.ArgumentTypeError` for a type, :class:`~flamerecon.errors.ArgumentError`
for a value; both :class:`~flamerecon.errors.FlameReconError`) with one line that starts with
the argument's name, never in an internal error (AttributeError, ZeroDivisionError,
RuntimeError, KeyError, IndexError) or a silent result. The option classes are checked by the
CLI's rules: whatever they accept, ``check_options`` accepts too (hypothesis)."""

from __future__ import annotations

import dataclasses
import inspect
import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from kornia.geometry.camera import PinholeCamera

import flamerecon as fr
from flamerecon.errors import ArgumentError, ArgumentTypeError, FlameReconError, RunFolderError
from flamerecon.fit.option_rules import check_options

TYPE, VALUE = ArgumentTypeError, ArgumentError
KINDS = ("none", "type", "shape", "range")
#: public names without a case of some kind, and why.
NOT_APPLICABLE = {
    ("Fit", "shape"): "holds no tensor of its own (the solve result's x is the SolveResult's)",
    ("Reconstruction", "shape"): "holds typed objects only, each checked when made",
    ("Reconstruction", "range"): "holds typed objects only, each checked when made",
    ("JointReconstruction", "shape"): "holds typed objects only, each checked when made",
    ("JointReconstruction", "range"): "holds typed objects only, each checked when made",
    ("MotionReconstruction", "shape"): "holds typed objects and the solve's own result, each checked when made",
    ("MotionReconstruction", "range"): "holds typed objects and the solve's own result, each checked when made",
    ("make_problem", "shape"): "takes a SolverOptions and a Setup, each checked when made",
    ("make_problem", "range"): "takes a SolverOptions and a Setup, each checked when made",
    ("build", "shape"): "takes a Scene, options and a grid, each checked when made",
    ("confidence", "shape"): "takes a Reconstruction or Run and options, each checked when made",
    ("confidence", "range"): "takes a Reconstruction or Run and options, each checked when made",
}


@pytest.fixture(scope="module")
def w():
    """Small valid objects of every public type, to break one argument of at a time."""
    scene = fr.load_scene("synthetic", width=24, height=18, n_cameras=3, phantom_resolution=16)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=8), device="cpu",
                                       solver=fr.SolverOptions("fista", None, 1e-3, {"max_iters": 5}))
    setup = fr.build(scene, options)
    rec = fr.reconstruct(scene, options)
    run = fr.Run(Path("run"), options, {"name": "synthetic"}, scene, rec.grid, rec.density, setup.train,
                 setup.holdout, None, None, {}, {})
    later = fr.load_scene("synthetic", width=24, height=18, n_cameras=3, phantom_resolution=16, frame=1)
    joint = fr.reconstruct_frames([scene, later], options)
    motion = fr.reconstruct_motion([scene, later], options, fr.MotionOptions(window=1), target=0)
    problem, solver, _ = fr.make_problem(options.solver, setup)
    M, C = int(setup.voxel_index.numel()), int(setup.pixels.shape[1])
    from flamerecon.dynamics.flow import PairFlow

    pair = PairFlow(torch.zeros(3, *rec.grid.shape), torch.zeros(3, 2, 2, 2), 0.1, 0.05, 0.1, 0.5, 1.0, False, 0)
    conf = fr.confidence(rec)
    return SimpleNamespace(scene=scene, options=options, setup=setup, rec=rec, run=run, joint=joint, motion=motion,
                           problem=problem, solver=solver, M=M, C=C, pair=pair, conf=conf)


def hook_solve(w, **change):
    """``SolveHook().solve`` with one argument changed."""
    args = {"stage": fr.Stage(0, 0), "setup": w.setup, "problem": w.problem, "solver": w.solver, "x0": None,
            "carry": {}, **change}
    return fr.SolveHook().solve(**args)


def with_density(run, density):
    changed = replace(run)
    changed.density = density  # a Run is mutable: score checks what it is given
    return changed


def mixed_sizes(w):
    """Two of the scene's cameras, one with a smaller image."""
    cams = w.scene.cameras
    return PinholeCamera(cams.intrinsics[:2], cams.extrinsics[:2], torch.tensor([18.0, 10.0]), torch.tensor([24.0, 24.0]))


def no_cameras(w):
    cams = w.scene.cameras
    return PinholeCamera(cams.intrinsics[:0], cams.extrinsics[:0], cams.height[:0], cams.width[:0])


def nan_at_start(t: torch.Tensor) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[0] = math.nan
    return t


#: (public name, kind, call, exception, argument the message starts with)
CASES = [
    # option classes: the CLI's rules, one field at a time
    ("DebiasOptions", "none", lambda w: fr.DebiasOptions(method=None), TYPE, "debias.method"),
    ("DebiasOptions", "type", lambda w: fr.DebiasOptions(iterations="5"), TYPE, "debias.iterations"),
    ("DebiasOptions", "shape", lambda w: fr.DebiasOptions(iterations=[5]), TYPE, "debias.iterations"),
    ("DebiasOptions", "range", lambda w: fr.DebiasOptions(iterations=0), VALUE, "debias.iterations"),
    ("DebiasOptions", "range", lambda w: fr.DebiasOptions(method="median"), VALUE, "debias.method"),
    ("GridOptions", "none", lambda w: fr.GridOptions(resolution=None), TYPE, "grid.resolution"),
    ("GridOptions", "type", lambda w: fr.GridOptions(resolution="64"), TYPE, "grid.resolution"),
    ("GridOptions", "shape", lambda w: fr.GridOptions(resolution=(8, 8)), VALUE, "grid.resolution"),
    ("GridOptions", "shape", lambda w: fr.GridOptions(bbox=((0, 0), (1, 1))), VALUE, "grid.bbox"),
    ("GridOptions", "range", lambda w: fr.GridOptions(resolution=-3), VALUE, "grid.resolution"),
    ("GridOptions", "range", lambda w: fr.GridOptions(bbox=((0, 0, 0), (1, -1, 1))), VALUE, "grid.bbox"),
    ("GridOptions", "range", lambda w: fr.GridOptions(level_iters=-5), VALUE, "grid.level_iters"),
    ("HullOptions", "none", lambda w: fr.HullOptions(margin_voxels=None), TYPE, "hull.margin_voxels"),
    ("HullOptions", "type", lambda w: fr.HullOptions(margin_voxels="1"), TYPE, "hull.margin_voxels"),
    ("HullOptions", "shape", lambda w: fr.HullOptions(margin_voxels=(1, 1)), TYPE, "hull.margin_voxels"),
    ("HullOptions", "range", lambda w: fr.HullOptions(margin_voxels=-1), VALUE, "hull.margin_voxels"),
    ("FlowOptions", "none", lambda w: fr.FlowOptions(control=None), TYPE, "flow.control"),
    ("FlowOptions", "type", lambda w: fr.FlowOptions(up=1), TYPE, "flow.up"),
    ("FlowOptions", "shape", lambda w: fr.FlowOptions(smooth=[1.0]), TYPE, "flow.smooth"),
    ("FlowOptions", "range", lambda w: fr.FlowOptions(inflow=2.0), VALUE, "flow.inflow"),
    ("Flow", "none", lambda w: fr.Flow(None, [0], [w.pair], fr.FlowOptions()), TYPE, "Flow.grid"),
    ("Flow", "type", lambda w: fr.Flow(w.rec.grid, [0], [w.pair], {"control": 8}), TYPE, "Flow.options"),
    ("Flow", "shape", lambda w: fr.Flow(w.rec.grid, [0], [replace(w.pair, u=torch.zeros(3, 2, 2, 2))],
                                        fr.FlowOptions()), VALUE, "Flow.pairs[0].u"),
    ("Flow", "range", lambda w: fr.Flow(w.rec.grid, [0, 1], [w.pair], fr.FlowOptions()), VALUE, "Flow.frames"),
    ("advect", "none", lambda w: fr.advect(None, w.pair.u, 1), TYPE, "advect.density"),
    ("advect", "type", lambda w: fr.advect(w.rec.density, w.pair.u, "1"), TYPE, "advect.steps"),
    ("advect", "shape", lambda w: fr.advect(w.rec.density, torch.zeros(3, 2, 2, 2), 1), VALUE, "advect.velocity"),
    ("advect", "range", lambda w: fr.advect(w.rec.density, w.pair.u, -1), VALUE, "advect.steps"),
    ("estimate_flow", "none", lambda w: fr.estimate_flow(None), TYPE, "estimate_flow.frames"),
    ("estimate_flow", "type", lambda w: fr.estimate_flow([w.rec, "frame 1"]), TYPE, "estimate_flow.frames[1]"),
    ("estimate_flow", "shape", lambda w: fr.estimate_flow([w.rec]), VALUE, "estimate_flow.frames"),
    ("estimate_flow", "range", lambda w: fr.estimate_flow([w.rec, w.rec]), VALUE, "estimate_flow.frames"),
    ("MotionOptions", "none", lambda w: fr.MotionOptions(window=None), TYPE, "motion.window"),
    ("MotionOptions", "type", lambda w: fr.MotionOptions(fit_to=1), TYPE, "motion.fit_to"),
    ("MotionOptions", "shape", lambda w: fr.MotionOptions(decay=[0.5]), TYPE, "motion.decay"),
    ("MotionOptions", "range", lambda w: fr.MotionOptions(window=2), VALUE, "motion.window"),
    ("JointFramesOptions", "none", lambda w: fr.JointFramesOptions(l2=None), TYPE, "temporal.l2"),
    ("JointFramesOptions", "type", lambda w: fr.JointFramesOptions(motion=1), TYPE, "temporal.motion"),
    ("JointFramesOptions", "shape", lambda w: fr.JointFramesOptions(l2=[0.1]), TYPE, "temporal.l2"),
    ("JointFramesOptions", "range", lambda w: fr.JointFramesOptions(tv=-1.0), VALUE, "temporal.tv"),
    ("JointFramesOptions", "range", lambda w: fr.JointFramesOptions(motion="warp"), VALUE, "temporal.motion"),
    ("PhotometryOptions", "none", lambda w: fr.PhotometryOptions(fit_gain=None), TYPE, "photometry.fit_gain"),
    ("PhotometryOptions", "type", lambda w: fr.PhotometryOptions(fit_gain="yes"), TYPE, "photometry.fit_gain"),
    ("PhotometryOptions", "shape", lambda w: fr.PhotometryOptions(rounds=[2]), TYPE, "photometry.rounds"),
    ("PhotometryOptions", "range", lambda w: fr.PhotometryOptions(rounds=0), VALUE, "photometry.rounds"),
    ("ProjectorOptions", "none", lambda w: fr.ProjectorOptions(step=None), TYPE, "projector.step"),
    ("ProjectorOptions", "type", lambda w: fr.ProjectorOptions(step="0.5"), TYPE, "projector.step"),
    ("ProjectorOptions", "shape", lambda w: fr.ProjectorOptions(step=(0.5,)), TYPE, "projector.step"),
    ("ProjectorOptions", "range", lambda w: fr.ProjectorOptions(step=-1.0), VALUE, "projector.step"),
    ("ProjectorOptions", "range", lambda w: fr.ProjectorOptions(backend="gpu"), VALUE, "projector.backend"),
    ("ReconstructionOptions", "none", lambda w: fr.ReconstructionOptions(grid=None), TYPE, "grid"),
    ("ReconstructionOptions", "type", lambda w: fr.ReconstructionOptions(grid={"resolution": 8}), TYPE, "grid"),
    ("ReconstructionOptions", "type", lambda w: fr.ReconstructionOptions(seed="0"), TYPE, "seed"),
    ("ReconstructionOptions", "shape", lambda w: fr.ReconstructionOptions(holdout=[["cam01"]]), VALUE, "holdout"),
    ("ReconstructionOptions", "range", lambda w: fr.ReconstructionOptions(threads=0), VALUE, "threads"),
    ("ReconstructionOptions", "range", lambda w: fr.ReconstructionOptions(device="gpu"), VALUE, "device"),
    ("RefineOptions", "none", lambda w: fr.RefineOptions(refine=None), TYPE, "calibration.refine"),
    ("RefineOptions", "type", lambda w: fr.RefineOptions(rounds="3"), TYPE, "calibration.rounds"),
    ("RefineOptions", "shape", lambda w: fr.RefineOptions(frames=[[30, 50]]), VALUE, "calibration.frames"),
    ("RefineOptions", "range", lambda w: fr.RefineOptions(prior_focal=0.0), VALUE, "calibration.prior_focal"),
    ("RefineOptions", "range", lambda w: fr.RefineOptions(frames=[-1]), VALUE, "calibration.frames"),
    ("RefineOptions", "range", lambda w: fr.RefineOptions(rig=True), VALUE, "calibration.rig"),
    ("RefineOptions", "range", lambda w: fr.RefineOptions(gauge="procrustes"), VALUE, "calibration.gauge"),
    ("RefineOptions", "type", lambda w: fr.RefineOptions(score_before="yes"), TYPE, "calibration.score_before"),
    ("SelectOptions", "none", lambda w: fr.SelectOptions(candidates=None), TYPE, "select.candidates"),
    ("SelectOptions", "type", lambda w: fr.SelectOptions(folds="4"), TYPE, "select.folds"),
    ("SelectOptions", "shape", lambda w: fr.SelectOptions(candidates={"tv": [1, 2]}), VALUE, "select.candidates"),
    ("SelectOptions", "range", lambda w: fr.SelectOptions(folds=1), VALUE, "select.folds"),
    ("SilhouetteOptions", "none", lambda w: fr.SilhouetteOptions(method=None), TYPE, "silhouette.method"),
    ("SilhouetteOptions", "type", lambda w: fr.SilhouetteOptions(threshold="0.1"), TYPE, "silhouette.threshold"),
    ("SilhouetteOptions", "shape", lambda w: fr.SilhouetteOptions(threshold=[0.1]), TYPE, "silhouette.threshold"),
    ("SilhouetteOptions", "range", lambda w: fr.SilhouetteOptions(threshold=-0.1), VALUE, "silhouette.threshold"),
    ("SolverOptions", "none", lambda w: fr.SolverOptions(name=None), TYPE, "solver.name"),
    ("SolverOptions", "type", lambda w: fr.SolverOptions(params=None), TYPE, "solver.params"),
    ("SolverOptions", "shape", lambda w: fr.SolverOptions(params={"max_iters": [5]}), TYPE, "solver.max_iters"),
    ("SolverOptions", "range", lambda w: fr.SolverOptions(params={"max_iters": -1}), VALUE, "solver.max_iters"),
    ("SolverOptions", "range", lambda w: fr.SolverOptions(name="fsta"), VALUE, "solver.name"),
    ("SolverOptions", "range", lambda w: fr.SolverOptions(params={"max_iter": 5}), VALUE, "solver.max_iter"),
    # the functions
    ("build", "none", lambda w: fr.build(None, w.options), TYPE, "build.scene"),
    ("build", "type", lambda w: fr.build(w.scene, w.options.as_dict()), TYPE, "build.options"),
    ("build", "type", lambda w: fr.build(w.scene, w.options, grid=(8, 8, 8)), TYPE, "build.grid"),
    ("build", "range", lambda w: fr.build(w.scene, w.options, device="cuda:99"), VALUE, "device"),
    ("fit", "none", lambda w: fr.fit(None, w.options), TYPE, "fit.setup"),
    ("fit", "type", lambda w: fr.fit(w.setup, w.options.as_dict()), TYPE, "fit.options"),
    ("fit", "shape", lambda w: fr.fit(w.setup, w.options, torch.zeros(w.M + 1, w.C)), VALUE, "fit.x0"),
    ("fit", "range", lambda w: fr.fit(w.setup, w.options, torch.full((w.M, w.C), math.nan)), VALUE, "fit.x0"),
    ("fit", "range", lambda w: fr.fit(w.setup, w.options.replace(grid=fr.GridOptions(resolution=12))), VALUE,
     "fit.options"),
    ("make_problem", "none", lambda w: fr.make_problem(None, w.setup), TYPE, "make_problem.options"),
    ("make_problem", "type", lambda w: fr.make_problem(w.options, w.setup), TYPE, "make_problem.options"),
    ("make_solver", "none", lambda w: fr.make_solver(None), TYPE, "solver.name"),
    ("make_solver", "type", lambda w: fr.make_solver("fista", tol="1e-4"), TYPE, "solver.tol"),
    ("make_solver", "shape", lambda w: fr.make_solver("fista", max_iters=[10, 20]), TYPE, "solver.max_iters"),
    ("make_solver", "range", lambda w: fr.make_solver("fista", max_iters=-1), VALUE, "solver.max_iters"),
    ("make_solver", "range", lambda w: fr.make_solver("fista", max_iter=5), VALUE, "solver.max_iter"),
    ("reconstruct", "none", lambda w: fr.reconstruct(None, w.options), TYPE, "reconstruct.scene"),
    ("reconstruct", "type", lambda w: fr.reconstruct(w.scene, w.options, hook=print), TYPE, "reconstruct.hook"),
    ("reconstruct", "shape", lambda w: fr.reconstruct(w.scene, w.options, init=w.rec.density[0]), VALUE,
     "reconstruct.init"),
    ("reconstruct", "range", lambda w: fr.reconstruct(w.scene, w.options, init=w.rec.density[:1]), VALUE,
     "reconstruct.init"),
    ("reconstruct", "range", lambda w: fr.reconstruct(w.scene, w.options, init=nan_at_start(w.rec.density)),
     VALUE, "reconstruct.init"),
    ("reconstruct_motion", "none", lambda w: fr.reconstruct_motion(None, w.options), TYPE,
     "reconstruct_motion.scenes"),
    ("reconstruct_motion", "type", lambda w: fr.reconstruct_motion(w.scene, w.options), TYPE,
     "reconstruct_motion.scenes"),
    ("reconstruct_motion", "shape", lambda w: fr.reconstruct_motion([], w.options), VALUE,
     "reconstruct_motion.scenes"),
    ("reconstruct_motion", "range", lambda w: fr.reconstruct_motion([w.scene], w.options, target=5), VALUE,
     "reconstruct_motion.target"),
    ("reconstruct_frames", "none", lambda w: fr.reconstruct_frames(None, w.options), TYPE,
     "reconstruct_frames.scenes"),
    ("reconstruct_frames", "type", lambda w: fr.reconstruct_frames(w.scene, w.options), TYPE,
     "reconstruct_frames.scenes"),
    ("reconstruct_frames", "shape", lambda w: fr.reconstruct_frames([], w.options), VALUE,
     "reconstruct_frames.scenes"),
    ("reconstruct_frames", "range", lambda w: fr.reconstruct_frames([w.scene], w.options, device="cuda:99"), VALUE,
     "device"),
    ("render", "none", lambda w: fr.render(None, w.rec.grid, w.scene.cameras), TYPE, "render.volume"),
    ("render", "type", lambda w: fr.render(w.rec.density.long(), w.rec.grid, w.scene.cameras), TYPE,
     "render.volume"),
    ("render", "type", lambda w: fr.render(w.rec.density, w.rec.grid, w.scene.cameras.intrinsics), TYPE,
     "render.cameras"),
    ("render", "shape", lambda w: fr.render(w.rec.density, fr.VoxelGrid((0, 0, 0), (1, 1, 1), (4, 4, 4)),
                                            w.scene.cameras), VALUE, "render.volume"),
    ("render", "range", lambda w: fr.render(w.rec.density, w.rec.grid, w.scene.cameras, step=-0.5), VALUE,
     "render.step"),
    ("score", "none", lambda w: fr.score(None), TYPE, "score.result"),
    ("score", "type", lambda w: fr.score(w.rec.density), TYPE, "score.result"),
    ("score", "shape", lambda w: fr.score(with_density(w.run, torch.zeros(3, 2, 2, 2))), VALUE,
     "score.result.density"),
    ("score", "range", lambda w: fr.score(with_density(w.run, nan_at_start(w.rec.density))), VALUE,
     "score.result.density"),
    ("load_scene", "none", lambda w: fr.load_scene(None), TYPE, "load_scene.scene"),
    ("load_scene", "type", lambda w: fr.load_scene("synthetic", width="48"), TYPE, "scene.width"),
    ("load_scene", "shape", lambda w: fr.load_scene("nerf", root="/nowhere", bbox=[[0, 0], [1, 1]]), VALUE,
     "scene.bbox"),
    ("load_scene", "range", lambda w: fr.load_scene("synthetic", width=-3), VALUE, "scene.width"),
    ("load_scene", "range", lambda w: fr.load_scene("synthetic", widht=48), VALUE, "scene.widht"),
    ("load_scene", "range", lambda w: fr.load_scene("synthtic"), VALUE, "scene.name"),
    ("load_scene", "range", lambda w: fr.load_scene("synthetic", frames=[1, 2]), VALUE, "scene.frames"),
    ("load_run", "none", lambda w: fr.load_run(None), TYPE, "load_run.run_dir"),
    ("load_run", "type", lambda w: fr.load_run(42), TYPE, "load_run.run_dir"),
    ("load_run", "shape", lambda w: fr.load_run(["run", "other"]), TYPE, "load_run.run_dir"),
    ("load_run", "range", lambda w: fr.load_run("run", device="gpu"), VALUE, "load_run.device"),
    ("load_run", "range", lambda w: fr.load_run("/nowhere/run", device="cpu"), RunFolderError,
     "/nowhere/run/.hydra/config.yaml"),
    ("view", "none", lambda w: fr.view(None), TYPE, "view.result"),
    ("view", "type", lambda w: fr.view(w.rec, port="8080"), TYPE, "view.port"),
    ("view", "shape", lambda w: fr.view(["run", "other"]), TYPE, "view.result"),
    ("view", "range", lambda w: fr.view(w.rec, port=0), VALUE, "view.port"),
    ("view", "range", lambda w: fr.view(w.rec, device="gpu"), VALUE, "view.device"),
    ("framing_camera", "none", lambda w: fr.framing_camera(None), TYPE, "framing_camera.result"),
    ("framing_camera", "type", lambda w: fr.framing_camera(w.rec, width="64"), TYPE, "framing_camera.width"),
    ("framing_camera", "shape", lambda w: fr.framing_camera(with_density(w.run, torch.zeros(3, 2, 2, 2))), VALUE,
     "framing_camera.result.density"),
    ("framing_camera", "range", lambda w: fr.framing_camera(w.rec, elevation_deg=100), VALUE,
     "framing_camera.elevation_deg"),
    ("framing_camera", "range", lambda w: fr.framing_camera(w.rec, [0, math.nan]), VALUE, "framing_camera.azimuth_deg"),
    ("save_image", "none", lambda w: fr.save_image(None, w.scene.images[0]), TYPE, "save_image.path"),
    ("save_image", "type", lambda w: fr.save_image("out/a.png", "image"), TYPE, "save_image.image"),
    ("save_image", "shape", lambda w: fr.save_image("out/a.png", torch.zeros(2, 4, 4)), VALUE, "save_image.image"),
    ("save_image", "range", lambda w: fr.save_image("out/a.png", w.scene.images[0], vmax=-1), VALUE, "save_image.vmax"),
    ("save_image", "range", lambda w: fr.save_image("out/a.jpg", w.scene.images[0]), VALUE, "save_image.path"),
    ("preset", "none", lambda w: fr.preset(None), TYPE, "preset.scene"),
    ("preset", "type", lambda w: fr.preset("synthetic", 5), TYPE, "preset.overrides[0]"),
    ("preset", "shape", lambda w: fr.preset("synthetic", "grid.resolution=[8,8]"), VALUE, "grid.resolution"),
    ("preset", "range", lambda w: fr.preset("synthetic", "grid.resolution=-3"), VALUE, "grid.resolution"),
    ("preset", "range", lambda w: fr.preset("synthtic"), VALUE, "preset.scene"),
    ("preset", "range", lambda w: fr.preset("synthetic", "solver.max_iter=3"), VALUE, "preset.overrides"),
    ("UncertaintyOptions", "none", lambda w: fr.UncertaintyOptions(scale=None), TYPE, "uncertainty.scale"),
    ("UncertaintyOptions", "type", lambda w: fr.UncertaintyOptions(enabled="yes"), TYPE, "uncertainty.enabled"),
    ("UncertaintyOptions", "shape", lambda w: fr.UncertaintyOptions(shift_voxels=[0.5]), TYPE,
     "uncertainty.shift_voxels"),
    ("UncertaintyOptions", "range", lambda w: fr.UncertaintyOptions(scale=0.0), VALUE, "uncertainty.scale"),
    ("UncertaintyOptions", "range", lambda w: fr.UncertaintyOptions(members="views"), VALUE, "uncertainty.members"),
    ("confidence", "none", lambda w: fr.confidence(None), TYPE, "confidence.result"),
    ("confidence", "type", lambda w: fr.confidence(w.rec, {"scale": 2.0}), TYPE, "confidence.options"),
    ("uncertainty", "none", lambda w: fr.uncertainty(w.conf, None), TYPE, "uncertainty.cameras"),
    ("uncertainty", "type", lambda w: fr.uncertainty(w.rec.density, w.scene.cameras), TYPE, "uncertainty.result"),
    ("uncertainty", "shape", lambda w: fr.uncertainty(w.conf, mixed_sizes(w)), VALUE, "uncertainty.cameras"),
    ("uncertainty", "range", lambda w: fr.uncertainty(w.conf, no_cameras(w)), VALUE, "uncertainty.cameras"),
    ("Confidence", "none", lambda w: replace(w.conf, grid=None), TYPE, "Confidence.grid"),
    ("Confidence", "type", lambda w: replace(w.conf, hull=w.conf.hull.float()), TYPE, "Confidence.hull"),
    ("Confidence", "shape", lambda w: replace(w.conf, members=w.conf.members[:, 1:]), VALUE, "Confidence.members"),
    ("Confidence", "range", lambda w: replace(w.conf, scale=-1.0), VALUE, "Confidence.scale"),
    ("Confidence", "range", lambda w: replace(w.conf, groups=["views"] * len(w.conf.groups)), VALUE,
     "Confidence.groups"),
    ("export", "none", lambda w: fr.export(None, "out/a"), TYPE, "export.result"),
    ("export", "type", lambda w: fr.export(w.rec, 42), TYPE, "export.stem"),
    ("export", "shape", lambda w: fr.export(w.rec, "out/a", [["vti"]]), TYPE, "export.formats[0]"),
    ("export", "range", lambda w: fr.export(w.rec, "out/a", "vtk"), VALUE, "export.formats"),
    ("export", "range", lambda w: fr.export(w.rec, "out/a", iso=2.0), VALUE, "export.iso"),
    ("look_at_camera", "none", lambda w: fr.look_at_camera(None, (0, 0, 0)), TYPE, "look_at_camera.eye"),
    ("look_at_camera", "type", lambda w: fr.look_at_camera("abc", (0, 0, 0)), TYPE, "look_at_camera.eye"),
    ("look_at_camera", "shape", lambda w: fr.look_at_camera((0, 0), (0, 0, 0)), VALUE, "look_at_camera.eye"),
    ("look_at_camera", "shape", lambda w: fr.look_at_camera(torch.ones(4, 3), torch.zeros(2, 3)), VALUE,
     "look_at_camera.target"),
    ("look_at_camera", "range", lambda w: fr.look_at_camera((0, 0, 1), (0, 0, 0), fov_deg=180), VALUE,
     "look_at_camera.fov_deg"),
    ("look_at_camera", "range", lambda w: fr.look_at_camera((0, 0, 1), (0, 0, 1)), VALUE, "look_at_camera.target"),
    ("look_at_camera", "range", lambda w: fr.look_at_camera((0, 1, 0), (0, 0, 0)), VALUE, "look_at_camera.up"),
    ("look_at_camera", "range", lambda w: fr.look_at_camera((0, 0, 1), (0, 0, 0), width=2.5), VALUE,
     "look_at_camera.width"),
    ("orbit_cameras", "none", lambda w: fr.orbit_cameras(None, 10, 3, (0, 0, 0)), TYPE, "orbit_cameras.azimuth_deg"),
    ("orbit_cameras", "type", lambda w: fr.orbit_cameras("0", 10, 3, (0, 0, 0)), TYPE, "orbit_cameras.azimuth_deg"),
    ("orbit_cameras", "shape", lambda w: fr.orbit_cameras([0], 10, 3, (0, 0)), VALUE, "orbit_cameras.target"),
    ("orbit_cameras", "range", lambda w: fr.orbit_cameras([0], 100, 3, (0, 0, 0)), VALUE,
     "orbit_cameras.elevation_deg"),
    ("orbit_cameras", "range", lambda w: fr.orbit_cameras([0], 10, -3, (0, 0, 0)), VALUE, "orbit_cameras.distance"),
    ("orbit_cameras", "range", lambda w: fr.orbit_cameras([0, math.nan], 10, 3, (0, 0, 0)), VALUE,
     "orbit_cameras.azimuth_deg"),
    ("orbit_cameras", "range", lambda w: fr.orbit_cameras([], 10, 3, (0, 0, 0)), VALUE, "orbit_cameras.azimuth_deg"),
    # the classes a user may make or meet
    ("Fit", "none", lambda w: replace(w.rec.fit, options=None), TYPE, "Fit.options"),
    ("Fit", "type", lambda w: replace(w.rec.fit, result=w.rec.density), TYPE, "Fit.result"),
    ("Fit", "range", lambda w: replace(w.rec.fit, l1=-1.0), VALUE, "Fit.l1"),
    ("MotionReconstruction", "none", lambda w: replace(w.motion, setup=None), TYPE, "MotionReconstruction.setup"),
    ("MotionReconstruction", "type", lambda w: replace(w.motion, frames=[w.scene]), TYPE,
     "MotionReconstruction.frames"),
    ("JointReconstruction", "none", lambda w: replace(w.joint, frames=None), TYPE, "JointReconstruction.frames"),
    ("JointReconstruction", "type", lambda w: replace(w.joint, frames=[w.scene]), TYPE,
     "JointReconstruction.frames"),
    ("Problem", "none", lambda w: fr.Problem(w.problem.A, None), TYPE, "Problem.b"),
    ("Problem", "type", lambda w: fr.Problem(w.problem.b, w.problem.b), TYPE, "Problem.A"),
    ("Problem", "shape", lambda w: fr.Problem(w.problem.A, w.problem.b[1:]), VALUE, "Problem.b"),
    ("Problem", "range", lambda w: fr.Problem(w.problem.A, w.problem.b, -0.1), VALUE, "Problem.l1"),
    ("Problem", "range", lambda w: fr.Problem(w.problem.A, w.problem.b, 0.0, (2, 2, 2), w.setup.voxel_index),
     VALUE, "Problem.voxel_index"),
    ("Reconstruction", "none", lambda w: replace(w.rec, scene=None), TYPE, "Reconstruction.scene"),
    ("Reconstruction", "type", lambda w: replace(w.rec, setup=w.scene), TYPE, "Reconstruction.setup"),
    ("Run", "none", lambda w: replace(w.run, scene=None), TYPE, "Run.scene"),
    ("Run", "type", lambda w: replace(w.run, options=w.options.as_dict()), TYPE, "Run.options"),
    ("Run", "shape", lambda w: replace(w.run, density=w.rec.density[:, :2]), VALUE, "Run.density"),
    ("Run", "range", lambda w: replace(w.run, holdout=[7]), VALUE, "Run.holdout"),
    ("Scene", "none", lambda w: replace(w.scene, images=None), TYPE, "Scene.images"),
    ("Scene", "type", lambda w: replace(w.scene, views=5), TYPE, "Scene.views"),
    ("Scene", "shape", lambda w: replace(w.scene, images=w.scene.images[0]), VALUE, "Scene.images"),
    ("Scene", "shape", lambda w: replace(w.scene, masks=torch.ones(3, 2, 2, dtype=torch.bool)), VALUE,
     "Scene.masks"),
    ("Scene", "range", lambda w: replace(w.scene, bbox_max=(0.5, -1.0, 0.5)), VALUE, "Scene.bbox_max"),
    ("Setup", "none", lambda w: replace(w.setup, scene=None), TYPE, "Setup.scene"),
    ("Setup", "type", lambda w: replace(w.setup, hull=w.setup.hull.float()), TYPE, "Setup.hull"),
    ("Setup", "shape", lambda w: replace(w.setup, masks=w.setup.masks[:2]), VALUE, "Setup.masks"),
    ("Setup", "range", lambda w: replace(w.setup, holdout=[3]), VALUE, "Setup.holdout"),
    ("SolveHook", "none", lambda w: hook_solve(w, stage=None), TYPE, "SolveHook.solve.stage"),
    ("SolveHook", "type", lambda w: hook_solve(w, problem=w.setup), TYPE, "SolveHook.solve.problem"),
    ("SolveHook", "shape", lambda w: hook_solve(w, x0=torch.zeros(2, w.C)), VALUE, "SolveHook.solve.x0"),
    ("SolveHook", "range", lambda w: hook_solve(w, x0=torch.full((w.M, w.C), math.inf)), VALUE,
     "SolveHook.solve.x0"),
    ("Stage", "none", lambda w: fr.Stage(None, 0), TYPE, "Stage.level"),
    ("Stage", "type", lambda w: fr.Stage("1", 2), TYPE, "Stage.level"),
    ("Stage", "shape", lambda w: fr.Stage(0, (1, 2)), TYPE, "Stage.levels"),
    ("Stage", "range", lambda w: fr.Stage(3, 2), VALUE, "Stage.level"),
    ("Stage", "range", lambda w: fr.Stage(0, 0, -1), VALUE, "Stage.round"),
    ("VoxelGrid", "none", lambda w: fr.VoxelGrid(None, (1, 1, 1), (2, 2, 2)), TYPE, "VoxelGrid.bbox_min"),
    ("VoxelGrid", "type", lambda w: fr.VoxelGrid((0, 0, 0), (1, 1, 1), "abc"), TYPE, "VoxelGrid.resolution"),
    ("VoxelGrid", "shape", lambda w: fr.VoxelGrid((0, 0), (1, 1, 1), (2, 2, 2)), VALUE, "VoxelGrid.bbox_min"),
    ("VoxelGrid", "range", lambda w: fr.VoxelGrid((0, 0, 0), (1, 1, 1), (0, 2, 2)), VALUE, "VoxelGrid.resolution"),
    ("VoxelGrid", "range", lambda w: fr.VoxelGrid.from_box((0, 0, 0), (1, 0, 1), 8), VALUE, "VoxelGrid.bbox_max"),
]
INTERNAL = (AttributeError, ZeroDivisionError, RuntimeError, KeyError, IndexError)


def test_every_public_name_has_a_case_of_every_kind():
    covered = {(name, kind) for name, kind, *_ in CASES}
    missing = [(name, kind) for name in fr.__all__ for kind in KINDS
               if (name, kind) not in covered and (name, kind) not in NOT_APPLICABLE]
    assert not missing, f"public names without a case: {missing}"
    assert not covered & set(NOT_APPLICABLE), "a case marked not applicable has one"
    assert {name for name, *_ in CASES} == set(fr.__all__)


@pytest.mark.parametrize("name, kind, call, error, argument", CASES,
                         ids=[f"{c[0]}-{c[1]}-{c[4]}" for c in CASES])
def test_a_bad_argument_is_refused_by_name(w, name, kind, call, error, argument):
    with pytest.raises(FlameReconError) as info:
        call(w)
    assert isinstance(info.value, error), f"{type(info.value).__name__}: {info.value}"
    assert not isinstance(info.value, INTERNAL)
    message = str(info.value)
    assert message.startswith(f"{argument}: "), message
    assert "\n" not in message


def test_types_and_values_are_python_s_type_and_value_errors():
    assert issubclass(ArgumentTypeError, TypeError) and issubclass(ArgumentError, ValueError)
    assert issubclass(ArgumentTypeError, FlameReconError) and issubclass(ArgumentError, FlameReconError)


def test_fit_is_the_function_whichever_import_came_first():
    assert callable(fr.fit)
    assert list(inspect.signature(fr.fit).parameters)[:2] == ["setup", "options"]


def test_float64_and_numpy_arguments_are_converted(w):
    images = fr.render(w.rec.density.double(), w.rec.grid, w.scene.cameras)
    assert images.dtype == torch.float32
    torch.testing.assert_close(images, fr.render(w.rec.density, w.rec.grid, w.scene.cameras))
    found = fr.fit(w.setup, w.options, torch.zeros(w.M, w.C, dtype=torch.float64).numpy())
    assert found.result.x.dtype == w.setup.pixels.dtype
    assert replace(w.scene, images=w.scene.images.double()).images.dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device")
def test_cuda_tensors_are_taken_and_moved_where_they_are_needed(w):
    images = fr.render(w.rec.density.cuda().double(), w.rec.grid, w.scene.cameras)
    assert images.device.type == "cuda"
    torch.testing.assert_close(images.cpu(), fr.render(w.rec.density, w.rec.grid, w.scene.cameras),
                               rtol=1e-4, atol=1e-6)
    found = fr.fit(w.setup, w.options, torch.zeros(w.M, w.C, device="cuda"))
    assert found.result.x.device == w.setup.pixels.device


def test_one_holdout_name_is_one_view_not_its_letters(w):
    assert fr.ReconstructionOptions(holdout="cam01").holdout == ("cam01",)
    setup = fr.build(w.scene, w.options.replace(holdout="cam01"))
    assert [w.scene.views[v] for v in setup.holdout] == ["cam01"]


def test_the_options_read_back_from_a_config_are_the_ones_made_by_hand():
    by_hand = fr.ReconstructionOptions(grid=fr.GridOptions(levels=[8, 16], bbox=[[0, 0, 0], [1, 1, 1]]),
                                       holdout=["cam01"], calibration=fr.RefineOptions(refine="pose", frames=[1, 2]))
    assert fr.ReconstructionOptions.from_dict(by_hand.as_dict()) == by_hand
    assert by_hand.grid.levels == (8, 16) and by_hand.calibration.frames == (1, 2)


#: any plain value a user might pass for an option
ANYTHING = st.one_of(
    st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8), st.lists(st.integers(-3, 300), max_size=4), st.lists(st.floats(-2, 2), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
    st.tuples(st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)),
              st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2))),
)
SECTIONS = {"grid": fr.GridOptions, "projector": fr.ProjectorOptions, "silhouette": fr.SilhouetteOptions,
            "hull": fr.HullOptions, "photometry": fr.PhotometryOptions, "debias": fr.DebiasOptions,
            "calibration": fr.RefineOptions, "select": fr.SelectOptions, "uncertainty": fr.UncertaintyOptions}
FIELDS = [(section, f.name) for section, cls in SECTIONS.items() for f in dataclasses.fields(cls)]


@pytest.mark.parametrize("section, field", FIELDS, ids=[f"{s}.{f}" for s, f in FIELDS])
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(given=ANYTHING)
def test_an_option_class_takes_what_the_cli_takes_and_refuses_the_rest_by_name(section, field, given):
    try:
        options = fr.ReconstructionOptions(**{section: SECTIONS[section](**{field: given})})
    except FlameReconError as err:  # a bad value, or one that does nothing alone (NEEDS)
        assert isinstance(err, (ArgumentError, ArgumentTypeError))
        assert str(err).startswith(f"{section}.{field}:"), str(err)
        return
    check_options(options.as_dict())  # one rule, two doors


@settings(max_examples=60, deadline=None)
@given(bbox_min=ANYTHING, bbox_max=ANYTHING, resolution=ANYTHING)
def test_a_voxel_grid_is_made_or_refused_never_broken(bbox_min, bbox_max, resolution):
    try:
        grid = fr.VoxelGrid(bbox_min, bbox_max, resolution)
    except FlameReconError as err:
        assert str(err).startswith("VoxelGrid.")
        return
    assert all(lo < hi for lo, hi in zip(grid.bbox_min, grid.bbox_max)) and min(grid.resolution) >= 1
    assert grid.num_voxels == math.prod(grid.resolution)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["fista", "tv", "pqn", "lars"]), key=st.sampled_from(["max_iters", "tol", "check_every",
                                                                                  "max_seconds", "maxiter"]),
       given=ANYTHING)
def test_make_solver_takes_what_the_cli_takes(name, key, given):
    try:
        solver = fr.make_solver(name, **{key: given})
    except FlameReconError as err:
        assert str(err).startswith("solver."), str(err)
        return
    check_options({"solver": {"name": name, key: given}})
    assert solver.max_iters >= 1 if solver.max_iters is not None else name == "lars"


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["width", "height", "n_cameras", "frame", "downscale", "noise", "peak", "holdout",
                            "phantom_step", "seed", "bbox"]), given=ANYTHING)
def test_load_scene_checks_every_option_before_loading(monkeypatch, key, given):
    monkeypatch.setattr("flamerecon.api.load_scene_node", lambda node: node)  # checks only: no render
    try:
        node = fr.load_scene("synthetic", **{key: given})
    except FlameReconError as err:
        assert str(err).startswith(f"scene.{key}:") or str(err).startswith("scene.holdout:"), str(err)
        return
    assert key not in ("bbox", "holdout"), "synthetic scenes take neither"
    check_options({"scene": node})
