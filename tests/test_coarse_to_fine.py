"""Coarse-to-fine grids (``grid.levels``): no levels is the plain solve bit for bit; each level
starts from the previous solution resampled onto it; the warm start does not end worse than a
cold start with the same fine budget; the L1 weight of each level; leave-one-out solves the
levels; bad level lists are refused by name; an interrupted coarse level resumes;
``python train.py grid.levels=[...]`` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from flamerecon.errors import ConfigError, Interrupted, ResumeError, SolveDiverged
from flamerecon.run.pipeline import prepare, reconstruct, solve
from flamerecon.solvers import Solver
from tests.helpers import CliRun, interrupt_at, tiny_cfg, tiny_synthetic

#: every solve runs its whole budget (no early stop), no scheduled checkpoints.
FIXED = ["solver.tol=0", "solver.max_iters=30", "checkpoint.every=0"]


def _density(run) -> np.ndarray:
    with np.load(run / "density.npz") as f:
        return f["density"]


def _solver_info(run) -> dict:
    return json.loads((run / "metrics.json").read_text())["solver"]


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread: on a busy two-core machine two threads make these tiny solves slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def solves(monkeypatch):
    """Every Solver.solve of the test, in order: (problem, x0 or None, result x)."""
    calls = []
    original = Solver.solve

    def recording(self, problem, x0=None, callback=None):
        result = original(self, problem, x0=x0, callback=callback)
        calls.append((problem, None if x0 is None else x0.clone(), result.x.clone()))
        return result

    monkeypatch.setattr(Solver, "solve", recording)
    return calls


def test_no_levels_is_the_plain_solve_bit_for_bit(tmp_path):
    cfg = tiny_cfg(*FIXED, "grid.levels=[]")
    reconstruct(cfg, tmp_path / "run")
    setup = prepare(cfg, tiny_synthetic(), torch.device("cpu"))
    result, _, _ = solve(cfg, setup)
    assert np.array_equal(_density(tmp_path / "run"), setup.volume(result.x).numpy())
    assert "levels" not in _solver_info(tmp_path / "run")


def test_each_level_starts_from_the_previous_solution_resampled(tmp_path, solves):
    # 2x finer along every axis, so each fine cell lies inside one coarse cell and the exact
    # resampling is a plain repeat of the coarse values (0 outside the coarse hull)
    run = tmp_path / "run"
    reconstruct(tiny_cfg(*FIXED, "grid.resolution=[12,16,12]", "grid.levels=[[6,8,6]]"), run)
    assert len(solves) == 2
    (coarse, cold_x0, coarse_x), (fine, fine_x0, _) = solves
    assert cold_x0 is None and coarse.grid_shape == (6, 8, 6) and fine.grid_shape == (12, 16, 12)
    C = coarse_x.shape[1]
    dense = torch.zeros(C, 6 * 8 * 6)
    dense[:, coarse.voxel_index] = coarse_x.T
    up = dense.reshape(C, 6, 8, 6)
    for axis in (1, 2, 3):
        up = up.repeat_interleave(2, dim=axis)
    expected = up.reshape(C, -1)[:, fine.voxel_index].T
    torch.testing.assert_close(fine_x0, expected, rtol=1e-6, atol=0)
    in_coarse_hull = torch.zeros(6 * 8 * 6, dtype=torch.bool)
    in_coarse_hull[coarse.voxel_index] = True
    up_hull = in_coarse_hull.reshape(6, 8, 6)
    for axis in (0, 1, 2):
        up_hull = up_hull.repeat_interleave(2, dim=axis)
    outside = ~up_hull.reshape(-1)[fine.voxel_index]
    assert bool((fine_x0[outside] == 0).all())
    assert float(fine_x0.sum()) > 0
    # TensorBoard's first fine-level objective (step 0) is that of the resampled start
    acc = EventAccumulator(str(run))
    acc.Reload()
    first = acc.Scalars("solve/objective")[0]
    assert first.step == 0
    assert first.value == pytest.approx(fine.objective(fine_x0), rel=1e-6)
    assert acc.Scalars("level0/solve/objective")[-1].step == 30


def test_levels_end_no_worse_than_a_cold_start_with_the_same_fine_budget(tmp_path):
    reconstruct(tiny_cfg(*FIXED), tmp_path / "cold")
    reconstruct(tiny_cfg(*FIXED, "grid.levels=[8]", "grid.level_iters=30"), tmp_path / "warm")
    cold, warm = _solver_info(tmp_path / "cold"), _solver_info(tmp_path / "warm")
    assert cold["iterations"] == warm["iterations"] == 30
    assert warm["objective"] <= cold["objective"]
    coarse, final = warm["levels"]
    assert coarse["resolution"] == [5, 8, 5] and final["resolution"] == [11, 16, 11]
    assert final["objective"] == warm["objective"] and coarse["iterations"] == 30
    # solver.l1_rel is relative to each level's own max(A^T P): larger on the coarser cells
    assert coarse["l1"] > 2 * final["l1"] and final["l1"] == warm["l1"]


def test_an_absolute_l1_is_scaled_by_the_cell_volume(tmp_path):
    run = tmp_path / "run"
    reconstruct(tiny_cfg(*FIXED, "solver.l1=1e-3", "grid.levels=[8]", "grid.level_iters=5"), run)
    coarse, final = _solver_info(run)["levels"]
    assert final["l1"] == 1e-3
    cells = [r["resolution"][0] * r["resolution"][1] * r["resolution"][2] for r in (coarse, final)]
    assert coarse["l1"] == pytest.approx(1e-3 * cells[1] / cells[0], rel=1e-12)


def test_leave_one_out_solves_the_levels_in_every_fold(tmp_path, solves):
    from flamerecon.run.leave_one_out import leave_one_out

    cfg = tiny_cfg(*FIXED, "solver.max_iters=5", "grid.levels=[8]")
    leave_one_out(cfg, tmp_path, views=["cam03", "cam04"])
    shapes = [problem.grid_shape for problem, _, _ in solves]
    assert shapes == [(5, 8, 5), (11, 16, 11)] * 2
    assert all(x0 is not None for _, x0, _ in solves[1::2])


@pytest.mark.parametrize("levels, match", [
    ("[16]", r"grid.levels: level 16 .* not coarser than grid.resolution"),
    ("[24]", r"grid.levels: level 24 .* not coarser than grid.resolution"),
    ("[8,4]", r"grid.levels: level 8 .* not coarser than level 4"),
    ("[8,8]", r"grid.levels: level 8 .* not coarser than level 8"),
    ("[[5,20,5]]", r"grid.levels: level \[5, 20, 5\] .* not coarser"),
])
def test_bad_levels_are_refused_by_name(tmp_path, levels, match):
    with pytest.raises(ConfigError, match=match):
        reconstruct(tiny_cfg(f"grid.levels={levels}"), tmp_path / "run")


def test_bad_level_budget_is_refused_by_name(tmp_path):
    with pytest.raises(ConfigError, match=r"grid.level_iters: .* one positive int per entry"):
        reconstruct(tiny_cfg("grid.levels=[4,8]", "grid.level_iters=[10]"), tmp_path / "run")


@pytest.mark.parametrize("tag_root, message", [
    ("level0/", r"SIGINT received at iteration 20 of coarse level grid.levels\[0\] \(5x8x5 cells\)"),
    ("", r"SIGINT received at iteration 20; the state is saved"),
])
def test_interrupted_level_resumes_to_the_uninterrupted_result(tmp_path, monkeypatch, tag_root, message):
    cfg = tiny_cfg(*FIXED, "grid.levels=[8]", "solver.check_every=5")
    reference = tmp_path / "reference"
    reconstruct(cfg, reference)
    run = tmp_path / "run"
    with pytest.raises(Interrupted, match=message):
        reconstruct(cfg, run, watch=interrupt_at(20, tag_root))  # the run's handler: checkpoint, stop
    with pytest.raises(ResumeError, match="field 'levels'"):
        reconstruct(tiny_cfg(*FIXED, "grid.levels=[4]", "solver.check_every=5"), run, resume=True)
    reconstruct(cfg, run, resume=True)
    np.testing.assert_allclose(_density(run), _density(reference), rtol=1e-5, atol=1e-7)
    levels = _solver_info(run)["levels"]
    assert [r["iterations"] for r in levels] == [30, 30]
    assert levels[0]["objective"] == pytest.approx(_solver_info(reference)["levels"][0]["objective"],
                                                   rel=1e-6)
    assert not (run / "checkpoint.pt").exists()


def test_a_diverging_coarse_level_stops_the_run_by_name(tmp_path):
    run = tmp_path / "run"
    with pytest.raises(SolveDiverged, match=r"coarse level grid.levels\[0\] \(5x8x5 cells\) diverged"):
        reconstruct(tiny_cfg(*FIXED, "grid.levels=[8]", "checkpoint.divergence_factor=1e-9"), run)
    assert not (run / "density.npz").exists()


@pytest.mark.slow
@pytest.mark.e2e
def test_train_py_with_levels_end_to_end(tmp_path):
    run = tmp_path / "run"
    cli = CliRun(run, "grid.levels=[4,8]", "grid.level_iters=[20,10]", "threads=1")
    done = cli.result()
    assert done.returncode == 0, done.stderr
    info = _solver_info(run)
    assert [r["resolution"][1] for r in info["levels"]] == [4, 8, 16]
    assert [r["iterations"] for r in info["levels"]] == [20, 10, 30]
    assert _density(run).shape[1:] == (11, 16, 11)
    acc = EventAccumulator(str(run))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"level0/solve/objective", "level1/solve/objective", "solve/objective",
            "level1/eval/heldout_psnr", "eval/heldout_psnr"} <= tags
