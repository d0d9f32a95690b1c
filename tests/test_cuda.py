"""The CUDA path agrees with the CPU path: operators, a solve, and ``python train.py``.

Skipped where torch sees no CUDA device (CI has none); run on a GPU machine with
``python -m pytest tests/test_cuda.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from flamerecon.operators import dottest
from flamerecon.operators.projector import make_operator
from flamerecon.solvers import Problem, make_solver
from tests.helpers import REPO, TINY, csr, random_hull, random_rays, repo_env, tiny_problem

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device")
CUDA = torch.device("cuda")


@pytest.mark.parametrize("backend", ["assembled", "matrix_free"])
def test_operators_on_cuda_match_cpu_and_pass_the_dot_test(box_grid, backend):
    rays = random_rays(box_grid, 300)
    voxel_index = random_hull(box_grid)
    cpu = make_operator(backend, box_grid, rays, voxel_index)
    gpu = make_operator(backend, box_grid, rays.to(CUDA), voxel_index.to(CUDA))
    g = torch.Generator().manual_seed(1)
    x, y = torch.rand(cpu.shape[1], 3, generator=g), torch.randn(cpu.shape[0], 3, generator=g)
    Ax, ATy = gpu.forward(x.to(CUDA)).cpu(), gpu.adjoint(y.to(CUDA)).cpu()
    assert Ax.abs().max() > 0
    assert (Ax - cpu.forward(x)).abs().max() <= 1e-5 * Ax.abs().max()
    assert (ATy - cpu.adjoint(y)).abs().max() <= 1e-5 * ATy.abs().max()
    dottest(gpu, x.to(CUDA), y.to(CUDA), rtol=1e-5)


@pytest.mark.parametrize("name", ["fista", "fista_smooth", "tv"])
def test_a_solve_on_cuda_reaches_the_cpu_objective(name):
    A, b, lam = tiny_problem()
    op = csr(A)
    geometry = {"grid_shape": (3, 4, 5), "voxel_index": torch.arange(A.shape[1])}
    options = {"max_iters": 3000, "tol": 1e-7}
    objectives = []
    for device in ("cpu", CUDA):
        operator = op if device == "cpu" else op.to(device)
        problem = Problem(operator, torch.tensor(b).to(device), lam, **geometry)
        objectives.append(make_solver(name, **options).solve(problem).objective)
    assert objectives[1] == pytest.approx(objectives[0], rel=1e-5)


@pytest.mark.slow
@pytest.mark.e2e
def test_train_py_on_cuda_scores_like_the_cpu_run(tmp_path):
    scores = {}
    for device in ("cpu", "cuda"):
        run_dir = tmp_path / device
        args = [*[a for a in TINY if not a.startswith("device=")], f"device={device}",
                f"hydra.run.dir={run_dir}"]
        subprocess.run([sys.executable, "train.py", *args], cwd=REPO, check=True,
                       env=repo_env(), capture_output=True)
        metrics = json.loads((run_dir / "metrics.json").read_text())
        assert metrics["solver"]["device"].startswith(device)
        scores[device] = metrics["heldout"]["cam04"]
    for key in ("psnr", "ssim"):
        assert scores["cuda"][key] == pytest.approx(scores["cpu"][key], abs=0.05)
