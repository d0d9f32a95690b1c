"""The resolution ladder (``ladder.rungs``): coarser images and grids solved before the run's
own, each warm-starting the next; only the rungs coarser than the run's images run; the camera
fit runs once on the coarsest rung's images and its cameras carry over with their intrinsics
scaled; the final level takes ``ladder.final_iterations``; bad ladders are refused by name."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

import flamerecon as fr
from flamerecon.errors import ConfigError, FlameReconError
from flamerecon.fit.levels import LadderOptions, ladder_rungs
from flamerecon.fit.reconstruct import calibrated_scene, scene_grid
from flamerecon.geometry.cameras import K_of, project_points, resized_cameras
from flamerecon.run.pipeline import reconstruct as run_reconstruct
from flamerecon.solvers import Solver
from tests.helpers import tiny_config

#: a small synthetic capture whose loader takes scene.downscale: 96x72 px at downscale 1
CAPTURE = {"name": "synthetic", "n_cameras": 5, "width": 96, "height": 72, "phantom_resolution": 32}


def capture(downscale: int = 1):
    return fr.load_scene({**CAPTURE, "downscale": downscale})


def options(**ladder) -> fr.ReconstructionOptions:
    return fr.ReconstructionOptions.from_dict({
        "grid": {"resolution": 16}, "device": "cpu", "threads": 1,
        "solver": {"name": "fista", "max_iters": 10, "tol": 0.0}, "ladder": ladder})


def test_only_the_rungs_coarser_than_the_run_s_images_run():
    rungs = LadderOptions(((4, 8), (2, 12)))
    full, half = capture(1), capture(2)
    fine = scene_grid(options().grid, full)
    assert [(r.downscale, r.grid.resolution[1]) for r in ladder_rungs(full, rungs, fine)] == [(4, 8), (2, 12)]
    assert [r.downscale for r in ladder_rungs(half, rungs, fine)] == [4]
    assert ladder_rungs(capture(4), rungs, fine) == []  # the default run of a preset: nothing added


def test_resized_cameras_are_the_cameras_a_coarser_load_makes():
    full, quarter = capture(1), capture(4)
    resized = resized_cameras(full.cameras, *quarter.image_size)
    torch.testing.assert_close(K_of(resized), K_of(quarter.cameras), rtol=1e-6, atol=1e-5)
    assert torch.equal(resized.extrinsics, full.cameras.extrinsics)
    # a continuous pixel coordinate scales with the image: pixel centres at +0.5
    points = torch.tensor([[0.0, 0.5, 0.0], [0.1, 0.3, -0.2]])
    uv_full, _ = project_points(full.cameras, points)
    uv_quarter, _ = project_points(resized, points)
    torch.testing.assert_close(uv_quarter * 4, uv_full, rtol=1e-5, atol=1e-3)


def test_each_rung_solves_its_own_images_and_warm_starts_the_next(monkeypatch):
    starts = []
    original = Solver.solve

    def recording(self, problem, x0=None, callback=None):
        starts.append(None if x0 is None else float(x0.abs().sum()))
        return original(self, problem, x0=x0, callback=callback)

    monkeypatch.setattr(Solver, "solve", recording)
    rec = fr.reconstruct(capture(1), options(rungs=[[4, 8], [2, 12]], iterations=[6, 8], final_iterations=5))
    images = [level["image"] for level in rec.levels]
    assert images == [[24, 18], [48, 36], [96, 72]]
    assert [level["resolution"][1] for level in rec.levels] == [8, 12, 16]
    assert [level["iterations"] for level in rec.levels] == [6, 8, 5]
    assert rec.options.solver.params["max_iters"] == 5  # what the final level was solved with
    assert starts[0] is None and all(s is not None and s > 0 for s in starts[1:])  # each from the last
    held = fr.score(rec)["heldout"]["cam04"]
    assert held["psnr"] > held["psnr_black"] + 10


def test_the_camera_fit_runs_once_on_the_coarsest_rung_and_its_cameras_serve_the_run():
    fit = {"refine": "pose", "rounds": 1, "iterations": 1, "max_rays": 500, "first_iterations": 10,
           "solve_iterations": 5, "min_gain": 0.0}  # exact cameras: run the fit though it finds nothing
    laddered = options(rungs=[[2, 12]]).replace(calibration=fr.RefineOptions(**fit))
    scene, record = calibrated_scene(capture(1), laddered, torch.device("cpu"))
    assert record["downscale"] == 2
    coarse = laddered.replace(ladder=LadderOptions(), grid=replace(laddered.grid, resolution=12))
    alone, _ = calibrated_scene(capture(2), coarse, torch.device("cpu"))  # as a run at 1/2 fits them
    expected = resized_cameras(alone.cameras, 72, 96)
    torch.testing.assert_close(K_of(scene.cameras), K_of(expected))
    torch.testing.assert_close(scene.cameras.extrinsics, expected.extrinsics)
    assert not torch.equal(scene.cameras.extrinsics, capture(1).cameras.extrinsics)  # they were fitted
    assert torch.equal(scene.meta["calibrated_cameras"].extrinsics, capture(1).cameras.extrinsics)


def test_a_scene_not_loaded_by_load_scene_cannot_climb_the_ladder():
    scene = capture(1)
    bare = replace(scene, meta={k: v for k, v in scene.meta.items() if k != "config"})
    with pytest.raises(ConfigError, match=r"ladder.rungs: this scene was not loaded by load_scene"):
        fr.reconstruct(bare, options(rungs=[[2, 12]]))


@pytest.mark.parametrize("ladder, match", [
    ({"rungs": [[2, 12], [4, 8]]}, r"ladder.rungs: .*downscales decrease, coarsest first"),
    ({"rungs": [[0, 12]]}, r"ladder.rungs: .*a list of rungs \[downscale, grid resolution\]"),
    ({"rungs": [[2, 12, 1]]}, r"ladder.rungs: .*a list of rungs"),
    ({"rungs": [[4, 8], [2, 12]], "iterations": [5]}, r"ladder.iterations: .*one per rung"),
    ({"final_iterations": 0}, r"ladder.final_iterations: .*integer >= 1"),
])
def test_a_bad_ladder_is_refused_by_name(ladder, match):
    with pytest.raises(FlameReconError, match=match):
        options(**ladder)


def test_a_run_records_each_rung_in_its_metrics(tmp_path):
    cfg = tiny_config("scene.width=96", "scene.height=72", "ladder.rungs=[[4,8],[2,12]]", "ladder.final_iterations=5",
                      "solver.max_iters=8", "log.eval_every=0", "checkpoint.every=0")
    run_reconstruct(cfg, tmp_path / "run")
    levels = json.loads((tmp_path / "run" / "metrics.json").read_text())["solver"]["levels"]
    assert [level["image"] for level in levels] == [[24, 18], [48, 36], [96, 72]]
    assert [level["iterations"] for level in levels] == [8, 8, 5]
