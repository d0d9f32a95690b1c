"""Camera self-calibration (flamerecon/fit/refine_cameras.py): the corrections' parametrization and
gauge, their Jacobian against finite differences, the camera fit recovering perturbed
cameras, and a run with ``calibration.refine`` writing what it found."""

from __future__ import annotations

import functools
import json
import math
from dataclasses import replace

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.evaluate.metrics import resample_to
from flamerecon.fit.refine_cameras import (
    N_PARAMS,
    CalibrationFrame,
    CameraFit,
    RefineOptions,
    align_similarity,
    corrected_cameras,
    fit_pixels,
    gauge_basis,
    ray_tangents,
    refine,
    similarity,
    skew,
    with_cameras,
)
from flamerecon.geometry.cameras import (
    K_of,
    camera_centers,
    camera_subset,
    make_cameras,
    pixel_rays,
    project_points,
)
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.run.pipeline import evaluate, reconstruct, refine_options, summary_table
from flamerecon.scenes import load_scene
from tests.helpers import REPO


@functools.lru_cache(maxsize=1)
def scene64():
    """The synthetic flame, 6 cameras at 64x48 from a 96-cell phantom (cam05 held out)."""
    return load_scene({"name": "synthetic", "n_cameras": 6, "width": 64, "height": 48,
                       "phantom_resolution": 96, "seed": 0, "frame": 0})


def perturbation(cams, pivot, degrees=0.5, fraction=0.01, pixels=2.0, seed=1) -> torch.Tensor:
    """Corrections theta (T, 9) that turn each camera by ``degrees`` about a random axis, move
    its centre by ``fraction`` of its distance to ``pivot`` and its principal point by
    ``pixels``, with the common part (a motion of every camera together, which no training
    view can see) projected out as :func:`gauge_basis` does."""
    g = torch.Generator().manual_seed(seed)
    T = cams.batch_size
    unit = torch.nn.functional.normalize(torch.randn(2, T, 3, generator=g), dim=-1)
    theta = torch.zeros(T, N_PARAMS)
    theta[:, :3] = unit[0] * math.radians(degrees)
    c = camera_centers(cams)
    R = torch.linalg.matrix_exp(skew(theta[:, :3]))
    moved = c + unit[1] * fraction * (c - pivot).norm(dim=-1, keepdim=True)
    theta[:, 3:6] = moved - pivot - (R @ (c - pivot)[..., None]).squeeze(-1)
    angle = torch.rand(T, generator=g) * 2 * math.pi
    theta[:, 7], theta[:, 8] = pixels * torch.cos(angle), pixels * torch.sin(angle)
    basis = gauge_basis(cams, pivot, torch.ones(T, N_PARAMS, dtype=torch.float64), list(range(N_PARAMS)))
    return (basis @ (basis.T @ theta.double().reshape(-1))).reshape(T, N_PARAMS).float()


def fixed_density(volume: torch.Tensor):
    """A CalibrationFrame's ``solve`` that returns ``volume`` whatever the cameras."""
    return lambda views, cams, start: volume


def corner_error(cams, truth, grid) -> float:
    """Mean distance in pixels between the box corners' projections in ``cams`` and ``truth``."""
    a, _ = project_points(cams, grid.corners())
    b, _ = project_points(truth, grid.corners())
    return float((a - b).norm(dim=-1).mean())


def test_options_refuse_an_unknown_mode_and_bad_sizes_by_field():
    with pytest.raises(ValueError, match="calibration.refine"):
        RefineOptions(refine="bundle")
    with pytest.raises(ValueError, match="calibration.prior_focal"):
        RefineOptions(refine="pose", prior_focal=0.0)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["++calibration.steps=3"])
    with pytest.raises(ConfigError, match="calibration: .*steps"):
        refine_options(cfg)


def test_zero_corrections_leave_the_cameras_as_they_are(small_scene):
    cams = small_scene.cameras
    pivot = torch.tensor([0.0, 0.75, 0.0])
    same = corrected_cameras(cams, torch.zeros(cams.batch_size, N_PARAMS), pivot)
    assert torch.allclose(same.extrinsics, cams.extrinsics, atol=1e-6)
    assert torch.allclose(K_of(same), K_of(cams))


def test_the_gauge_allows_no_common_motion_and_no_common_scaling(small_scene):
    cams = small_scene.cameras
    T, pivot = cams.batch_size, torch.tensor([0.0, 0.75, 0.0])
    sizes = torch.rand(T, N_PARAMS, dtype=torch.float64) + 0.5
    basis = gauge_basis(cams, pivot, sizes, list(range(6)))
    assert basis.shape == (T * N_PARAMS, 6 * T - 7)  # 3 rotations, 3 translations, 1 scale fixed
    theta = (basis @ torch.randn(basis.shape[1], dtype=torch.float64)).reshape(T, N_PARAMS) * sizes
    # the same world motion of every camera would show as a nonzero mean
    assert torch.allclose(theta.mean(0), torch.zeros(N_PARAMS, dtype=torch.float64), atol=1e-12)
    outward = (camera_centers(cams) - pivot).double()
    assert abs(float((theta[:, 3:6] * outward).sum())) < 1e-12  # no common scaling about the pivot
    assert float(theta[:, 6:].abs().max()) < 1e-12  # intrinsics stay put with refine=pose
    assert float(theta[:, :6].abs().max()) > 0


def test_ray_tangents_match_forward_mode_autodiff_far_from_zero():
    """The analytic d ray / d theta against torch.func's forward mode through corrected_cameras
    and pixel_rays, at corrections of about 10 degrees and 20 px (the right Jacobian of SO(3)
    matters there), every parameter; an inactive parameter's tangents are zero."""
    cams = camera_subset(scene64().cameras, [0, 1, 2])
    g = torch.Generator().manual_seed(3)
    theta = torch.randn(3, N_PARAMS, generator=g) * torch.tensor([0.2] * 3 + [0.05] * 3 + [0.05, 20.0, 20.0])
    pivot = torch.tensor([0.1, -0.05, 0.2])
    uv = torch.rand(3, 40, 2, generator=g) * torch.tensor([64.0, 48.0])

    def rays(th: torch.Tensor) -> torch.Tensor:
        origins, directions = pixel_rays(corrected_cameras(cams, th, pivot), uv)
        return torch.cat([origins, directions], -1)

    for k in range(N_PARAMS):
        direction = torch.zeros_like(theta)
        direction[:, k] = 1.0
        reference = torch.func.jvp(rays, (theta,), (direction,))[1].double()  # (T, R, 6)
        ours = ray_tangents(cams, theta, pivot, uv, list(range(N_PARAMS)))[..., k]
        scale = float(reference.abs().max())
        assert scale > 0 and float((ours - reference).abs().max()) <= 1e-5 * scale, k
    assert float(ray_tangents(cams, theta, pivot, uv, [0, 1, 2])[..., 3:].abs().max()) == 0


def test_the_jacobian_of_rendered_pixels_matches_finite_differences():
    scene = scene64()
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 24)
    volume = resample_to(scene.truth, grid.shape)
    cams = camera_subset(scene.cameras, [0, 1, 2])
    pivot = 0.5 * (grid.lo() + grid.hi())
    index, valid = fit_pixels(silhouettes(scene.images[:3]), 2, 3000, torch.Generator().manual_seed(0))
    fit = CameraFit([volume] * 3, grid, cams, pivot, scene.images[:3], index, valid, 0.5)
    g = torch.Generator().manual_seed(2)
    theta = torch.randn(3, N_PARAMS, generator=g) * torch.tensor([0.004] * 3 + [0.02] * 3 + [0.01, 1.0, 1.0])
    _, J = fit.jacobian(theta, list(range(N_PARAMS)))
    weights = torch.randn(J.shape[:2], generator=g)
    h = torch.tensor([1e-3] * 3 + [2e-3] * 3 + [1e-3, 0.05, 0.05])  # about 0.05-0.15 px each
    analytic, numeric = [], []
    for k in range(N_PARAMS):
        d = torch.zeros(3, N_PARAMS)
        d[:, k] = h[k]
        numeric.append(float(((fit.residuals(theta + d) - fit.residuals(theta - d)) * weights).sum() / 2))
        analytic.append(float((J[..., k] * weights).sum() * h[k]))
    analytic, numeric = torch.tensor(analytic), torch.tensor(numeric)
    scale = float(numeric.abs().max())
    assert scale > 0
    # trilinear interpolation has kinks at voxel faces, so a few percent is what agrees
    assert float((analytic - numeric).abs().max()) < 0.1 * scale
    assert float(torch.nn.functional.cosine_similarity(analytic, numeric, dim=0)) > 0.99


def test_the_camera_fit_recovers_perturbed_cameras_to_a_fraction_of_a_pixel():
    """Training cameras off by 0.5 degrees, 1% of their distance and 2 px, fitted to the true
    density (the density solve replaced by the truth, to test the camera fit alone): the box
    corners' projections come back to within a third of a pixel; the held-out camera stays."""
    scene = scene64()
    train, holdout = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 48)
    pivot = 0.5 * (grid.lo() + grid.hi())
    truth = camera_subset(scene.cameras, train)
    perturbed = corrected_cameras(truth, perturbation(truth, pivot), pivot)
    start = corner_error(perturbed, truth, grid)
    assert start > 1.0
    K4, E = scene.cameras.intrinsics.clone(), scene.cameras.extrinsics.clone()
    calibration = with_cameras(scene.cameras, train, perturbed)
    volume = resample_to(scene.truth, grid.shape)
    frame = CalibrationFrame(scene.images, silhouettes(scene.images), fixed_density(volume))
    found = refine(calibration, train, [frame], grid, RefineOptions(refine="pose+intrinsics", rounds=1))
    assert corner_error(camera_subset(found.cameras, train), truth, grid) < start / 5
    assert corner_error(camera_subset(found.cameras, train), truth, grid) < 0.35
    assert torch.equal(found.cameras.extrinsics[holdout], E[holdout])
    assert torch.equal(found.cameras.intrinsics[holdout], K4[holdout])


def test_cameras_fitted_to_several_frames_at_once_recover_as_well_as_to_one():
    """The cameras stand still while the flame moves: perturbed training cameras fitted to two
    frames at once (each frame compared with its own true density, the pixel budget shared)
    come back as close as when fitted to one frame with the whole budget."""
    scene = scene64()
    later = load_scene({**scene.meta["config"], "frame": 20})
    train, _ = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 48)
    pivot = 0.5 * (grid.lo() + grid.hi())
    truth = camera_subset(scene.cameras, train)
    calibration = with_cameras(scene.cameras, train, corrected_cameras(truth, perturbation(truth, pivot), pivot))
    start = corner_error(camera_subset(calibration, train), truth, grid)
    frames = [CalibrationFrame(s.images, silhouettes(s.images), fixed_density(resample_to(s.truth, grid.shape)))
              for s in (scene, later)]
    assert not torch.equal(later.images, scene.images)
    options = RefineOptions(refine="pose", rounds=1)
    one = refine(calibration, train, frames[:1], grid, options)
    both = refine(calibration, train, frames, grid, options)
    assert sum(r["rays"] for r in both.history) <= options.max_rays * len(train)
    error_one = corner_error(camera_subset(one.cameras, train), truth, grid)
    error_both = corner_error(camera_subset(both.cameras, train), truth, grid)
    assert error_both < start / 3
    assert error_both < 1.25 * error_one


def test_calibration_frames_fit_the_cameras_once_per_capture_and_read_them_back(tmp_path, monkeypatch):
    """calibration.frames: the training cameras are fitted to those frames (not the one
    reconstructed), kept in one cameras.json in the cache folder's calibration/, and another
    frame of the capture reads it back; held-out cameras keep their calibration, and the record
    says which frames were fitted and where the cameras came from."""
    import flamerecon as fr
    from flamerecon.fit import capture_calibration
    from flamerecon.fit.reconstruct import calibrated_scene

    monkeypatch.setenv("FLAMERECON_CACHE_DIR", str(tmp_path))
    fits = []
    real_refine = capture_calibration.refine
    monkeypatch.setattr(capture_calibration, "refine", lambda *a, **k: fits.append(1) or real_refine(*a, **k))
    options = fr.ReconstructionOptions(
        grid=fr.GridOptions(resolution=16), solver=fr.SolverOptions().with_values(max_iters=20),
        calibration=RefineOptions(refine="pose", rounds=1, iterations=2, frames=(3, 6), min_gain=0.0), device="cpu")
    first = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32, frame=0)
    other = fr.load_scene({**first.meta["config"], "frame": 9})
    refined, record = calibrated_scene(first, options, torch.device("cpu"))
    scored = options.replace(calibration=replace(options.calibration, score_before=True))
    again, again_record = calibrated_scene(other, scored, torch.device("cpu"))
    (kept,) = (tmp_path / "calibration").rglob("*.json")
    assert len(fits) == 1 and kept.parent.name == "synthetic"  # score_before does not change the cameras
    assert (record["source"], record["file"], again_record["source"]) == ("fitted", str(kept), "read")
    assert again_record["file"] == str(kept)
    # the scores with the capture's own cameras cost a solve: only when asked
    assert record["frames"] == [3, 6] and "train_psnr_before" not in record and "heldout_psnr_before" not in record
    assert math.isfinite(again_record["train_psnr_before"]) and math.isfinite(again_record["heldout_psnr_before"])
    train, holdout = first.split(None)
    assert torch.equal(refined.cameras.extrinsics, again.cameras.extrinsics)
    assert not torch.equal(refined.cameras.extrinsics[train], first.cameras.extrinsics[train])
    assert torch.equal(refined.cameras.extrinsics[holdout], first.cameras.extrinsics[holdout])


def test_the_rig_protocol_refines_every_camera_on_frames_that_are_not_scored(tmp_path, monkeypatch):
    """calibration.rig: the held-out camera is refined with the others on calibration.frames
    (one rig), so it moves where the strict protocol keeps it; a scored frame among the
    calibration frames, or a rig without frames, is refused by name."""
    import flamerecon as fr
    from flamerecon.errors import ConfigError
    from flamerecon.fit.reconstruct import calibrated_scene

    monkeypatch.setenv("FLAMERECON_CACHE_DIR", str(tmp_path))
    options = fr.ReconstructionOptions(
        grid=fr.GridOptions(resolution=16), solver=fr.SolverOptions().with_values(max_iters=20),
        calibration=RefineOptions(refine="pose", rounds=1, iterations=2, frames=(3, 6), rig=True, min_gain=0.0),
        device="cpu")
    scene = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32, frame=0)
    refined, record = calibrated_scene(scene, options, torch.device("cpu"))
    _, holdout = scene.split(None)
    assert record["rig"] and sorted(record["cameras"]) == sorted(scene.views)
    assert not torch.equal(refined.cameras.extrinsics[holdout], scene.cameras.extrinsics[holdout])
    other_fold = options.replace(holdout=(scene.views[0],))
    _, again = calibrated_scene(scene, other_fold, torch.device("cpu"))  # one rig calibration for every fold
    assert (again["source"], again["file"]) == ("read", record["file"])
    given = options.replace(calibration=RefineOptions(refine="pose", frames=(3, 6), rig=True, file=record["file"]))
    from_file, _ = calibrated_scene(scene, given, torch.device("cpu"))  # calibration.file of a rig: every camera
    assert torch.allclose(from_file.cameras.extrinsics[holdout], refined.cameras.extrinsics[holdout], atol=1e-6)
    scored = fr.load_scene({**scene.meta["config"], "frame": 6})
    with pytest.raises(ConfigError, match=r"calibration\.rig: frame 6 is reconstructed"):
        calibrated_scene(scored, options, torch.device("cpu"))
    with pytest.raises(ValueError, match=r"calibration\.rig: needs calibration\.frames"):
        RefineOptions(refine="pose", rig=True)


def test_calibration_frames_refuse_a_scene_that_does_not_know_its_capture():
    import dataclasses

    import flamerecon as fr
    from flamerecon.fit.reconstruct import calibrated_scene
    from flamerecon.scenes import SceneError

    scene = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32)
    orphan = dataclasses.replace(scene, meta={k: v for k, v in scene.meta.items() if k != "config"})
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16),
                                       calibration=RefineOptions(refine="pose", frames=(3,)), device="cpu")
    with pytest.raises(SceneError, match="load_scene"):
        calibrated_scene(orphan, options, torch.device("cpu"))


def test_the_cameras_are_fitted_to_penalised_densities_when_the_run_refits(monkeypatch):
    """debias.method=refit: the densities the cameras are fitted to are debiased by the gain
    (an unpenalised refit would fit part of the cameras' errors into them); the final solve
    still refits."""
    import flamerecon as fr
    from flamerecon.fit import reconstruct as reconstruction
    from flamerecon.fit.debias import DebiasOptions

    used = []
    real = reconstruction.debias
    monkeypatch.setattr(reconstruction, "debias", lambda o, *a: used.append(o.method) or real(o, *a))
    options = fr.ReconstructionOptions(
        grid=fr.GridOptions(resolution=16), solver=fr.SolverOptions().with_values(max_iters=10),
        calibration=RefineOptions(refine="pose", rounds=2, iterations=1, min_gain=0.0), debias=DebiasOptions("refit", 3),
        device="cpu")
    scene = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32)
    fr.reconstruct(scene, options)
    assert used[-1] == "refit" and set(used[:-1]) == {"gain"} and len(used) >= 3


def test_each_density_solve_after_a_frames_first_starts_from_its_previous_density():
    """fit_against=all: round 0 uses each frame's first density; every later solve of a frame
    gets that frame's latest density as its start, never another frame's."""
    scene = scene64()
    later = load_scene({**scene.meta["config"], "frame": 20})
    train, _ = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 24)
    starts = []

    def recording(frame: int):
        def solve(views, cams, start):
            starts.append((frame, None if start is None else float(start.sum())))
            return torch.full((scene.images.shape[1], *grid.shape), float(len(starts)))  # the call's number
        return solve

    frames = [CalibrationFrame(s.images, silhouettes(s.images), recording(k)) for k, s in enumerate((scene, later))]
    refine(scene.cameras, train, frames, grid, RefineOptions(refine="pose", rounds=3, iterations=1, max_rays=500))
    cells = scene.images.shape[1] * grid.shape[0] * grid.shape[1] * grid.shape[2]
    # first solves (calls 1, 2), round 1's (3, 4) from them, round 2's (5, 6) from those
    assert starts == [(0, None), (1, None), (0, 1.0 * cells), (1, 2.0 * cells), (0, 3.0 * cells), (1, 4.0 * cells)]


def test_calibration_iterations_limit_the_first_and_the_warm_started_solves(monkeypatch):
    """calibration.solve_iterations=k: a frame's first density solve runs the solver's
    max_iters from zero (or calibration.first_iterations), every later one k iterations from the
    frame's previous density; the run's own solve keeps the solver's max_iters."""
    import flamerecon as fr
    from flamerecon.fit import reconstruct as reconstruction

    calls = []
    real = reconstruction.fit
    monkeypatch.setattr(reconstruction, "fit", lambda setup, options, x0=None, *a, **k: calls.append(
        (options.solver.params["max_iters"], x0 is None)) or real(setup, options, x0, *a, **k))
    options = fr.ReconstructionOptions(
        grid=fr.GridOptions(resolution=16), solver=fr.SolverOptions().with_values(max_iters=12),
        calibration=RefineOptions(refine="pose", rounds=3, iterations=1, solve_iterations=4, min_gain=0.0), device="cpu")
    scene = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32)
    fr.reconstruct(scene, options)
    assert calls == [(12, True), (4, False), (4, False), (12, True)]  # the last: the run's own solve
    calls.clear()
    fr.reconstruct(scene, options.replace(calibration=replace(options.calibration, first_iterations=7)))
    assert calls == [(7, True), (4, False), (4, False), (12, True)]
    for name in ("first_iterations", "solve_iterations"):
        with pytest.raises(ArgumentError, match=f"calibration.{name}"):
            RefineOptions(refine="pose", **{name: 0})


def test_select_auto_chooses_the_camera_fits_weights_once_per_frame(monkeypatch):
    """select.auto with a camera fit: the frame's first density solve chooses the weights, its
    warm-started solves reuse them (a selection costs several solves), and the run's own solve
    chooses again with the refined cameras."""
    import flamerecon as fr
    from flamerecon.fit import reconstruct as reconstruction

    weights, selections = [], []
    real_fit, real_select = reconstruction.fit, reconstruction.select_weights
    monkeypatch.setattr(reconstruction, "fit", lambda setup, options, *a, **k: weights.append(
        (options.select.auto, options.solver.l1_rel)) or real_fit(setup, options, *a, **k))
    monkeypatch.setattr(reconstruction, "select_weights", lambda *a, **k: selections.append(1) or real_select(*a, **k))
    candidates = {"fista": ({"l1_rel": 0.3}, {"l1_rel": 0.01})}
    options = fr.ReconstructionOptions(
        grid=fr.GridOptions(resolution=16), solver=fr.SolverOptions("fista", l1_rel=0.5, params={"max_iters": 10}),
        select=fr.SelectOptions(auto=True, candidates=candidates, iterations=5),
        calibration=RefineOptions(refine="pose", rounds=3, iterations=1, min_gain=0.0), device="cpu")
    scene = fr.load_scene("synthetic", n_cameras=5, width=48, height=36, phantom_resolution=32)
    result = fr.reconstruct(scene, options)
    assert len(selections) == 2
    first_choice = weights[1][1]
    assert first_choice in (0.3, 0.01)
    assert weights[0] == (True, 0.5) and weights[1:3] == [(False, first_choice)] * 2 and weights[3] == (True, 0.5)
    assert result.fit.selection is not None


@pytest.fixture(scope="module")
def refined_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("refined")
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            "scene.width=48", "scene.height=36", "scene.n_cameras=5", "scene.phantom_resolution=32",
            "grid.resolution=16", "solver.max_iters=20", "log.eval_every=0", "device=cpu",
            "calibration.refine=pose+intrinsics", "calibration.rounds=1", "calibration.iterations=2",
            "calibration.min_gain=0"])  # exact cameras: the fit would find nothing to correct
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")  # what train.py's Hydra writes
    return run_dir, reconstruct(cfg, run_dir)


def test_a_refined_run_records_both_calibrations_and_the_training_psnr_before_and_after(refined_run):
    run_dir, metrics = refined_run
    cams = json.loads((run_dir / "cameras.json").read_text())["cameras"]
    held = [c for c in cams if c["split"] == "holdout"]
    assert held and all(c["K"] == c["K_calibrated"] for c in held)
    assert all(c["world_to_camera"] == c["world_to_camera_calibrated"] for c in held)
    assert any(c["world_to_camera"] != c["world_to_camera_calibrated"] for c in cams if c["split"] == "train")
    record = json.loads((run_dir / "metrics.json").read_text())["calibration"]
    assert record["refine"] == "pose+intrinsics"
    assert set(record["cameras"]) == {c["name"] for c in cams if c["split"] == "train"}
    for key in ("train_psnr_before", "train_psnr_after", "heldout_psnr_before"):
        assert math.isfinite(record[key])
    assert record["train_psnr_after"] == pytest.approx(
        sum(v["psnr"] for v in metrics["train"].values()) / len(metrics["train"]))
    table = summary_table(metrics)
    assert "calibration (pose+intrinsics)" in table
    # heldout_psnr_before is the camera fit's first solve, not a calibration.refine=none run: said so
    assert "before refinement" not in table
    assert f"held-out {record['heldout_psnr_before']:.2f} dB with the capture's cameras in the camera fit's" in table


def test_the_summary_says_how_to_get_the_scores_with_the_captures_own_cameras_when_not_asked(refined_run):
    _, metrics = refined_run
    record = {k: v for k, v in metrics["calibration"].items() if not k.endswith("_before")}
    table = summary_table({**metrics, "calibration": record})
    assert f"training {record['train_psnr_after']:.2f} dB (calibration.score_before=true: also with" in table


def test_evaluate_scores_a_refined_run_with_its_refined_cameras(refined_run):
    run_dir, metrics = refined_run
    again = evaluate(run_dir, device="cpu", native=False)
    for name, values in metrics["train"].items():
        assert again["train"][name]["psnr"] == pytest.approx(values["psnr"], abs=1e-3)
    assert again["calibration"]["train_psnr_before"] == metrics["calibration"]["train_psnr_before"]


def test_the_similarity_gauge_undoes_a_common_motion_of_the_rig_and_keeps_every_image():
    """calibration.gauge=similarity: cameras that drifted as one rig (rotated 2 degrees about a
    point off the pivot, shifted, scaled) plus a little each are put back where the calibration
    had them, up to that little; and every point of the moved world projects through the
    aligned cameras exactly where it projected through the drifted ones (the frame changes,
    no image does)."""
    from tests.helpers.views import ring_cameras

    K = torch.tensor([[40.0, 0, 20.5], [0, 40.0, 16.5], [0, 0, 1]]).expand(5, 3, 3)
    calibrated = make_cameras(K, ring_cameras(5).float(), torch.full((5,), 32.0), torch.full((5,), 40.0))
    pivot = torch.tensor([0.05, 0.1, -0.02])
    common = torch.tensor([[0.0, 0.035, 0.0]] * 5)  # the rig's common rotation (2 degrees) ...
    wobble = 0.002 * torch.randn(5, 9, generator=torch.Generator().manual_seed(1))  # ... and each its own
    theta = torch.zeros(5, 9)
    theta[:, :3] = common[:, :3] + wobble[:, :3]
    theta[:, 3:6] = torch.tensor([0.03, -0.02, 0.01]) + wobble[:, 3:6]
    drifted = corrected_cameras(calibrated, theta, pivot)
    scale = 1.01
    drifted.extrinsics[:, :3, 3] *= scale  # a common scale: same images of a world scaled by 1/scale
    aligned = align_similarity(drifted, calibrated, pivot)
    before = (camera_centers(drifted) - camera_centers(calibrated)).norm(dim=-1)
    after = (camera_centers(aligned) - camera_centers(calibrated)).norm(dim=-1)
    assert before.min() > 0.05 and after.max() < 0.02 and after.max() < before.min() / 5
    s, R, t = similarity(camera_frame_points_of(drifted, pivot), camera_frame_points_of(calibrated, pivot))
    points = torch.rand(50, 3, generator=torch.Generator().manual_seed(2)).double() - 0.5
    moved = (s * points @ R.T + t).float()
    uv_drifted, _ = project_points(drifted, points.float())
    uv_aligned, _ = project_points(aligned, moved)
    assert torch.allclose(uv_aligned, uv_drifted, atol=1e-3)
    same = align_similarity(calibrated, calibrated, pivot)
    assert torch.allclose(same.extrinsics, calibrated.extrinsics, atol=1e-5)


def camera_frame_points_of(cams, pivot):
    from flamerecon.fit.refine_cameras import camera_frame_points

    return camera_frame_points(cams, pivot)


def test_a_camera_fit_that_finds_nothing_to_correct_keeps_the_cameras_and_stops():
    """Exact cameras fitted to a penalised density: the first round lowers the residual by a
    fraction of a percent (chasing the density's bias and the noise), under calibration.min_gain:
    the fit stops there and keeps the capture's own cameras, saying why. Cameras off by half a
    degree and 2 px gain far more and are corrected."""
    import flamerecon as fr
    from flamerecon.fit.refine_cameras import found_nothing

    scene = fr.load_scene("synthetic", n_cameras=6, width=64, height=48, phantom_resolution=48)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=32),
                                       solver=fr.SolverOptions().with_values(max_iters=100), device="cpu",
                                       calibration=RefineOptions(refine="pose", rounds=3, iterations=2))
    from flamerecon.fit.reconstruct import calibrated_scene

    kept, record = calibrated_scene(scene, options, torch.device("cpu"))
    assert found_nothing(record["rounds"]) and len(record["rounds"]) == 1
    assert "under calibration.min_gain 3%" in record["rounds"][0]["stopped"]
    assert torch.equal(kept.cameras.extrinsics, scene.cameras.extrinsics)
    assert "nothing to correct" in summary_table({"heldout": {}, "train": {"a": {"psnr": 30.0}}, "calibration": {
        **record, "train_psnr_after": 30.0}, "solver": {"name": "x", "l1": 1.0, "iterations": 1, "seconds": 1.0}})
    train, _ = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 32)
    pivot = 0.5 * (grid.lo() + grid.hi())
    truth = camera_subset(scene.cameras, train)
    off = with_cameras(scene.cameras, train, corrected_cameras(truth, perturbation(truth, pivot), pivot))
    fixed, record = calibrated_scene(replace(scene, cameras=off), options, torch.device("cpu"))
    assert not found_nothing(record["rounds"]) and record["rounds"][0]["rms_after"] < 0.97 * record["rounds"][0]["rms_before"]
    assert corner_error(camera_subset(fixed.cameras, train), truth, grid) < corner_error(camera_subset(off, train), truth, grid)
