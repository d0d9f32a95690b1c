"""scene=scalarflow brings the settings cross-validated on that capture (solver, weights, grid,
working resolution) while the command line still wins and the synthetic defaults stay."""

from __future__ import annotations

from hydra import compose, initialize_config_dir

from flamerecon.run.pipeline import solver_options
from flamerecon.solvers import make_solver
from tests.helpers import REPO


def composed(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def test_scalarflow_picks_its_cross_validated_solver_grid_and_resolution():
    cfg = composed("scene=scalarflow")
    assert cfg.scene.name == "scalarflow" and cfg.scene.downscale == 4
    assert cfg.solver.name == "tv"
    assert (cfg.solver.tv, cfg.solver.l1_rel, cfg.solver.l1) == (0.02, 0.05, None)
    # a small dual step: the same held-out score in a third of the iterations (docs/results.md)
    assert (cfg.solver.dual_step, cfg.solver.max_iters) == (0.25, 100)
    assert (cfg.calibration.first_iterations, cfg.calibration.solve_iterations) == (30, 10)
    assert cfg.grid.resolution == 128
    make_solver(cfg.solver.name, **solver_options(cfg))  # a complete, valid solver config


def test_the_command_line_wins_over_the_scene_defaults():
    cfg = composed("scene=scalarflow", "solver=fista", "grid.resolution=96", "solver.max_iters=7")
    assert cfg.solver.name == "fista" and "tv" not in cfg.solver
    assert cfg.grid.resolution == 96 and cfg.solver.max_iters == 7
    make_solver(cfg.solver.name, **solver_options(cfg))
    cfg = composed("scene=scalarflow", "solver.tv=0.1", "scene.downscale=2")
    assert (cfg.solver.name, cfg.solver.tv, cfg.scene.downscale) == ("tv", 0.1, 2)


def test_the_synthetic_default_is_the_best_measured_method_and_the_papers_is_one_switch_away():
    cfg = composed()
    assert (cfg.scene.name, cfg.solver.name, cfg.grid.resolution) == ("synthetic", "pqn_smooth", 64)
    assert (cfg.solver.l1_rel, cfg.solver.smooth) == (0.001, 0.01) and cfg.photometry.fit_gain is False
    paper = composed("solver=fista")
    assert (paper.solver.name, paper.solver.l1_rel, "smooth" in paper.solver) == ("fista", 0.001, False)


def test_scalarflow_debiases_its_fixed_weights_and_fits_its_cameras_once_to_two_frames():
    cfg = composed("scene=scalarflow")
    assert (cfg.debias.method, cfg.debias.iterations) == ("refit", 10) and cfg.select.auto is False
    assert cfg.calibration.refine == "pose" and cfg.calibration.resolution == 96
    assert list(cfg.calibration.frames) == [30, 70] and cfg.calibration.iterations == 2
    # select.auto=true (2 folds of 15 iterations) walks a path, strongest first, that holds the
    # fixed weights (it chose them on frames 62/67/72)
    assert (cfg.select.folds, cfg.select.iterations) == (2, 15)
    path = [(c.l1_rel, c.tv) for c in cfg.select.candidates.tv]
    assert (cfg.solver.l1_rel, cfg.solver.tv) in path and path == sorted(path, reverse=True)


def test_other_captures_choose_their_own_weights_and_the_paper_method_is_one_switch_away():
    for scene in ("opencv", "nerf"):
        cfg = composed(f"scene={scene}", "scene.root=/data")
        assert (cfg.solver.name, cfg.select.auto, cfg.debias.method, cfg.projector.rays) == (
            "tv", True, "gain", "hull")
        assert cfg.scene.name == scene and cfg.scene.root == "/data"
        assert len(cfg.select.candidates.tv) >= 3  # a path of weights, strongest first
        first, last = cfg.select.candidates.tv[0], cfg.select.candidates.tv[-1]
        assert first.tv > last.tv and first.l1_rel > last.l1_rel
        paper = composed(f"scene={scene}", "scene.root=/data", "solver=fista", "select.auto=false",
                         "debias.method=none")
        assert (paper.solver.name, paper.select.auto, paper.debias.method) == ("fista", False, "none")
