"""Solver options are strict: every shipped solver config instantiates exactly, and a key no
solver takes is an error naming it and the valid ones (exit status 2 at the run layer)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from flamerecon.operators import norm_sq
from flamerecon.run.pipeline import solver_options
from flamerecon.run.runner import run_task
from flamerecon.solvers import SOLVERS, Problem, make_solver
from tests.helpers import REPO, csr, tiny_cfg, tiny_problem

SOLVER_CONFIGS = sorted(p.stem for p in (REPO / "conf" / "solver").glob("*.yaml"))


def composed(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def test_an_unknown_option_names_the_key_and_lists_the_valid_ones():
    with pytest.raises(ValueError, match=r"^solver.max_iter: unknown option of solver 'fista'; "
                                         r"valid: check_every, max_iters, max_seconds, restart, tol"):
        make_solver("fista", max_iter=100)
    with pytest.raises(ValueError, match=r"solver.restart: unknown option of solver 'adam'"):
        make_solver("adam", restart=False)
    # options a subclass passes on to its parent stay valid
    assert make_solver("fista_smooth", smooth=0.1, max_iters=7, restart=False).max_iters == 7


@pytest.mark.parametrize("name", SOLVER_CONFIGS)
def test_every_solver_config_instantiates_strictly(name):
    cfg = composed(f"solver={name}")
    solver = make_solver(cfg.solver.name, **solver_options(cfg))
    assert isinstance(solver, SOLVERS[cfg.solver.name])
    with pytest.raises(ValueError, match=r"solver.max_iter: unknown option"):
        misspelt = composed(f"solver={name}", "++solver.max_iter=100")
        make_solver(misspelt.solver.name, **solver_options(misspelt))


def test_every_solver_of_the_package_has_a_config():
    names = {composed(f"solver={n}").solver.name for n in SOLVER_CONFIGS}
    assert {n for n, cls in SOLVERS.items() if cls.__module__.startswith("flamerecon.")} <= names


def test_fista_iterate_is_its_solve_untimed_with_a_given_lipschitz_constant():
    A, b, lam = tiny_problem()
    problem = Problem(csr(A), torch.tensor(b), lam)
    solved = make_solver("fista", max_iters=40, tol=0.0).solve(problem)
    warm = make_solver("fista", max_iters=40, tol=0.0)
    warm._started = time.perf_counter()
    L = 1.01 * norm_sq(problem.A, problem.b.device, problem.b.dtype)
    iterated = warm.iterate(problem, torch.zeros_like(solved.x), None, lipschitz=L)
    assert torch.equal(iterated.x, solved.x) and iterated.iterations == solved.iterations == 40
    doubled = warm.iterate(problem, torch.zeros_like(solved.x), None, lipschitz=2 * L)
    assert not torch.equal(doubled.x, solved.x)  # the constant given is the one used


def test_a_misspelt_solver_key_exits_2_with_one_line(tmp_path: Path, capsys):
    with pytest.raises(SystemExit) as info:
        run_task(tiny_cfg("++solver.max_iter=100"), tmp_path)
    assert info.value.code == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith(
        "flamerecon: error: solver.max_iter: unknown option of solver 'fista'; valid: ")
    assert "max_iters" in errors[0]
