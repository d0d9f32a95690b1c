"""flamerecon: sparse multi-view emission tomography of flames and smoke.

The Python API (what ``python train.py`` does, without Hydra or a run folder)::

    import flamerecon as fr

    scene = fr.load_scene("synthetic")                   # or "scalarflow", as scene=scalarflow loads it
    options = fr.preset("synthetic")                      # the CLI's options for that scene, typed
    rec = fr.reconstruct(scene, options)                  # hull, operator, solve, refits, debias
    rec.density                                           # (C, nz, ny, nx) on rec.grid
    fr.score(rec)["heldout"]                              # PSNR / SSIM per held-out view
    fr.render(rec.density, rec.grid, fr.look_at_camera((0, 1, 3), (0, 0.5, 0)))  # a novel view
    fr.export(rec, "out/flame", ["vti", "mesh"])          # ParaView volume, PLY + OBJ surface

Step by step: ``setup = fr.build(scene, options)`` (silhouettes, hull, rays, operator),
``fr.fit(setup, options)``; ``fr.render(density, grid, cameras)``; ``fr.load_run(folder)``
reads a CLI run folder back; ``fr.reconstruct_frames(scenes, options, fr.JointFramesOptions())``
solves consecutive frames jointly; ``fr.reconstruct_motion(scenes, options, fr.MotionOptions(window=5))``
reconstructs one frame with its neighbours' views carried onto it by their motion;
``fr.estimate_flow(recs)`` fits a velocity to each consecutive pair of reconstructions and
``fr.advect(density, u, k)`` carries a density k frames along one; ``v = fr.view(rec)`` serves it
to a browser (``v.url``; ``v.stop()``); ``conf = fr.confidence(rec)`` says what the cameras
determine (``conf.volume()``, and ``fr.uncertainty(conf, cameras)``: the predicted spread of any
camera's render). Names are imported on first use.

Every public function and class checks its arguments before any work: a wrong type raises
:class:`~flamerecon.errors.ArgumentTypeError` (a ``TypeError``), a wrong shape or a value out
of range :class:`~flamerecon.errors.ArgumentError` (a ``ValueError``), one line naming the
argument, what it got and what it wants; the options follow the command line's rules.
"""

from __future__ import annotations

import importlib
import os
import sys

if "torch" not in sys.modules and not {"OMP_WAIT_POLICY", "GOMP_SPINCOUNT"} & set(os.environ):
    # OpenMP threads (GNU libgomp, torch's on Linux) spin ~300,000 times before they sleep, and
    # on a busy machine they spin on the cores the working threads need: the default
    # `python train.py` with two other processes busy on 2 cores solved in 11.7-16.9 s, with a
    # spin count of 1000 in 2.9-3.2 s (passive waiting: 2.5-2.8), and idle alike (1.1-1.5 s
    # against 1.0-1.5; passive 1.9-2.3). Read when torch loads, so it takes effect only if
    # flamerecon is imported first; the user's own OMP_WAIT_POLICY or GOMP_SPINCOUNT wins.
    os.environ["GOMP_SPINCOUNT"] = "1000"

from flamerecon.resources import __version__ as __version__

#: public name -> module it lives in (imported lazily, so ``import flamerecon`` stays cheap).
API = {
    "ReconstructionOptions": "fit.options", "GridOptions": "fit.options", "ProjectorOptions": "fit.options",
    "SilhouetteOptions": "fit.options", "HullOptions": "fit.options", "SolverOptions": "fit.options",
    "PhotometryOptions": "fit.options", "SelectOptions": "fit.options",
    "DebiasOptions": "fit.debias", "RefineOptions": "fit.refine_cameras",
    "Setup": "fit.build", "build": "fit.build", "make_problem": "fit.build",
    "Reconstruction": "fit.reconstruct", "Fit": "fit.reconstruct", "SolveHook": "fit.reconstruct",
    "Stage": "fit.reconstruct", "fit": "fit", "reconstruct": "fit.reconstruct",
    "load_scene": "api", "render": "api", "score": "api", "make_solver": "api", "preset": "api",
    "export": "api", "confidence": "api", "uncertainty": "api", "Confidence": "evaluate.uncertainty",
    "UncertaintyOptions": "fit.uncertainty_options", "look_at_camera": "geometry.cameras", "orbit_cameras": "outputs.figures",
    "Run": "run.folder", "load_run": "run.folder",
    "JointFramesOptions": "fit.joint_frames", "JointReconstruction": "fit.joint_frames",
    "reconstruct_frames": "fit.joint_frames",
    "MotionOptions": "dynamics.motion", "MotionReconstruction": "dynamics.motion", "reconstruct_motion": "dynamics.motion",
    "FlowOptions": "dynamics.flow", "Flow": "dynamics.flow", "estimate_flow": "api", "advect": "dynamics.flow",
    "Problem": "solvers", "VoxelGrid": "geometry.grid", "Scene": "scenes", "view": "api",
    "framing_camera": "api", "save_image": "api",
}
# ``fit`` is the package flamerecon.fit itself, callable as flamerecon.fit.reconstruct.fit: a
# package and a function cannot both be the attribute ``flamerecon.fit``.

__all__ = ["Confidence", "DebiasOptions", "Fit", "Flow", "FlowOptions", "GridOptions", "HullOptions",
           "JointFramesOptions", "JointReconstruction", "MotionOptions", "MotionReconstruction", "PhotometryOptions",
           "Problem", "ProjectorOptions", "Reconstruction", "ReconstructionOptions", "RefineOptions", "Run", "Scene",
           "SelectOptions", "Setup", "SilhouetteOptions", "SolveHook", "SolverOptions", "Stage",
           "UncertaintyOptions", "VoxelGrid", "advect", "build", "confidence", "estimate_flow", "export", "fit",
           "framing_camera", "load_run", "load_scene", "look_at_camera", "make_problem", "make_solver", "orbit_cameras",
           "preset", "reconstruct", "reconstruct_frames", "reconstruct_motion", "render", "save_image", "score",
           "uncertainty", "view"]


def __getattr__(name: str):
    if name in API:
        module = importlib.import_module(f"{__name__}.{API[name]}")
        value = module if API[name] == name else getattr(module, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'flamerecon' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *API])
