"""Cameras in the confidence (flamerecon.fit.pose_uncertainty, flamerecon.evaluate.pose_spread):
a camera's pose offset found against a density it is known to be off from, the share of the
render's change its images confirm, the pose spread of a render against renders by hand, the
capture's calibration file with every camera's pose uncertainty, and a run that names the camera
whose calibration limits it."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace

import pytest
import torch

import flamerecon as fr
from flamerecon.errors import ArgumentError
from flamerecon.evaluate.metrics import resample_to
from flamerecon.evaluate.uncertainty import load_confidence, predicted_psnr, save_confidence
from flamerecon.fit.build import scene_masks
from flamerecon.fit.ensemble import confidence, posed_pixels
from flamerecon.fit.pose_uncertainty import (
    PoseOffset,
    corrections_between,
    measure_offset,
    offsets_of,
    pose_report,
    spread,
)
from flamerecon.fit.refine_cameras import RefineOptions, corrected_cameras, with_cameras
from flamerecon.geometry.cameras import camera_subset, project_points
from flamerecon.run.summary import limiting_text
from tests.helpers import CliRun

SCENE = {"width": 48, "height": 36, "n_cameras": 5, "phantom_resolution": 32}


def offset(theta, before, after, change, source, curvature=None) -> PoseOffset:
    """A pose offset with the figures given (no curvature unless given)."""
    return PoseOffset(theta, before, after, change, source,
                      torch.zeros(9, 9, dtype=torch.float64) if curvature is None else curvature)


@pytest.fixture(scope="module")
def scene():
    return fr.load_scene("synthetic", **SCENE)


@pytest.fixture(scope="module")
def truth(scene):
    """The scene's phantom on a 24-cell grid of its box: a density its images agree with."""
    grid = fr.VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 24)
    return grid, resample_to(scene.truth, grid.shape)


def test_corrections_read_off_two_cameras_are_those_that_moved_one_onto_the_other(scene):
    pivot = torch.tensor([0.1, 0.5, -0.2])
    theta = torch.zeros(scene.num_views, 9)
    theta[:, :3] = 0.01 * torch.arange(1, 4)
    theta[:, 3:6] = torch.tensor([0.02, -0.01, 0.03])
    theta[:, 6], theta[:, 7:9] = 0.01, torch.tensor([0.5, -0.25])
    moved = corrected_cameras(scene.cameras, theta, pivot)
    torch.testing.assert_close(corrections_between(scene.cameras, moved, pivot).float(), theta, atol=2e-5, rtol=1e-4)


def test_a_camera_off_by_a_known_motion_is_fitted_back_and_its_images_confirm_it(scene, truth):
    grid, density = truth
    pivot = 0.5 * (grid.lo() + grid.hi())
    error = torch.zeros(1, 9)
    error[0, 3:6] = torch.tensor([0.03, -0.02, 0.0])  # world units: about a pixel and a half here
    view = 2
    given = corrected_cameras(camera_subset(scene.cameras, [view]), error, pivot)
    images = fr.render(density, grid, camera_subset(scene.cameras, [view]))  # what the true camera sees
    masks = scene_masks(scene, scene.images, fr.ReconstructionOptions())[view:view + 1]
    found = measure_offset([density], grid, given, [images[0]], [masks[0]], 0.5, pivot,
                           RefineOptions(refine="pose", max_rays=4000), "test")
    back = corrected_cameras(given, found.theta[None].float(), pivot)
    target = camera_subset(scene.cameras, [view])
    # the fitted camera sees the box where the true one does, to a fraction of the error's shift
    corners = grid.corners()
    off_before = (project_points(given, corners)[0] - project_points(target, corners)[0]).norm(dim=-1).mean()
    off_after = (project_points(back, corners)[0] - project_points(target, corners)[0]).norm(dim=-1).mean()
    assert float(off_after) < 0.3 * float(off_before)
    assert found.after < 0.3 * found.before and 0.7 < found.share <= 1.0
    spread_of = found.curvature[3:6, 3:6].diagonal().sqrt()  # the fit's one sigma of the translation
    assert bool((spread_of > 0).all()) and float(spread_of.max()) < 0.3 * float(error.abs().max())


def test_the_share_is_the_part_of_the_change_the_images_confirm():
    theta = torch.zeros(9, dtype=torch.float64)
    assert offset(theta, 4.0, 1.0, 6.0, "x").share == pytest.approx(0.5)
    assert offset(theta, 4.0, 5.0, 6.0, "x").share == 0.0  # moving made it worse: nothing confirmed
    assert offset(theta, 9.0, 1.0, 4.0, "x").share == 1.0  # at most all of it
    assert offset(theta, 1.0, 1.0, 0.0, "x").share == 0.0
    again = PoseOffset.from_record(offset(theta + 0.5, 4.0, 1.0, 6.0, "y", torch.eye(9, dtype=torch.float64)).record())
    assert torch.equal(again.curvature, torch.eye(9, dtype=torch.float64))
    assert again.share == pytest.approx(0.5) and float(again.theta[0]) == 0.5 and again.source == "y"
    assert offsets_of(None) == {} and offsets_of({"poses": {"a": again.record()}})["a"].before == 4.0


def test_the_pose_spread_of_a_render_is_the_share_of_its_change_both_ways(scene, truth):
    grid, density = truth
    pivot = 0.5 * (grid.lo() + grid.hi())
    theta = torch.zeros(9, dtype=torch.float64)
    theta[3], theta[1] = 0.04, 0.02
    offsets = {"cam01": offset(theta, 5.0, 2.0, 4.0, "test")}  # share 0.75
    found = spread(scene.cameras, list(scene.views), offsets, grid)
    assert found.views == ["cam01"] and found.limiting() == "cam01"
    variance = found.variance(density, grid, scene.cameras, list(scene.views))
    assert float(variance[[0, 2, 3, 4]].abs().max()) == 0.0  # a camera without an offset adds nothing
    cam = camera_subset(scene.cameras, [1])
    base = fr.render(density, grid, cam)[0].clamp(0, 1)
    moved = [fr.render(density, grid, corrected_cameras(cam, s * theta[None].float(), pivot))[0].clamp(0, 1)
             for s in (1, -1)]
    expected = 0.75 * 0.5 * sum((m - base).pow(2) for m in moved)
    torch.testing.assert_close(variance[1], expected, atol=1e-7, rtol=1e-4)
    r = found.records()["cam01"]
    assert r["pose_sigma_deg"] == pytest.approx(float(torch.rad2deg(torch.tensor(0.02))) * 0.75 ** 0.5, rel=1e-4)
    assert r["pose_sigma_box_px"] > 0 and r["pose_share"] == pytest.approx(0.75)
    assert r["pose_lost_db"] == pytest.approx(10 * math.log10(5.0 / 2.0), rel=1e-5)
    novel = found.variance(density, grid, cam, [None])  # a novel camera: no pose of its own to doubt
    assert float(novel.abs().max()) == 0.0
    curvature = torch.zeros(9, 9, dtype=torch.float64)
    curvature[:3, :3] = torch.diag(torch.tensor([1e-4, 4e-4, 1e-4], dtype=torch.float64))  # sigma 0.01, 0.02, 0.01 rad
    fitted = spread(scene.cameras, list(scene.views), {"cam01": offset(theta, 5.0, 2.0, 4.0, "t", curvature)}, grid,
                    {"cam01"})  # refined by a camera fit: its curvature, not its offset
    r = fitted.records()["cam01"]
    assert r["pose_sigma_deg"] == pytest.approx(math.degrees(math.sqrt(6e-4)), rel=1e-4) and r["pose_share"] == 1.0
    axis = torch.tensor([[0.0, 0.02, 0, 0, 0, 0, 0, 0, 0]])  # its principal axis, one sigma, both ways
    both = torch.cat([corrected_cameras(cam, sign * axis, pivot).extrinsics for sign in (1, -1)])
    moved = fitted.moved("cam01", cam).extrinsics
    assert min(float((moved - both).abs().max()), float((moved - both.flip(0)).abs().max())) < 1e-5


def test_the_confidence_adds_a_named_cameras_pose_spread_and_keeps_it_in_its_file(scene, tmp_path):
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                       solver=fr.SolverOptions("fista", None, 1e-3, {"max_iters": 20}))
    rec = fr.reconstruct(scene, options)
    theta = torch.zeros(9, dtype=torch.float64)
    theta[4] = 0.05
    calibration = {"poses": {"cam04": offset(theta, 3.0, 1.0, 2.0, "test").record()}}
    conf = confidence(rec.setup, rec.options, rec.fit.result.x, fr.UncertaintyOptions(scale=1.0), calibration)
    cams = camera_subset(rec.scene.cameras, [4])
    alone, named = conf.image(cams), conf.image(cams, ["cam04"])
    added = conf.poses.variance(rec.density, rec.grid, cams, ["cam04"])
    torch.testing.assert_close(named.pow(2), alone.pow(2) + added, atol=1e-8, rtol=1e-4)
    assert predicted_psnr(named[0]) < predicted_psnr(alone[0])
    again = load_confidence(save_confidence(tmp_path / "u.npz", conf, ["a"]))
    torch.testing.assert_close(again.image(cams, ["cam04"]), named)
    assert again.poses.views == conf.poses.views and again.poses.sources == conf.poses.sources
    torch.testing.assert_close(fr.uncertainty(conf, cams, ["cam04"]), named)
    with pytest.raises(ArgumentError, match=r"^uncertainty.views: "):
        fr.uncertainty(conf, cams, ["cam04", "cam03"])


def test_the_capture_check_says_which_camera_the_others_disagree_with(scene):
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                       solver=fr.SolverOptions("fista", None, 1e-3, {"max_iters": 20}))
    off = torch.zeros(1, 9)
    off[0, 3:6] = torch.tensor([0.12, 0.09, 0.0])  # about 3 px at the box
    grid = fr.VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 16)
    pivot = 0.5 * (grid.lo() + grid.hi())
    cams = scene.cameras
    bad = corrected_cameras(camera_subset(cams, [3]), off, pivot)
    shaken = replace(scene, cameras=with_cameras(cams, [3], bad))
    lines = pose_report(shaken, options)
    assert lines[0].startswith("pose uncertainty") and len(lines) == 2 + scene.num_views + 1
    assert lines[-1].startswith("least certain: cam03")


@pytest.mark.e2e
def test_a_capture_calibration_keeps_every_cameras_pose_uncertainty_and_the_run_names_the_worst(tmp_path):
    run = tmp_path / "run"
    done = CliRun(run, "uncertainty.enabled=true", "calibration.refine=pose", "calibration.frames=[1,2]",
                  "calibration.rounds=1", f"calibration.folder={tmp_path / 'calibration'}", "threads=1").result()
    assert done.returncode == 0, done.stderr
    files = list((tmp_path / "calibration").rglob("cameras-*.json"))
    assert len(files) == 1
    records = json.loads(files[0].read_text())["cameras"]
    assert {r["name"] for r in records if "pose_sigma_deg" in r} == {r["name"] for r in records}  # held out too
    assert all(r["pose_sigma_box_px"] >= 0 and 0 <= r["pose_share"] <= 1 for r in records)
    metrics = json.loads((run / "metrics.json").read_text())
    u = metrics["uncertainty"]
    worst = max(u["poses"], key=lambda name: u["poses"][name]["pose_lost_db"])
    assert metrics["calibration"]["limiting_camera"] == worst
    assert metrics["calibration"]["limiting_lost_db"] == pytest.approx(u["poses"][worst]["pose_lost_db"], rel=1e-5)
    assert re.search(rf"calibration limits +{worst}: .* dB .*uncertain by", done.stdout)
    assert set(u["poses"]) == {r["name"] for r in records}


@pytest.mark.e2e
def test_a_capture_calibration_measures_the_pose_offsets_only_where_asked_and_adds_them_to_its_file(tmp_path):
    """A capture's first run pays for the camera fit alone: its calibration file holds no pose
    offsets and the summary says how to measure them; a later run asking for them
    (calibration.offsets=true) measures them once into the same file, its cameras untouched."""
    fit = ["calibration.refine=pose", "calibration.frames=[1,2]", "calibration.rounds=1",
           f"calibration.folder={tmp_path / 'calibration'}", "threads=1"]
    first = CliRun(tmp_path / "first", *fit).result()
    assert first.returncode == 0, first.stderr
    [path] = (tmp_path / "calibration").rglob("cameras-*.json")
    before = json.loads(path.read_text())
    assert not any("pose_offset" in r for r in before["cameras"])
    assert "limiting_camera" not in json.loads((tmp_path / "first" / "metrics.json").read_text())["calibration"]
    assert re.search(r"calibration limits +not measured: calibration.offsets=true", first.stdout)
    second = CliRun(tmp_path / "second", *fit, "calibration.offsets=true").result()
    assert second.returncode == 0, second.stderr
    assert list((tmp_path / "calibration").rglob("cameras-*.json")) == [path]
    after = json.loads(path.read_text())
    assert after["calibration"] == before["calibration"]
    assert [r["world_to_camera"] for r in after["cameras"]] == [r["world_to_camera"] for r in before["cameras"]]
    assert all("pose_offset" in r and r["pose_sigma_deg"] >= 0 for r in after["cameras"])
    metrics = json.loads((tmp_path / "second" / "metrics.json").read_text())
    assert metrics["calibration"]["source"] == "read" and metrics["calibration"]["limiting_camera"] in {
        r["name"] for r in after["cameras"]}
    assert re.search(rf"calibration limits +{metrics['calibration']['limiting_camera']}: .* dB", second.stdout)


def test_the_poses_members_see_the_training_cameras_moved_and_are_not_scaled(scene):
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                       solver=fr.SolverOptions("fista", None, 1e-3, {"max_iters": 20}))
    rec = fr.reconstruct(scene, options)
    theta = torch.zeros(9, dtype=torch.float64)
    theta[3] = 0.05
    offsets = {"cam01": offset(theta, 3.0, 1.0, 2.0, "test")}  # a training camera, share 1
    poses = spread(rec.scene.cameras, list(rec.scene.views), offsets, rec.grid)
    found = posed_pixels(rec.setup, rec.fit.result.x, poses)
    assert [label for label, _ in found] == ["poses:+", "poses:-"]
    k = rec.setup.train.index(1)
    for _, pixels in found:
        moved = (pixels - rec.setup.pixels).abs().amax(1) > 0
        assert bool(moved.any()) and bool((rec.setup.row_view[moved] == k).all())  # cam01's rows only
    calibration = {"poses": {"cam01": offsets["cam01"].record()}}
    one, two = (confidence(rec.setup, rec.options, rec.fit.result.x, fr.UncertaintyOptions(scale=s, shift_voxels=0),
                           calibration) for s in (1.0, 2.0))
    assert one.groups.count("poses") == 2
    parts = one.variance_parts()
    torch.testing.assert_close(two.volume().pow(2), 4 * parts["cameras"] + parts["poses"], atol=1e-10, rtol=1e-4)


def test_the_summary_names_the_camera_whose_pose_error_cost_most():
    calibration = {"limiting_camera": "cam02", "limiting_lost_db": 4.47}
    assert limiting_text(calibration, {}) == ("cam02: its pose error cost its images 4.47 dB on the calibration "
                                              "frames, the most of any camera")
    poses = {"cam02": {"pose_sigma_deg": 1.5, "pose_sigma_box_px": 3.25}}
    assert "uncertain by 1.50 deg, 3.25 px at the box" in limiting_text(calibration, poses)
