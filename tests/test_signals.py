"""A stop signal (SIGINT, SIGTERM, SIGHUP) ends every entry point at every stage the same way
(issue 33): acted on within an iteration or a chunk wherever it arrives, one line, exit status
130, the run's state checkpointed inside the solve and a ``FAILED`` file outside it (a folder
holding nothing but Hydra's entries removed instead), the lock released, no traceback.

Three tables: the mechanism itself (:mod:`flamerecon.interrupt`) with real signals in this
process; a run's stages, in this process through the entry point's handlers; every entry point
(``train.py``, the ``flamerecon`` command, each script) as a subprocess, signalled at its
start-up and at stages of its work (``tests/helpers/signal_child.py``)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tomllib
import torch
from omegaconf import OmegaConf

from flamerecon.errors import Interrupted
from flamerecon.interrupt import REQUIRED
from flamerecon.run import guard, pipeline
from flamerecon.run.checkpoint import CHECKPOINT_FILE
from flamerecon.run.runner import FAILED_FILE, run_task
from flamerecon.solvers import Problem, make_solver
from tests.helpers import FAST, REPO, TINY, csr, repo_env, tiny_cfg, tiny_problem
from tests.helpers.interrupts import signal_in_loop, signal_on_call, stop_handlers

ERROR = "flamerecon: error: "


@pytest.fixture
def handlers():
    with stop_handlers() as interrupt:
        yield interrupt


# ---------------------------------------------------------------------------------------------
# the mechanism

def a_problem() -> Problem:
    A, b, lam = tiny_problem()
    return Problem(csr(A), torch.from_numpy(b), lam)


def test_a_signal_outside_a_solve_raises_at_once_naming_itself(handlers):
    for sig in handlers.STOP_SIGNALS:
        with pytest.raises(handlers.Stopped) as stop:
            os.kill(os.getpid(), sig)
        assert stop.value.signal == signal.Signals(sig).name
        assert isinstance(stop.value, KeyboardInterrupt)  # no `except Exception` swallows it


def test_inside_a_solve_the_first_signal_waits_for_check_and_a_second_raises_at_once(handlers):
    with pytest.raises(handlers.Stopped, match="SIGHUP") as second, handlers.deferred():
        os.kill(os.getpid(), signal.SIGTERM)
        assert handlers.received() == "SIGTERM"  # recorded, not raised
        os.kill(os.getpid(), signal.SIGHUP)
    assert second.value.forced and handlers.received() is None
    with pytest.raises(handlers.Stopped, match="SIGTERM"), handlers.deferred():
        os.kill(os.getpid(), signal.SIGTERM)
        handlers.check()
    with pytest.raises(handlers.Stopped, match="SIGINT"), handlers.deferred():  # raised at the block's end
        os.kill(os.getpid(), signal.SIGINT)
    with pytest.raises(ValueError), handlers.deferred():  # an error ends the block: nothing left over
        os.kill(os.getpid(), signal.SIGINT)
        raise ValueError
    handlers.check()


def test_check_is_a_no_op_without_a_signal_and_when_nothing_is_installed():
    from flamerecon import interrupt

    interrupt.check()
    assert signal.getsignal(signal.SIGTERM) is not interrupt._handle  # the API installs nothing


def test_once_the_work_is_over_signals_are_ignored(handlers):
    handlers.finish()
    for sig in handlers.STOP_SIGNALS:
        os.kill(os.getpid(), sig)  # the process goes on: it is exiting anyway


def test_a_long_loop_stops_between_its_chunks(handlers):
    """The solve whose next check is 10**6 iterations away (the 38-minute case) stops at the
    next iteration after the signal, its state saved at the last check."""
    solver = make_solver("fista", max_iters=10**6, check_every=10**6, tol=0.0)
    seen = []

    def count(it, x, info):
        seen.append(it)

    original = handlers.check
    calls = [0]

    def check():
        calls[0] += 1
        if calls[0] == 50:
            os.kill(os.getpid(), signal.SIGTERM)
        original()

    handlers.check = check
    try:
        with pytest.raises(handlers.Stopped), handlers.deferred():
            solver.solve(a_problem(), callback=count)
    finally:
        handlers.check = original
    assert calls[0] == 50 and not seen  # stopped at iteration 50 of 10**6, before any check


# ---------------------------------------------------------------------------------------------
# a run's stages, in this process (the entry point's handlers installed)

SOLVE = [*FAST, "solver.max_iters=40", "solver.tol=0", "solver.check_every=10", "checkpoint.every=0"]


def _scene(monkeypatch, sig):
    signal_on_call(monkeypatch, pipeline, "load_scene", sig)


def _camera_fit(monkeypatch, sig):
    signal_in_loop(monkeypatch, "camera_step", sig)


def _weight_selection(monkeypatch, sig):
    signal_in_loop(monkeypatch, "select_weights", sig, nth=2)


def _solve_at_a_check(monkeypatch, sig):
    signal_on_call(monkeypatch, guard.SolveGuard, "__call__", sig, nth=3)


def _solve_between_checks(monkeypatch, sig):
    signal_in_loop(monkeypatch, "_run", sig, nth=25)


def _twice_in_the_solve(monkeypatch, sig):
    signal_in_loop(monkeypatch, "_run", sig, nth=25, times=2)  # the second stops at once, no checkpoint


def _scoring(monkeypatch, sig):
    signal_in_loop(monkeypatch, "score_views", sig)


def _outputs(monkeypatch, sig):
    signal_on_call(monkeypatch, pipeline, "write_outputs", sig)


# stage: (overrides, how the signal is sent, signal, checkpointed (else FAILED), message)
STAGES = {
    "loading the scene": ([], _scene, signal.SIGTERM, False, r"interrupted by SIGTERM outside the solve; nothing"),
    "the camera fit": (["calibration.refine=pose", "calibration.rounds=1", "calibration.iterations=2"],
                       _camera_fit, signal.SIGHUP, False, r"interrupted by SIGHUP outside the solve; nothing"),
    "the weight selection": (["select.auto=true", "select.iterations=5", "select.folds=2"], _weight_selection,
                             signal.SIGINT, False, r"interrupted by SIGINT outside the solve; nothing"),
    "the solve, at a check": ([], _solve_at_a_check, signal.SIGTERM, True,
                              r"SIGTERM received at iteration 30; the state is saved in checkpoint.pt; continue"),
    "the solve, between checks": ([], _solve_between_checks, signal.SIGHUP, True,
                                  r"SIGHUP received at iteration 20; the state is saved"),
    "the solve, a second signal": ([], _twice_in_the_solve, signal.SIGINT, False,
                                   r"stopped at once by a second SIGINT; nothing was checkpointed"),
    "the scoring": ([], _scoring, signal.SIGTERM, False, r"interrupted by SIGTERM outside the solve; nothing"),
    "writing the outputs": ([], _outputs, signal.SIGINT, False, r"interrupted by SIGINT outside the solve"),
}


@pytest.mark.parametrize("stage", list(STAGES))
def test_a_signal_at_each_stage_of_a_run(stage, handlers, tmp_path, capsys, monkeypatch):
    overrides, send, sig, checkpointed, pattern = STAGES[stage]
    run = tmp_path / "run"
    send(monkeypatch, sig)
    with pytest.raises(SystemExit) as stop:
        run_task(tiny_cfg(*SOLVE, *overrides), run)
    assert stop.value.code == 130
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(ERROR)]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert re.search(pattern, lines[0]), lines[0]
    assert not (run / ".lock").exists()
    assert (run / CHECKPOINT_FILE).is_file() == checkpointed
    assert (run / FAILED_FILE).is_file() != checkpointed
    if not checkpointed:
        assert (run / FAILED_FILE).read_text().strip() == lines[0][len(ERROR):]


def stopped_run(monkeypatch, run: Path, send) -> None:
    """The tiny solve run into ``run``, stopped by ``send`` (a stage of :data:`STAGES`) with a
    SIGTERM, its config saved as Hydra saves it (``resume=`` reads it)."""
    cfg = tiny_cfg(*SOLVE)
    with monkeypatch.context() as patch:
        send(patch, signal.SIGTERM)
        with pytest.raises(SystemExit):
            run_task(cfg, run)
    (run / ".hydra").mkdir()
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")


def test_a_solve_stopped_between_checks_resumes_to_the_uninterrupted_result(handlers, tmp_path, capsys,
                                                                           monkeypatch):
    whole, run = tmp_path / "whole", tmp_path / "run"
    run_task(tiny_cfg(*SOLVE), whole)
    stopped_run(monkeypatch, run, _solve_between_checks)
    run_task(tiny_cfg(*SOLVE, f"resume={run}"), tmp_path / "resume-command")
    with np.load(whole / "density.npz") as a, np.load(run / "density.npz") as b:
        np.testing.assert_array_equal(a["density"], b["density"])
    capsys.readouterr()


def test_a_signal_while_resuming_marks_the_resumed_run_and_a_later_resume_clears_it(handlers, tmp_path, capsys,
                                                                                  monkeypatch):
    from flamerecon.run import hook

    run = tmp_path / "run"
    stopped_run(monkeypatch, run, _solve_at_a_check)
    with monkeypatch.context() as patch:
        signal_on_call(patch, hook, "resume_solver", signal.SIGHUP)
        with pytest.raises(SystemExit) as stop:
            run_task(tiny_cfg(*SOLVE, f"resume={run}"), tmp_path / "resume-command")
    assert stop.value.code == 130
    failed = (run / FAILED_FILE).read_text()
    assert "interrupted by SIGHUP outside the solve; its last checkpoint is kept: python train.py resume=" in failed
    run_task(tiny_cfg(*SOLVE, f"resume={run}"), tmp_path / "resume-command")
    assert not (run / FAILED_FILE).exists() and json.loads((run / "metrics.json").read_text())["solver"]
    capsys.readouterr()


def test_the_python_api_keeps_pythons_own_ctrl_c(tmp_path):
    """No entry point ran: a SIGINT in a solve called from Python is Python's KeyboardInterrupt."""
    def ctrl_c(it, x, info):
        os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        make_solver("fista", max_iters=50, check_every=5).solve(a_problem(), callback=ctrl_c)
    assert not isinstance(Interrupted("x"), KeyboardInterrupt)  # the run layer's own, exit status 130


# ---------------------------------------------------------------------------------------------
# every entry point as a subprocess

CHILD = REPO / "tests" / "helpers" / "signal_child.py"
TINY_RUN = [*TINY, *FAST]


def signalled(sig: str, where: str, entry: str | Path, *args: str, cwd=REPO) -> subprocess.CompletedProcess:
    """``entry args`` run as a user runs it, sent ``sig`` at ``where`` (see signal_child.py)."""
    env = {**repo_env(), "FLAMERECON_PROGRESS": "1"}
    return subprocess.run([sys.executable, str(CHILD), sig, where, str(entry), *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300, check=False)


def assert_one_line_130(done: subprocess.CompletedProcess, pattern: str) -> str:
    err = done.stderr
    lines = [line for line in err.splitlines() if line.startswith(ERROR)]
    assert done.returncode == 130, (done.returncode, err[-3000:])
    assert "Traceback" not in err + done.stdout and len(lines) == 1, err[-3000:]
    assert re.search(pattern, lines[0]), lines[0]
    return lines[0]


HYDRA_LOAD = "call:hydra._internal.config_loader_impl:ConfigLoaderImpl.load_configuration"

# stage: (signal, trigger, extra overrides, what the folder holds after: None (no folder),
# "checkpoint" or "FAILED"; the message)
TRAIN_STAGES = {
    "start-up (importing torch)": ("SIGTERM", "import:torch", [], None, r"interrupted by SIGTERM while starting"),
    "composing the config": ("SIGHUP", HYDRA_LOAD, [], None, r"interrupted by SIGHUP outside a run's work"),
    "before any work (the workload estimate)": ("SIGINT", "log:estimate", [], None,
                                                r"SIGINT before the run wrote anything; its folder was removed"),
    "a long solve, mid-loop": ("SIGTERM", "check:_run@1.5", ["solver.max_iters=1000000", "solver.check_every=1000000",
                                                            "solver.tol=0"], "checkpoint",
                               r"SIGTERM received at iteration 0; the state is saved in checkpoint.pt"),
    "the scoring": ("SIGHUP", "check:score_views", [], "FAILED", r"interrupted by SIGHUP outside the solve"),
}


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.parametrize("stage", list(TRAIN_STAGES))
def test_train_py_at_each_stage(stage, tmp_path):
    sig, where, overrides, left, pattern = TRAIN_STAGES[stage]
    run = tmp_path / "run"
    done = signalled(sig, where, "train.py", *TINY_RUN, *overrides, f"hydra.run.dir={run}")
    assert_one_line_130(done, pattern)
    if left is None:
        assert not run.exists()
        return
    assert not (run / ".lock").exists()
    assert (run / (CHECKPOINT_FILE if left == "checkpoint" else FAILED_FILE)).is_file()


@pytest.mark.slow
@pytest.mark.e2e
def test_a_multirun_stops_at_the_job_it_was_in(tmp_path):
    sweep = tmp_path / "sweep"
    done = signalled("SIGTERM", "call:flamerecon.run.guard:SolveGuard.__call__:5", "train.py", "--multirun",
                     *TINY_RUN, "solver.max_iters=30", "seed=0,1", f"hydra.sweep.dir={sweep}")
    assert_one_line_130(done, r"sweep/1: SIGTERM received at iteration \d+")
    assert (sweep / "0" / "metrics.json").is_file() and (sweep / "1" / CHECKPOINT_FILE).is_file()
    assert not list(sweep.rglob(".lock"))


@pytest.mark.slow
@pytest.mark.e2e
def test_a_multirun_interrupted_while_it_starts_a_job_keeps_the_jobs_before(tmp_path):
    sweep = tmp_path / "sweep"
    done = signalled("SIGINT", "call:hydra.core.utils:run_job:2", "train.py", "--multirun", *TINY_RUN,
                     "seed=0,1", f"hydra.sweep.dir={sweep}")
    assert_one_line_130(done, r"interrupted by SIGINT outside a run's work \(starting, or between a sweep's jobs\)")
    assert (sweep / "0" / "metrics.json").is_file() and not (sweep / "1").exists()
    assert not list(sweep.rglob(".lock"))


@pytest.mark.slow
@pytest.mark.e2e
def test_the_flamerecon_command_installs_them_from_its_first_line(tmp_path):
    command = shutil.which("flamerecon", path=str(Path(sys.executable).parent))
    assert command is not None, "the console script of the editable install"
    run = tmp_path / "run"
    done = signalled("SIGTERM", "import:hydra", command, *TINY_RUN, f"hydra.run.dir={run}")
    assert_one_line_130(done, r"interrupted by SIGTERM")
    assert not run.exists()


SCRIPTS = sorted(p.stem for p in (REPO / "scripts").glob("*.py"))


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.parametrize("name", SCRIPTS)
def test_every_script_handles_a_signal_from_its_first_line(name):
    sig = ("SIGTERM", "SIGHUP", "SIGINT")[SCRIPTS.index(name) % 3]
    done = signalled(sig, "import:flamerecon.run.cli", REPO / "scripts" / f"{name}.py", "--help")
    assert_one_line_130(done, rf"interrupted by {sig} while starting")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("signals") / "run"
    done = subprocess.run([sys.executable, "train.py", *TINY_RUN, f"hydra.run.dir={run}"], cwd=REPO,
                          env=repo_env(), capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    return run


@pytest.mark.slow
@pytest.mark.e2e
def test_scripts_mid_work(finished_run, tmp_path):
    done = signalled("SIGHUP", "check:score_views", REPO / "scripts" / "evaluate.py", str(finished_run),
                     "--device", "cpu", "--no-native")
    assert_one_line_130(done, r"evaluate.py|interrupted by SIGHUP; every file written before is complete")
    assert not (finished_run / ".lock").exists()
    json.loads((finished_run / "metrics.json").read_text())  # whole: written before, or not at all
    done = signalled("SIGTERM", "check:leave_one_out:2", REPO / "scripts" / "leave_one_out.py", "--out",
                     str(tmp_path / "loo"), *TINY_RUN)
    assert_one_line_130(done, r"interrupted by SIGTERM; every file written before is complete")


@pytest.mark.slow
@pytest.mark.e2e
def test_a_script_passes_the_signal_on_to_the_run_it_started(tmp_path):
    out = tmp_path / "out"
    done = signalled("SIGTERM", "call:flamerecon.run.cli:run_child@10", REPO / "scripts" / "first_run.py", "--out",
                     str(out), "--frames", "0", "1", "scene=synthetic", *TINY_RUN, "solver.max_iters=1000000",
                     "solver.tol=0")
    assert_one_line_130(done, r"interrupted by SIGTERM")
    run = out / "frame0"
    assert (run / CHECKPOINT_FILE).is_file() or (run / FAILED_FILE).is_file(), list(run.iterdir())
    assert not (run / ".lock").exists()


@pytest.mark.parametrize("entry", [["train.py", "holdout=[no_such_camera]"], ["scripts/uncertainty_check.py", "--help"]])
def test_a_python_without_a_package_the_project_needs_is_told_in_one_line(entry, tmp_path):
    """An entry point run by a Python that lacks a dependency (here hydra, hidden from the import
    system) ends in one line naming the module, its package and the way to install it, exit 2."""
    code = ("import runpy, sys; sys.modules['hydra'] = None; sys.modules['torch'] = None; "
            f"sys.argv = {entry!r}; runpy.run_path({entry[0]!r}, run_name='__main__')")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=repo_env(), capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    assert re.fullmatch(r"flamerecon: error: this Python \(.+\) has no module '(hydra|torch)' \(package "
                        r"(hydra-core|torch)\), which flamerecon needs; install the project into it .*\n", done.stderr)


def test_the_packages_an_entry_point_names_are_those_pyproject_declares():
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0] for d in declared}
    assert set(REQUIRED.values()) == names
