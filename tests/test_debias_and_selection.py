"""Background rays, debiasing and run-time weight selection: the hull footprint covers every
pixel the density can reach, the gain debias is the least-squares gain, a fold's score is the
PSNR of the real render of the left-out camera, and the chosen weights enter the solve."""

from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize_config_dir

from flamerecon.errors import ConfigError
from flamerecon.evaluate.scores import render_scene_views, score_views
from flamerecon.fit.debias import DebiasOptions, debias, training_gain
from flamerecon.fit.weight_selection import (
    RowSubset,
    SelectionOptions,
    fold_views,
    row_subset,
    select_weights,
)
from flamerecon.geometry.cameras import camera_subset
from flamerecon.geometry.hull import hull_footprint
from flamerecon.operators.projector import render_image
from flamerecon.operators.sparse import CsrOperator
from flamerecon.run.pipeline import choose_weights, prepare, solve
from flamerecon.scenes import load_scene
from flamerecon.solvers import Problem, make_solver
from tests.helpers import REPO

TINY = ["scene.width=48", "scene.height=36", "scene.n_cameras=5", "scene.phantom_resolution=32",
        "grid.resolution=16", "solver.max_iters=40", "device=cpu", "projector.rays=hull"]


def config(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=[*TINY, *overrides])


@pytest.fixture(scope="module")
def tiny():
    cfg = config()
    scene = load_scene(cfg.scene)
    return cfg, scene, prepare(cfg, scene, torch.device("cpu"))


def test_the_hull_footprint_covers_every_pixel_a_hull_density_renders(tiny):
    _cfg, scene, setup = tiny
    cams = camera_subset(scene.cameras, setup.train)
    footprint = hull_footprint(setup.grid, cams, setup.hull)
    ones = setup.volume(torch.ones(setup.voxel_index.numel(), 1))
    lit = render_image(ones, setup.grid, cams, setup.step)[:, 0] > 0  # (T, H, W)
    assert bool(lit.any())
    assert not bool((lit & ~footprint).any()), "a pixel the hull renders is outside the footprint"
    assert footprint.sum() < footprint.numel()  # it is a footprint, not the whole image


def test_hull_rays_add_the_background_rows_with_their_zeros(tiny):
    cfg, scene, setup = tiny
    sil = prepare(config("projector.rays=silhouette"), scene, torch.device("cpu"))
    assert setup.operator.shape[1] == sil.operator.shape[1]  # same hull voxels
    assert setup.operator.shape[0] > sil.operator.shape[0]  # more rows: the background ones
    extra = setup.pixels.shape[0] - sil.pixels.shape[0]  # background: dark, below the threshold
    background = (setup.pixels.sum() - sil.pixels.sum()) / (extra * setup.pixels.shape[1])
    assert float(background) < cfg.silhouette.threshold < float(sil.pixels.mean())


def test_gain_debias_is_the_least_squares_gain_of_the_training_rows():
    g = torch.Generator().manual_seed(0)
    A = torch.rand(40, 12, generator=g)
    x = torch.rand(12, 2, generator=g)
    op = type("Dense", (), {"shape": (40, 12), "forward": lambda s, v: A @ v, "adjoint": lambda s, v: A.T @ v})()
    b = A @ x * torch.tensor([1.25, 0.8]) + 0.01 * torch.randn(40, 2, generator=g)
    gain = training_gain(op, b, x)
    ax = (A @ x).double()
    for c in range(2):  # the 1-parameter least squares of b against A x, by numpy's solver
        ref = torch.linalg.lstsq(ax[:, c:c + 1], b[:, c:c + 1].double()).solution.item()
        assert float(gain[c]) == pytest.approx(ref, rel=1e-5)
    xd, record = debias(DebiasOptions("gain"), op, b, x)
    assert torch.allclose(xd, x * gain)
    assert record["method"] == "gain" and len(record["gain"]) == 2


def test_refit_debias_lowers_the_data_term_and_stays_nonnegative(tiny):
    _cfg, _scene, setup = tiny
    problem = Problem(setup.operator, setup.pixels, 0.0)
    shrunk = make_solver("fista", max_iters=30).solve(
        Problem(setup.operator, setup.pixels, 0.05 * float(setup.operator.adjoint(setup.pixels).max()))).x
    xd, record = debias(DebiasOptions("refit", 5), setup.operator, setup.pixels, shrunk)
    assert record == {"method": "refit", "iterations": 5}
    assert bool((xd >= 0).all())
    assert problem.objective(xd) < problem.objective(shrunk)


def test_bad_debias_options_name_the_field():
    with pytest.raises(ValueError, match="debias.method"):
        DebiasOptions("median")
    with pytest.raises(ValueError, match="debias.iterations"):
        DebiasOptions("refit", 0)


def test_row_subset_passes_the_dot_test_and_keeps_the_rows(tiny):
    _, _, setup = tiny
    rows = torch.arange(0, setup.operator.shape[0], 3)
    sub = RowSubset(setup.operator, rows)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(setup.operator.shape[1], 1, generator=g)
    y = torch.rand(rows.numel(), 1, generator=g)
    lhs = float((sub.forward(x).double() * y.double()).sum())
    rhs = float((x.double() * sub.adjoint(y).double()).sum())
    assert lhs == pytest.approx(rhs, rel=1e-5)
    assert torch.equal(sub.forward(x), setup.operator.forward(x)[rows])


def test_an_assembled_operators_rows_are_sliced_out_with_the_same_products(tiny):
    """row_subset of a CsrOperator: a CsrOperator of the rows kept, whose A x equals the full
    operator's restricted product bit for bit, and A^T y its zero-filled one (to float rounding
    on the CPU's compiled adjoint: its partial sums run over fixed shares of the rows)."""
    _, _, setup = tiny
    A = setup.operator
    rows = torch.cat([torch.arange(0, A.shape[0] // 3), torch.arange(A.shape[0] // 2, A.shape[0], 2)])
    sub = row_subset(A, rows)
    assert isinstance(sub, CsrOperator) and sub.shape == (rows.numel(), A.shape[1])
    g = torch.Generator().manual_seed(2)
    x = torch.rand(A.shape[1], 3, generator=g)
    y = torch.rand(rows.numel(), 3, generator=g)
    view = RowSubset(A, rows)
    assert torch.equal(sub.forward(x), view.forward(x))
    assert torch.allclose(sub.adjoint(y), view.adjoint(y), rtol=1e-6, atol=1e-7)
    assert sub.nnz < A.nnz


def test_fold_views_spread_over_the_training_cameras():
    assert fold_views(4, 4) == [0, 1, 2, 3]
    assert fold_views(7, 4) == [0, 2, 4, 6]
    assert fold_views(7, 2) == [0, 6]


def test_a_fold_score_is_the_psnr_of_the_real_render_of_the_left_out_camera(tiny):
    _cfg, scene, setup = tiny
    T = len(setup.train)
    energy = (scene.images[setup.train].double() ** 2).sum((-2, -1))
    H, W = scene.image_size
    candidate = {"l1_rel": 1e-3}
    found = select_weights("fista", {"l1_rel": 1e-3, "max_iters": 40}, SelectionOptions((candidate,), folds=2),
                           DebiasOptions("gain"), setup.operator, setup.pixels, setup.row_view, energy,
                           H * W, [scene.views[v] for v in setup.train])
    k = fold_views(T, 2)[1]  # redo that fold by hand: fit the other rows, render camera k fully
    keep = (setup.row_view != k).nonzero().squeeze(1)
    sub = RowSubset(setup.operator, keep)
    b = setup.pixels[keep]
    l1 = 1e-3 * float(sub.adjoint(b).max())
    x = make_solver("fista", max_iters=40).solve(Problem(sub, b, l1)).x
    x, _ = debias(DebiasOptions("gain"), sub, b, x)
    view = setup.train[k]
    image = render_scene_views(setup.volume(x), setup.grid, scene, [view], setup.step)
    expected = score_views(image, scene, [view])[scene.views[view]]["psnr"]
    assert found.table[0]["folds"][scene.views[view]] == pytest.approx(expected, abs=0.02)


def test_the_run_uses_the_weights_that_leave_one_view_out_prefers(tiny):
    _cfg, _scene, setup = tiny
    candidates = "select.candidates.fista=[{l1_rel: 0.3},{l1_rel: 0.001}]"  # too strong, mild
    chosen_cfg, record = choose_weights(config("solver=fista", "select.auto=true", candidates,
                                               "select.folds=2"), setup)
    psnrs = [row["psnr"] for row in record["candidates"]]
    assert all(math.isfinite(p) for p in psnrs)
    best = record["candidates"][psnrs.index(max(psnrs))]["overrides"]
    assert record["chosen"] == best
    assert float(chosen_cfg.solver.l1_rel) == best["l1_rel"]
    assert best == {"l1_rel": 0.001}  # the strong weight zeroes most of the flame
    _result, l1, _ = solve(config("solver=fista", "select.auto=true", candidates, "select.folds=2"), setup)
    assert l1 == pytest.approx(0.001 * float(setup.operator.adjoint(setup.pixels).max()), rel=1e-5)


def test_selection_refuses_a_misspelt_candidate_key(tiny):
    _cfg, _scene, setup = tiny
    with pytest.raises(ConfigError, match="select"):
        choose_weights(config("solver=fista", "select.auto=true", "select.candidates.fista=[{l1_rell: 0.1}]"),
                       setup)


def test_selection_for_a_solver_without_candidates_is_refused(tiny):
    """select.auto would do nothing there (issue 20): refused by name, not ignored."""
    _cfg, _scene, setup = tiny
    with pytest.raises(ConfigError, match=r"^select.auto: got True, which does nothing without candidates for the run.s solver"):
        choose_weights(config("solver=cgls", "select.auto=true"), setup)
