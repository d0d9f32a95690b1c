"""What the cameras determine (flamerecon.evaluate.uncertainty, flamerecon.fit.ensemble,
flamerecon.evaluate.camera_planning): the shifts and the rank correlation against hand-worked
answers, the calibration figures against errors drawn with a known spread, the ensemble's
members against what leaving a camera out must do, the confidence images against renders of the
deviations, the files written and read back, the API's door, and the camera plan's ranking."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.errors import ArgumentError, ArgumentTypeError, ConfigError
from flamerecon.evaluate.camera_planning import (
    orbit_candidates,
    total_variance,
    variance_reduction,
)
from flamerecon.evaluate.image_noise import NoiseModel
from flamerecon.evaluate.uncertainty import (
    Confidence,
    capture_sigma,
    check_view,
    coverage,
    load_confidence,
    neighbour_rms,
    predicted_psnr,
    ranks,
    save_confidence,
    shifted,
    spearman,
)
from flamerecon.fit.ensemble import solve_ensemble, weight_variants
from flamerecon.geometry.axes import up_vector, world_angles
from flamerecon.geometry.cameras import camera_centers, camera_subset
from flamerecon.run.pipeline import reconstruct
from tests.helpers import HELDOUT, TRAIN, CliRun, tiny_config

SCENE = {"width": 48, "height": 36, "n_cameras": 5, "phantom_resolution": 32}


@pytest.fixture(scope="module")
def rec():
    """The tiny synthetic flame, four cameras fitted (cam04 held out)."""
    scene = fr.load_scene("synthetic", **SCENE)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                       solver=fr.SolverOptions("fista", None, 1e-3, {"max_iters": 30}))
    return fr.reconstruct(scene, options)


@pytest.fixture(scope="module")
def conf(rec):
    return fr.confidence(rec, fr.UncertaintyOptions(shift_voxels=0.5, scale=2.0))


def test_a_shift_moves_a_voxel_by_whole_and_part_cells():
    v = torch.zeros(1, 3, 4, 5)
    v[0, 1, 2, 2] = 1.0
    whole = shifted(v, 3, 1)  # one cell along x
    assert whole[0, 1, 2, 3] == 1 and whole.sum() == 1
    half = shifted(v, 3, -0.5)  # half a cell back along x: shared with the neighbour
    assert half[0, 1, 2, 2] == 0.5 and half[0, 1, 2, 1] == 0.5 and half.sum() == 1
    assert shifted(v, 1, 3).sum() == 0  # moved out of the grid: nothing left
    assert torch.equal(shifted(v, 2, 0.0), v)


def test_ranks_and_spearman_match_hand_worked_answers():
    assert ranks(torch.tensor([10.0, 30.0, 20.0, 20.0])).tolist() == [1.0, 4.0, 2.5, 2.5]
    a = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    assert spearman(a, a ** 3) == pytest.approx(1.0)
    assert spearman(a, -a) == pytest.approx(-1.0)
    # ranks (1, 2, 3, 4) against (2, 1, 4, 3): d^2 sums to 4, rho = 1 - 6*4/(4*15) = 0.6
    assert spearman(torch.tensor([1.0, 2, 3, 4]), torch.tensor([2.0, 1, 4, 3])) == pytest.approx(0.6)
    assert math.isnan(spearman(a, torch.ones(5)))


def test_spearman_agrees_with_scipy_on_ties():
    stats = pytest.importorskip("scipy.stats", reason="scipy (an independent reference) is not installed")
    g = torch.Generator().manual_seed(0)
    a, b = torch.randint(0, 5, (200,), generator=g).float(), torch.randint(0, 7, (200,), generator=g).float()
    assert spearman(a, b) == pytest.approx(stats.spearmanr(a.numpy(), b.numpy())[0], abs=1e-12)


def test_errors_drawn_with_the_predicted_spread_are_covered_as_a_gaussian_is():
    g = torch.Generator().manual_seed(1)
    H, W = 120, 100
    sigma = 0.002 + 0.05 * torch.rand(1, H, W, generator=g)  # varies independently of the image
    rendered = 0.5 * torch.rand(1, H, W, generator=g)
    captured = rendered + sigma * torch.randn(1, H, W, generator=g)
    found = check_view(rendered, captured, sigma, torch.ones(H, W, dtype=torch.bool))
    assert found["coverage_1sigma"] == pytest.approx(0.683, abs=0.02)
    assert found["coverage_2sigma"] == pytest.approx(0.954, abs=0.01)
    assert found["psnr_predicted"] == pytest.approx(found["psnr"], abs=0.1)
    assert found["spearman"] > 0.3 > abs(found["spearman_trivial"])
    assert predicted_psnr(torch.full((1, 4, 4), 0.1)) == pytest.approx(20.0)
    assert coverage(torch.tensor([0.0, 1.0, 3.0]), torch.ones(3), 2.0) == pytest.approx(2 / 3)


def test_the_oracle_reads_the_error_around_a_pixel_not_at_it():
    spike = torch.zeros(1, 20, 20)
    spike[0, 10, 10] = 1.0
    around = neighbour_rms(spike, 2.0)
    assert float(around[0, 10, 10]) == 0.0 and float(around[0, 10, 11]) > 0.1
    torch.testing.assert_close(neighbour_rms(torch.full((1, 9, 9), 0.3), 2.0), torch.full((1, 9, 9), 0.3),
                               check_dtype=False)


def test_leaving_a_camera_out_loosens_the_fit_to_that_camera(rec):
    ensemble = solve_ensemble(rec.setup, rec.options, rec.fit.result.x, fr.UncertaintyOptions())
    train = rec.setup.train
    assert ensemble.labels == [f"cameras:{rec.scene.views[v]}" for v in train]
    assert ensemble.members.shape == (len(train), *rec.fit.result.x.shape)
    A, b = rec.setup.operator, rec.setup.pixels
    for k, member in enumerate(ensemble.members):
        rows = rec.setup.row_view == k
        left_out = float((A.forward(member)[rows] - b[rows]).pow(2).sum())
        fitted = float((A.forward(rec.fit.result.x)[rows] - b[rows]).pow(2).sum())
        assert left_out > fitted  # the member never saw camera k: it predicts it worse


def test_the_weights_members_perturb_each_weight_both_ways():
    tv = fr.SolverOptions("tv", None, 0.05, {"tv": 0.02})
    assert weight_variants(tv, 2.0) == [("weights:l1_rel*2", {"l1_rel": 0.1}), ("weights:l1_rel/2", {"l1_rel": 0.025}),
                                        ("weights:tv*2", {"tv": 0.04}), ("weights:tv/2", {"tv": 0.01})]
    assert weight_variants(fr.SolverOptions("fista", 0.3, None, {}), 3.0) == [
        ("weights:l1*3", {"l1": pytest.approx(0.9)}), ("weights:l1/3", {"l1": pytest.approx(0.1)})]


def test_the_confidence_image_is_the_scaled_spread_of_the_rendered_deviations(rec, conf):
    cams = camera_subset(rec.scene.cameras, rec.setup.holdout)
    devs = [rec.setup.volume(m - rec.fit.result.x) for m in conf.members]
    expected_cameras = torch.stack([fr.render(d, rec.grid, cams) for d in devs]).pow(2).mean(0)
    density = rec.density
    shifts = [shifted(density, axis, s * 0.5) - density for axis in (3, 2, 1) for s in (1, -1)]
    expected_shift = torch.stack([fr.render(d, rec.grid, cams) for d in shifts]).pow(2).mean(0)
    expected = 2.0 * (expected_cameras + expected_shift).sqrt()
    torch.testing.assert_close(conf.image(cams), expected, rtol=1e-4, atol=1e-6)
    volume = conf.volume()
    assert volume.shape == density.shape and bool((volume >= 0).all())
    expected_volume = 2.0 * (torch.stack(devs).pow(2).mean(0) + torch.stack(shifts).pow(2).mean(0)).sqrt()
    torch.testing.assert_close(volume, expected_volume)


def test_members_equal_to_the_density_and_no_shift_leave_nothing_uncertain(rec):
    x = rec.fit.result.x
    same = Confidence(rec.grid, rec.setup.voxel_index, rec.setup.hull, x, torch.stack([x, x]), ["cameras"] * 2,
                      0.0, 1.0)
    assert float(same.volume().abs().max()) == 0.0
    assert float(same.image(rec.scene.cameras).abs().max()) == 0.0


def test_the_footprint_is_where_rays_meet_the_hull(rec, conf):
    cams = camera_subset(rec.scene.cameras, rec.setup.holdout)
    inside = conf.footprint(cams)
    assert inside.shape == (1, *rec.scene.image_size) and 0 < float(inside.float().mean()) < 1
    render = fr.render(rec.density, rec.grid, cams)
    assert float(render[:, :, ~inside[0]].abs().max()) == 0.0  # nothing rendered off the hull
    sigma = conf.image(cams)
    assert float(sigma[:, :, ~inside[0]].abs().max()) < 0.5 * float(sigma.max())  # the shifts' fraction of a voxel


def test_the_confidence_file_reads_back_to_the_same_images(rec, conf, tmp_path):
    path = save_confidence(tmp_path / "uncertainty.npz", conf, ["a"])
    again = load_confidence(path)
    torch.testing.assert_close(again.image(rec.scene.cameras), conf.image(rec.scene.cameras))
    assert again.labels == conf.labels
    loaded = fr.export(tmp_path / "uncertainty.npz", tmp_path / "u", "raw")  # any export reads it
    assert loaded[0].name == "u.raw"
    with np.load(path) as f:
        torch.testing.assert_close(torch.from_numpy(f["density"]), conf.volume())


def test_the_api_renders_the_spread_of_any_camera(rec, conf):
    novel = fr.look_at_camera((0.0, 0.7, 3.0), (0.0, 0.6, 0.0), width=40, height=30)
    found = fr.uncertainty(conf, novel)
    assert found.shape == (1, rec.density.shape[0], 30, 40) and float(found.max()) > 0
    with pytest.raises(ArgumentTypeError, match=r"^uncertainty.result: "):
        fr.uncertainty(rec.density, novel)
    with pytest.raises(ArgumentTypeError, match=r"^uncertainty.cameras: "):
        fr.uncertainty(conf, None)
    with pytest.raises(ArgumentTypeError, match=r"^confidence.options: "):
        fr.confidence(rec, {"scale": 2.0})
    with pytest.raises(ArgumentError, match=r"^uncertainty.members: "):
        fr.UncertaintyOptions(members="views")
    with pytest.raises(ArgumentError, match=r"^Confidence.scale: "):
        Confidence(rec.grid, conf.voxel_index, conf.hull, conf.x, conf.members, conf.groups, 0.5, -1.0)


def test_a_bad_uncertainty_option_on_the_command_line_is_named():
    with pytest.raises(ConfigError, match=r"uncertainty.shift_voxels: got 3"):
        fr.preset("synthetic", "uncertainty.shift_voxels=3")


def test_a_camera_beside_a_fitted_one_adds_less_than_one_in_the_gap(rec, conf):
    fitted = camera_subset(rec.scene.cameras, rec.setup.train)
    centre = 0.5 * (rec.grid.lo().double() + rec.grid.hi().double())
    up = np.asarray(up_vector(rec.scene.up))
    cams, azimuths = orbit_candidates(fitted, centre, 12, up)
    found, _ = world_angles(camera_centers(cams).double().numpy() - centre.numpy(), up)
    apart = (found - azimuths.numpy() + 180) % 360 - 180
    assert float(np.abs(apart).max()) < 1e-3  # world azimuths about the scene's up (0: +z, 90: +x for +y up)
    gained = variance_reduction(conf, cams, 0.01, fitted)
    assert bool((gained >= -1e-9).all()) and float(gained.max()) <= total_variance(conf)
    # the candidate at a fitted camera's place (azimuth 0: the first fitted camera's) against the best
    assert float(gained[0]) < float(gained.max())
    alone = variance_reduction(conf, camera_subset(cams, [0]), 0.01)
    assert float(alone[0]) > float(gained[0])  # unconditioned, it claims what the fitted camera already saw


@pytest.mark.e2e
def test_a_run_with_the_confidence_writes_it_everywhere_it_is_read(tmp_path):
    run = tmp_path / "run"
    done = CliRun(run, "uncertainty.enabled=true", "export=raw", "threads=1").result()
    assert done.returncode == 0, done.stderr
    assert "predicted [dB]" in done.stdout and "uncertainty" in done.stdout
    metrics = json.loads((run / "metrics.json").read_text())
    held = metrics["heldout"][HELDOUT[0]]
    assert math.isfinite(held["psnr_predicted"]) and metrics["uncertainty"]["members"] == [f"cameras:{v}" for v in TRAIN]
    header = json.loads((run / "uncertainty.raw.json").read_text())
    assert header["channels"] == ["R_sigma", "G_sigma", "B_sigma"]
    figure = cv2.imread(str(run / "renders" / f"{HELDOUT[0]}.png"))
    assert figure.shape[1] > 4 * 48  # render | captured | error | predicted sigma, and the colour bar
    loaded = fr.confidence(fr.load_run(run))  # read back from uncertainty.npz, not solved again
    assert loaded.labels == metrics["uncertainty"]["members"]
    done_run = fr.load_run(run)
    cams = camera_subset(done_run.scene.cameras, [4])
    sigma = fr.uncertainty(loaded, cams)
    # the prediction against the capture: the render's spread and the noise the training images show
    noise = metrics["uncertainty"]["noise"]
    assert all(a >= 0 for a in noise["a"]) and max(noise["b"]) > 0  # the scene's noise grows with intensity
    model = NoiseModel(torch.tensor(noise["a"], dtype=torch.float64), torch.tensor(noise["b"], dtype=torch.float64))
    rendered = fr.render(done_run.density, done_run.grid, cams)[0]
    against = capture_sigma(done_run.scene, rendered, sigma[0], model)
    assert predicted_psnr(against) == pytest.approx(held["psnr_predicted"], abs=1e-3)
    assert predicted_psnr(sigma[0]) > held["psnr_predicted"] + 0.1  # the noise lowers it


def test_frames_solved_jointly_refuse_the_confidence_before_any_work(tmp_path):
    with pytest.raises(ConfigError, match=r"^uncertainty.enabled: .*scene.frames"):
        reconstruct(tiny_config("scene.frames=[0,1]", "uncertainty.enabled=true"), tmp_path / "run")
    assert not (tmp_path / "run" / "density.npz").exists()


def test_cameras_facing_each_other_or_side_by_side_are_named_alike():
    """Emission-only images are line integrals: a camera facing another (its mirror) sees nearly
    the same lines, as does one beside it; cameras a right angle apart are unlike."""
    from flamerecon.evaluate.camera_planning import alike

    def line(azimuth, elevation):
        a, e = math.radians(azimuth), math.radians(elevation)
        return [math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)]

    lines = np.array([line(0, 5), line(180, 5), line(10, 0), line(90, 5), line(190, -5)])
    found = alike(lines, lines[:1])
    assert found == [[(0, "beside")], [(0, "mirror")], [(0, "beside")], [], [(0, "mirror")]]
