"""Results that look like runs but mean little are said loudly (issues 20 and 33): an empty density
(a penalty that kills everything, a solver that collapsed without its guard firing), saturated
views, float images outside [0, 1], an all-black held-out view (its PSNR undefined: null in
metrics.json with the reason beside it) and a held-out PSNR below the all-black floor; then a
near-empty or non-finite density and the geometry and setup that cannot constrain a density
(one training camera, cameras at one pose, on one axis, inside the box, ...), each rule tried on
both sides of its threshold. Tables of cases over :func:`result_warnings` and its rules; then the same warnings where a user meets them: a
run's log, summary and metrics.json, ``scripts/evaluate.py`` and ``fr.score``."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace

import pytest
import torch
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.evaluate.result_warnings import (
    camera_geometry,
    near_empty,
    result_warnings,
    setup_warnings,
    view_warnings,
)
from flamerecon.evaluate.scores import score
from flamerecon.geometry.cameras import K_of, look_at, make_cameras
from flamerecon.run.runner import run_task
from tests.helpers import tiny_cfg, tiny_synthetic
from tests.helpers.scene import defective


def images_with(change):
    """The tiny scene with its images (B, C, H, W) changed in a copy."""
    def make(scene):
        images = scene.images.clone()
        change(images)
        return replace(scene, images=images)
    return make


def as_is(scene):
    return scene


def saturate(images):
    images[1] = (images[1] * 4).clamp(0, 1)


def black_heldout(images):
    images[4] = 0.0


CASES = {  # case: (scene change, density scale, (l1, l1_rel), {code: message pattern})
    "a good density": (as_is, 1.0, (0.01, 0.01), {}),
    "solver.l1_rel=1 zeroes it": (as_is, 0.0, (1.2, 1.0), {
        "empty_density": r"every voxel is zero.*solver\.l1_rel=1 is at or above 1.*lambda_max .* = 1\.2"}),
    "solver.l1_rel=1e6 zeroes it": (as_is, 0.0, (1.2e6, 1e6), {"empty_density": r"solver\.l1_rel=1e\+06 is at"}),
    "an absolute solver.l1 zeroes it": (as_is, 0.0, (5.0, None), {
        "empty_density": r"solver\.l1=5 \(L1 weight 5\) may be too strong: lower it"}),
    "a weak l1_rel, yet empty": (as_is, 0.0, (0.01, 0.01), {"empty_density": r"solver\.l1_rel=0\.01 .*solver\.lr"}),
    "no penalty, collapsed (a diverged solver)": (as_is, 0.0, (0.0, None), {
        "empty_density": r"no L1 penalty is set, so the solver likely diverged .*solver\.lr\) or solver=fista"}),
    "near zero, not zero": (as_is, 1e-9, (0.01, 0.01), {"empty_density": r"\(peak \d.*e-09; the training renders score [+-]0\.0\d\d dB against"}),
    "a saturated view": (images_with(saturate), 1.0, (0.01, 0.01), {
        "saturated": r"view 'cam01': \d+\.\d% of its pixels are at the maximum value .*holdout="}),
    "float values above 1": (images_with(lambda im: im[2].mul_(1.5)), 1.0, (0.01, 0.01), {
        "image_range": r"view 'cam02': \d+ pixel values outside \[0, 1\] \(min 0, max 1\.\d+\); float images"}),
    "negative float values": (images_with(lambda im: im[0].sub_(0.1)), 1.0, (0.01, 0.01), {
        "image_range": r"view 'cam00': \d+ pixel values outside \[0, 1\] \(min -0\.1"}),
    "an all-black held-out view": (images_with(black_heldout), 1.0, (0.01, 0.01), {
        "black_view": r"held-out view 'cam04' is all black: its PSNRs are undefined \(null in metrics\.json\)"}),
    "a render worse than black": (as_is, 30.0, (0.01, 0.01), {
        "below_black": r"held-out view 'cam04': PSNR -?\d+\.\d\d dB is below the all-black image's \d+\.\d\d dB"}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_meaningless_result_gets_its_warning(case):
    change, scale, (l1, l1_rel), expected = CASES[case]
    scene = change(tiny_synthetic())
    train, holdout = [0, 1, 2, 3], [4]
    density = scene.truth * scale
    metrics, _ = score(scene, density, scene.truth_grid, train, holdout, 0.5)
    found = {w["code"]: w["message"] for w in result_warnings(scene, density, metrics, train + holdout, l1, l1_rel)}
    assert set(found) == set(expected), found
    for code, pattern in expected.items():
        assert re.search(pattern, found[code]), found[code]


def test_a_black_views_psnrs_are_undefined_with_the_reason():
    scene = images_with(black_heldout)(tiny_synthetic())
    metrics, _ = score(scene, scene.truth, scene.truth_grid, [0, 1, 2, 3], [4], 0.5, {"threshold": 0.05})
    held = metrics["heldout"]["cam04"]
    assert held["psnr_undefined"] == "the captured view is all black"
    assert all(math.isnan(v) for k, v in held.items() if k.startswith("psnr_") and k != "psnr_undefined")
    assert math.isnan(held["psnr"]) and math.isfinite(held["ssim"])


def cli(tmp_path, capsys, *overrides):
    """(exit status, stdout, metrics.json) of a tiny run (its config kept as Hydra keeps it)."""
    cfg = tiny_cfg(*overrides)
    try:
        run_task(cfg, tmp_path)
        code = 0
    except SystemExit as stop:
        code = stop.code
    (tmp_path / ".hydra").mkdir()
    OmegaConf.save(cfg, tmp_path / ".hydra" / "config.yaml")
    return code, capsys.readouterr().out, json.loads((tmp_path / "metrics.json").read_text())


def test_a_run_that_zeroes_its_density_says_so_and_which_setting(tmp_path, capsys, caplog):
    code, out, metrics = cli(tmp_path, capsys, "solver.l1_rel=1e6")
    assert code == 0  # a warning, not a failure: the run did what it was told
    assert [w["code"] for w in metrics["warnings"]] == ["empty_density"]
    assert "solver.l1_rel=1e+06 is at or above 1" in metrics["warnings"][0]["message"]
    assert re.search(r"WARNINGS \(1\).*\n  ! empty_density: .*solver\.l1_rel=1e\+06", out), out
    assert any(r.levelname == "WARNING" and "empty_density" in r.getMessage() for r in caplog.records)


def test_a_black_heldout_view_is_undefined_in_the_run_the_script_and_the_api(tmp_path, capsys):
    from tests.test_bad_input import script

    code, out, metrics = cli(tmp_path, capsys, *defective("dark_view"), "holdout=[cam02]")
    assert code == 0
    assert metrics["heldout"]["cam02"]["psnr"] is None  # strict JSON: null, the reason beside it
    assert metrics["heldout"]["cam02"]["psnr_undefined"] == "the captured view is all black"
    assert "held-out PSNR [dB]         undefined (held-out view is black)" in out, out
    assert [w["code"] for w in metrics["warnings"]] == ["black_view"]
    assert script("evaluate").main([str(tmp_path), "--device", "cpu", "--no-native"]) == 0
    out = capsys.readouterr().out
    assert "undefined (held-out view is black)" in out and "! black_view: held-out view 'cam02'" in out, out
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["warnings"] == metrics["warnings"] and "timing" in again
    scored = fr.score(fr.load_run(tmp_path, device="cpu"))
    assert [w["code"] for w in scored["warnings"]] == ["black_view"] and "psnr_black" in scored["heldout"]["cam02"]


# ---------------------------------------------------------------------------------------------
# issue 33: the geometry and the setup, each rule's threshold tried on both sides

CENTRE = torch.tensor([0.0, 0.75, 0.0], dtype=torch.float64)


def posed(eyes: dict[int, list[float]] | None = None, K: dict[int, dict] | None = None, copy: dict | None = None):
    """The tiny scene with cameras moved: ``eyes`` {view: centre} (looking at the box centre),
    ``K`` {view: {(row, col): value or ("fx", share)}}, ``copy`` {view: view whose pose it takes}."""
    def make(scene):
        cams = scene.cameras
        E, Kmat = cams.extrinsics.double().clone(), K_of(cams).double().clone()
        for v, eye in (eyes or {}).items():
            E[v] = look_at(torch.tensor([eye], dtype=torch.float64), CENTRE[None])[0]
        for v, entries in (K or {}).items():
            for (r, c), value in entries.items():  # ("fx", k): k times the camera's focal length
                Kmat[v, r, c] = value[1] * Kmat[v, 0, 0] if isinstance(value, tuple) else value
        for v, other in (copy or {}).items():
            E[v] = E[other]
        return replace(scene, cameras=make_cameras(Kmat, E, cams.height, cams.width))
    return make


def ring(degrees: list[float], radius: float = 3.0) -> dict[int, list[float]]:
    return {v: [radius * math.sin(math.radians(a)), 0.75, radius * math.cos(math.radians(a))]
            for v, a in enumerate(degrees)}


def near(spread: float) -> dict[int, list[float]]:
    """The four training cameras within ``spread`` (share of their distance 3) of one spot."""
    return {v: [3 * spread / 2 * (v % 2), 0.75, 3.0 + 3 * spread / 2 * (v // 2)] for v in range(4)}


TRAIN4, HOLDOUT = [0, 1, 2, 3], [4]
GEOMETRY = {  # case: (scene change, training views, {codes expected})
    "a good rig": (as_is, TRAIN4, set()),
    "one training camera": (as_is, [0], {"one_camera"}),
    "two training cameras": (as_is, [0, 1], set()),
    "four cameras at one spot (0.5% apart)": (posed(near(0.005)), TRAIN4, {"one_pose"}),
    "four cameras 2% apart: one axis, not one pose": (posed(near(0.02)), TRAIN4, {"one_axis"}),
    "cameras facing each other across the box (one axis)": (
        posed({0: [0, 0.75, 3], 1: [0, 0.75, -3], 2: [0, 0.75, 4], 3: [0, 0.75, -4]}), TRAIN4, {"one_axis"}),
    "cameras 4 deg apart": (posed(ring([0, 4, 180, 184])), TRAIN4, {"one_axis"}),
    "cameras 6 deg apart": (posed(ring([0, 6, 180, 186])), TRAIN4, set()),
    "a camera inside the box": (posed({0: [0.0, 0.75, 0.4]}), TRAIN4, {"camera_inside_box"}),
    "a camera just outside the box": (posed({0: [0.0, 0.75, 0.6]}), TRAIN4, set()),
    "two training views at one pose, different images": (posed(copy={0: 1}), TRAIN4, {"duplicate_pose"}),
    "a held-out camera at a training camera's pose": (posed(copy={4: 2}), TRAIN4, {"heldout_at_training_pose"}),
    "a skew of 20% of the focal length": (posed(K={1: {(0, 1): ("fx", 0.2)}}), TRAIN4, {"skew"}),
    "a skew of 5%": (posed(K={1: {(0, 1): ("fx", 0.05)}}), TRAIN4, set()),
    "a principal point right of the image": (posed(K={2: {(0, 2): 58.0}}), TRAIN4, {"principal_point"}),
    "a principal point at the image's edge": (posed(K={2: {(0, 2): 47.0}}), TRAIN4, set()),
}


@pytest.mark.parametrize("case", list(GEOMETRY))
def test_a_degenerate_camera_geometry_gets_its_warning(case):
    change, train, expected = GEOMETRY[case]
    scene = change(tiny_synthetic())
    found = {w["code"]: w["message"] for w in camera_geometry(scene, train, [v for v in range(5) if v not in train])}
    assert set(found) == expected, found


SETUP = {  # case: (step, grid cells, volume scores, calibration, training views, {codes})
    "the default step": (0.5, (16, 24, 16), None, None, TRAIN4, set()),
    "a step of one voxel": (1.0, (16, 24, 16), None, None, TRAIN4, set()),
    "a step past one voxel": (1.5, (16, 24, 16), None, None, TRAIN4, {"coarse_step"}),
    "a step larger than the grid": (40.0, (16, 24, 16), None, None, TRAIN4, {"coarse_step"}),
    "a 2x3x2 grid with IoU 1 and L2 1.09": ((0.5), (2, 3, 2), {"iou": 1.0, "rel_l2": 1.09}, None, TRAIN4,
                                             {"coarse_grid", "tiny_grid", "no_closer_than_zero"}),
    "a 1x1x1 grid (a capture: no volume scores)": (0.5, (1, 1, 1), None, None, TRAIN4, {"coarse_grid"}),
    "a 3-cell axis": (0.5, (3, 12, 8), None, None, TRAIN4, {"coarse_grid"}),
    "4 cells along the shortest axis": (0.5, (4, 12, 8), None, None, TRAIN4, set()),
    "an 8-cell grid": (0.5, (8, 12, 8), {"iou": 0.8, "rel_l2": 0.3}, None, TRAIN4, set()),
    "a 7-cell grid": (0.5, (7, 10, 7), {"iou": 0.8, "rel_l2": 0.3}, None, TRAIN4, {"tiny_grid"}),
    "relative L2 just below 1": (0.5, (16, 24, 16), {"iou": 0.1, "rel_l2": 0.99}, None, TRAIN4, set()),
    "a camera fit with one training camera": (0.5, (16, 24, 16), None, {"source": "fitted"}, [0],
                                              {"camera_fit_inert"}),
    "a camera fit with two": (0.5, (16, 24, 16), None, {"source": "fitted"}, [0, 1], set()),
}


@pytest.mark.parametrize("case", list(SETUP))
def test_a_degenerate_setup_gets_its_warning(case):
    step, cells, volume, calibration, train, expected = SETUP[case]
    metrics = {k: v for k, v in (("volume", volume), ("calibration", calibration)) if v is not None}
    found = {w["code"]: w["message"] for w in setup_warnings(train, step, cells, metrics)}
    assert set(found) == expected, found


def fov_of_voxels(voxels: float):
    """The tiny scene with camera 1's focal lengths set so that its whole image spans ``voxels``
    voxels of a 16-cell grid at the box centre."""
    def make(scene):
        lo, hi = torch.tensor(scene.bbox_min, dtype=torch.float64), torch.tensor(scene.bbox_max, dtype=torch.float64)
        voxel = float((hi - lo).max() / 16)
        depth = float((scene.cameras.extrinsics[1].double() @ torch.cat([(lo + hi) / 2, torch.ones(1).double()]))[2])
        H, W = scene.image_size
        f = max(W, H) * depth / (voxels * voxel)  # the longer side spans `voxels` voxels
        return posed(K={1: {(0, 0): f, (1, 1): f}})(scene)
    return make


VIEWS_FOV = {  # case: (scene change, {codes})
    "the tiny rig": (as_is, set()),
    "a view spanning 0.9 voxel": (fov_of_voxels(0.9), {"narrow_view"}),
    "a view spanning 1.1 voxels": (fov_of_voxels(1.1), set()),
    "a view spanning 0.01 voxel (a focal length in the wrong units)": (fov_of_voxels(0.01), {"narrow_view"}),
}


@pytest.mark.parametrize("case", list(VIEWS_FOV))
def test_a_view_narrower_than_a_voxel_gets_its_warning(case):
    change, expected = VIEWS_FOV[case]
    scene = change(tiny_synthetic())
    cells = tuple(int(n) for n in (torch.tensor(scene.bbox_max) - torch.tensor(scene.bbox_min)).div(
        max(b - a for a, b in zip(scene.bbox_min, scene.bbox_max)) / 16).round().tolist())
    found = {w["code"]: w["message"] for w in view_warnings(scene, list(range(5)), (scene.bbox_min, scene.bbox_max),
                                                             cells)}
    assert set(found) == expected, found
    if expected:
        assert re.search(r"view 'cam01': its whole image spans .* less than one voxel", found["narrow_view"])


@pytest.mark.parametrize("gain, warned", [(0.16, True), (0.99, True), (1.0, False), (12.0, False), (-3.0, False)])
def test_a_near_empty_density_is_said_so_below_one_db(gain, warned):
    density = torch.zeros(3, 4, 4, 4)
    density[:, 0, 0, 0] = 1.0
    found = near_empty(density, gain, 0.9, 0.9)
    assert bool(found) == warned
    if warned:
        assert re.search(r"all but empty \(1 of 64 voxels nonzero; .*solver\.l1_rel=0\.9 is likely too strong",
                         found[0]["message"]), found


def test_a_nan_density_is_not_blamed_on_the_penalty():
    scene, train, holdout = tiny_synthetic(), [0, 1, 2, 3], [4]
    density = scene.truth.clone()
    metrics, _ = score(scene, density, scene.truth_grid, train, holdout, 0.5)
    density[0, 0, 0, 0] = math.nan
    found = result_warnings(scene, density, metrics, train + holdout, 0.01, 0.01)
    assert [w["code"] for w in found] == ["nonfinite_density"]
    assert "l1_rel" not in found[0]["message"] and "1 NaN/Inf values" in found[0]["message"]


def test_a_run_reports_its_geometry_warnings(tmp_path, capsys):
    code, out, metrics = cli(tmp_path, capsys, "holdout=[1,2,3,4]", "grid.resolution=6")
    assert code == 0
    codes = {w["code"] for w in metrics["warnings"]}
    assert {"one_camera", "tiny_grid"} <= codes, codes
    assert "! one_camera: 1 training camera" in out


def test_a_one_cell_grid_ends_with_a_warning_in_the_summary_and_metrics(tmp_path, capsys):
    code, out, metrics = cli(tmp_path, capsys, "grid.resolution=1")
    assert code == 0
    assert "coarse_grid" in {w["code"] for w in metrics["warnings"]}
    assert re.search(r"! coarse_grid: a 1x1x1-cell grid: fewer than 4 cells", out), out
