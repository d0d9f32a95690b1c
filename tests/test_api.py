"""The Python API: a notebook reconstructs the synthetic scene without Hydra and gets what
``python train.py`` gets, bit for bit; a CLI run folder loads back and re-scores to its own
metrics; the typed options are the CLI's defaults; the core imports neither Hydra nor
OmegaConf; photometry refits are checkpointed and resumed like the main solve."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

import flamerecon as fr
from flamerecon.errors import ConfigError, Interrupted
from flamerecon.run.pipeline import options_from_config, reconstruct
from tests.helpers import (
    REPO,
    TINY_API_SETUP,
    CliRun,
    interrupt_at,
    python_stdout,
    repo_env,
    tiny_cfg,
    tiny_config,
)

#: the settings of tests.helpers.TINY, written as a notebook would write them.
NOTEBOOK_SCENE = {"width": 48, "height": 36, "n_cameras": 5, "phantom_resolution": 32}
NOTEBOOK_OPTIONS = fr.ReconstructionOptions(
    grid=fr.GridOptions(resolution=16),
    solver=fr.SolverOptions("fista", None, 1.0e-3, {"max_iters": 30, "max_seconds": None, "tol": 1.0e-4,
                                                    "check_every": 10}),
    device="cpu", threads=1,  # one thread: the same summation order in both processes
)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """``python train.py`` on the tiny settings (TINY), as a user types it."""
    run = tmp_path_factory.mktemp("cli") / "run"
    done = CliRun(run, "threads=1").result()
    assert done.returncode == 0, done.stderr
    return run


def test_the_typed_defaults_are_the_clis():
    assert options_from_config(tiny_config("threads=1")) == NOTEBOOK_OPTIONS
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        default = compose(config_name="train")  # python train.py, nothing on the command line
    assert options_from_config(default) == fr.ReconstructionOptions()
    assert fr.ReconstructionOptions().solver.name == "pqn_smooth"


@pytest.mark.e2e
def test_a_notebook_gets_the_density_of_train_py_bit_for_bit(cli_run):
    scene = fr.load_scene("synthetic", **NOTEBOOK_SCENE)
    rec = fr.reconstruct(scene, NOTEBOOK_OPTIONS)
    with np.load(cli_run / "density.npz") as saved:
        np.testing.assert_array_equal(rec.density.numpy(), saved["density"])
    metrics = json.loads((cli_run / "metrics.json").read_text())
    scores = fr.score(rec)
    for part in ("heldout", "train"):
        for view, values in metrics[part].items():
            assert scores[part][view]["psnr"] == values["psnr"]
    assert rec.fit.result.iterations == metrics["solver"]["iterations"]


@pytest.mark.e2e
def test_load_run_rescores_a_cli_run_to_its_metrics(cli_run):
    run = fr.load_run(cli_run, device="cpu")
    assert run.options == NOTEBOOK_OPTIONS and run.scene.views[run.holdout[0]] == "cam04"
    written, again = run.metrics, fr.score(run)
    for part in ("heldout", "train"):
        assert again[part].keys() == written[part].keys()
        for view, values in written[part].items():
            for key, value in values.items():
                assert again[part][view][key] == pytest.approx(value, rel=1e-6, abs=1e-9), (part, view, key)
    assert again["volume"] == pytest.approx(written["volume"])
    images = fr.render(run.density, run.grid, run.scene.cameras)
    assert images.shape == (5, 3, 36, 48) and float(images.min()) >= 0


def test_the_core_imports_neither_hydra_nor_omegaconf():
    # a scene by its options mapping: a preset's name (fr.load_scene("synthetic"), fr.preset)
    # composes conf/ as the command line does, with Hydra, in the run layer
    code = (f"import sys, flamerecon as fr; {TINY_API_SETUP}; fr.reconstruct(s, o); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'omegaconf')))")
    assert python_stdout(code).strip() == "[]"


@pytest.mark.parametrize("given, expected", [({}, "1000"), ({"GOMP_SPINCOUNT": "50"}, "50"),
                                             ({"OMP_WAIT_POLICY": "ACTIVE"}, None)])
def test_openmp_threads_spin_briefly_unless_the_user_says_otherwise(given, expected):
    env = {k: v for k, v in repo_env().items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = "import os, flamerecon, torch; print(os.environ.get('GOMP_SPINCOUNT'))"
    done = subprocess.run([sys.executable, "-c", code], check=False, cwd=REPO, env={**env, **given},
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(expected)


def test_the_api_names_are_all_exported():
    assert fr.__all__ == sorted(fr.API)
    for name in fr.__all__:
        assert getattr(fr, name) is not None


@pytest.mark.parametrize("config, message", [
    ({"grid": {"resolutoin": 8}}, r"grid: unknown key 'resolutoin'; valid keys are \['resolution'"),
    ({"sovler": {}}, r"options: unknown key 'sovler'"),
    ({"solver": {"l1_rel": 0.1}}, r"solver.name: missing"),
    ({"debias": {"method": "mean"}}, r"debias.method: unknown method 'mean'; debias.method must be one of none, gain, refit"),
])
def test_bad_options_name_the_key(config, message):
    with pytest.raises(ConfigError, match=message):
        fr.ReconstructionOptions.from_dict(config)


def test_a_misspelt_solver_option_is_refused_by_name():
    with pytest.raises(ConfigError, match=r"solver.max_iter: unknown option of solver 'pqn_smooth'"):
        fr.SolverOptions(params={"max_iter": 5})


REFIT = ["photometry.fit_gain=true", "photometry.rounds=2", "solver.max_iters=30", "solver.check_every=5",
         "solver.tol=0", "checkpoint.every=10"]


@pytest.mark.slow
def test_an_interrupted_photometry_refit_resumes_to_the_uninterrupted_result(tmp_path):
    reference, run = tmp_path / "reference", tmp_path / "run"
    straight = reconstruct(tiny_cfg(*REFIT), reference)
    with pytest.raises(Interrupted, match=r"SIGINT received at iteration 15 \(photometry refit 2\)"):
        reconstruct(tiny_cfg(*REFIT), run, watch=interrupt_at(15, "refit2/"))
    assert (run / "checkpoint.pt").is_file() and not (run / "density.npz").exists()
    resumed = reconstruct(tiny_cfg(*REFIT), run, resume=True)
    with np.load(run / "density.npz") as a, np.load(reference / "density.npz") as b:
        np.testing.assert_allclose(a["density"], b["density"], rtol=1e-5, atol=1e-7)
    assert resumed["solver"]["photometry"] == straight["solver"]["photometry"] == {
        "rounds": 2, "iterations": [30, 30]}
    assert resumed["solver"]["iterations"] == straight["solver"]["iterations"] == 90  # solve + 2 refits
    assert resumed["solver"]["seconds"] > 0
    assert not (run / "checkpoint.pt").exists()


def test_a_density_warm_starts_the_next_reconstruction():
    scene = fr.load_scene("synthetic", width=24, height=18, n_cameras=3, phantom_resolution=16)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=8), device="cpu",
                                       solver=fr.SolverOptions().with_values(max_iters=60, tol=0))
    done = fr.reconstruct(scene, options)
    few = options.replace(solver=options.solver.with_values(max_iters=5))
    cold, warm = fr.reconstruct(scene, few), fr.reconstruct(scene, few, init=done.density)
    assert warm.fit.result.objective < cold.fit.result.objective
    assert warm.fit.result.objective <= done.fit.result.objective * (1 + 1e-6)


@pytest.mark.parametrize("section, values, message", [
    (fr.GridOptions, {"resolution": -3}, r"grid.resolution: got -3"),
    (fr.ProjectorOptions, {"step": 0}, r"projector.step: got 0"),
    (fr.SolverOptions, {"l1_rel": -1.0}, r"solver.l1_rel: got -1.0"),
])
def test_the_api_checks_values_by_the_clis_rules(section, values, message):
    with pytest.raises(ConfigError, match=message):
        section(**values)
