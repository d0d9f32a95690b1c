"""Bad input tried as a new user would (issue 13): one table per family, each case checked
against its one-line message and its exit status (0, 2, 3 or 130 only), and that nothing
already written is lost."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.errors import Interrupted
from flamerecon.geometry.cameras import K_of, opencv_w2c_to_opengl_c2w
from flamerecon.outputs.export import save_density
from flamerecon.run import checkpoint, pipeline
from flamerecon.run.hook import RunHook
from flamerecon.run.pipeline import reconstruct
from flamerecon.run.runner import FAILED_FILE, run_task
from flamerecon.run.summary import summary_table
from flamerecon.scenes import SceneError, load_scene
from flamerecon.scenes.frames import read_camera_frame
from tests.helpers import (
    FAST,
    REPO,
    interrupt_at,
    refused_line,
    repo_env,
    tiny_cfg,
    tiny_synthetic,
    tmpfs,
)
from tests.helpers import TINY as TINY_SCENE

TINY = [*TINY_SCENE, *FAST]  # the tiny config with the short solve

ERROR = "flamerecon: error: "


def outcome(capsys, cfg, run_dir, overrides=None) -> tuple[int, str]:
    """(exit status, the one error line) of ``run_task`` as train.py runs it."""
    try:
        run_task(cfg, run_dir, overrides=overrides)
        code = 0
    except SystemExit as stop:
        code = stop.code
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith(ERROR)]
    assert len(lines) <= 1, lines
    return code, lines[0][len(ERROR):] if lines else ""


def script(name: str):
    spec = importlib.util.spec_from_file_location(f"script_{name}", REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def script_outcome(capsys, name: str, argv: list[str]) -> tuple[int, str]:
    """(exit status, the one error line) of ``scripts/<name>.py argv``, run in this process."""
    try:
        code = script(name).main(argv)
    except SystemExit as stop:  # argparse
        code = stop.code
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(ERROR)]
    assert "Traceback" not in err and len(lines) <= 1, err
    return code, lines[0][len(ERROR):] if lines else ""


# ---------------------------------------------------------------------------------------------
# a tiny NeRF capture (the tiny synthetic scene written as transforms.json)

def write_nerf(folder: Path, paths: list[str] | None = None, holdout=None) -> Path:
    """transforms.json in ``folder`` listing ``paths`` (default ./images/cam0i); frame i uses
    camera and image i % 5 of the tiny synthetic scene, written at its path (``.png`` added
    when the path has no suffix)."""
    scene = tiny_synthetic()
    K = K_of(scene.cameras)[0]
    c2w = opencv_w2c_to_opengl_c2w(scene.cameras.extrinsics.double())
    paths = paths or [f"./images/{v}" for v in scene.views]
    frames = []
    for i, rel in enumerate(paths):
        file = folder / (rel if Path(rel).suffix else rel + ".png")
        file.parent.mkdir(parents=True, exist_ok=True)
        image = scene.images[i % 5].permute(1, 2, 0).numpy()[..., ::-1]
        cv2.imwrite(str(file), (image * 255 + 0.5).astype(np.uint8))
        frames.append({"file_path": rel, "transform_matrix": c2w[i % 5].tolist()})
    data = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2]), "w": 48, "h": 36, "frames": frames,
            "bbox": [list(scene.bbox_min), list(scene.bbox_max)]}
    (folder / "transforms.json").write_text(json.dumps(data))
    return folder


def nerf_cfg(root: Path, *overrides: str):
    with initialize_config_dir(str(REPO / "conf"), version_base="1.3"):
        return compose("train", overrides=["scene=nerf", f"scene.root={root}", "grid.resolution=16",
                                           "solver.max_iters=10", "log.eval_every=0", *overrides])


# ---------------------------------------------------------------------------------------------
# family: a held-out view that leaks into training (NeRF duplicates)

def _same_file_twice(folder):
    return write_nerf(folder, [*(f"./images/cam0{i}" for i in range(5)), "images/cam02"])


def _same_file_other_spelling(folder):
    return write_nerf(folder, [*(f"./images/cam0{i}" for i in range(5)), "./images/cam02.png"])


def _clashing_names(folder):
    return write_nerf(folder, [*(f"./images/cam0{i}.png" for i in range(5)), "./images/cam02.jpg"])


def _same_image_other_file(folder):
    write_nerf(folder, [*(f"./images/cam0{i}" for i in range(5)), "./images/dup"])
    shutil.copy(folder / "images" / "cam00.png", folder / "images" / "dup.png")
    return folder


LEAKS = {
    "file_path repeated": (_same_file_twice, None,
                           (r"frames\[5\]\.file_path: 'images/cam02' is a duplicate: 'images/cam02' is "
                           r"already frames\[2\]")),
    "file_path repeated with its extension": (
        _same_file_other_spelling, None,
        (r"frames\[5\]\.file_path: '\./images/cam02\.png' is a duplicate: the image .*cam02\.png is already "
        r"frames\[2\]")),
    "view name repeated": (_clashing_names, None,
                           (r"frames\[5\]\.file_path: .*duplicate: view name 'images/cam02' is already "
                           r"frames\[2\]")),
    "held-out image among the training images": (
        _same_image_other_file, "holdout=[dup]",
        r"held-out view 'dup' has the same image as training view 'cam00'; drop the duplicate"),
}


@pytest.mark.parametrize("case", list(LEAKS))
def test_a_held_out_view_never_leaks_into_training(case, tmp_path, capsys):
    make, holdout, message = LEAKS[case]
    root = make(tmp_path / "capture")
    cfg = nerf_cfg(root, *([holdout] if holdout else ["holdout=[cam04]"]))
    code, line = outcome(capsys, cfg, tmp_path / "run")
    assert code == 2 and line, line
    assert re.search(message, line), line
    assert "unknown view" not in line
    assert not (tmp_path / "run" / "density.npz").exists()


# ---------------------------------------------------------------------------------------------
# family: one writer per run folder

def _held_by_a_live_process(run: Path):
    run.mkdir(parents=True)
    fd = os.open(run / ".lock", os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.write(fd, b"pid=4242\nhost=elsewhere\nsince=now\n")
    return lambda: os.close(fd)


def _left_by_a_dead_process(run: Path):
    run.mkdir(parents=True)
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)
    (run / ".lock").write_text(f"pid={child.stdout.strip()}\nhost=this\nsince=then\n")
    return lambda: None


def _holder_killed(run: Path):
    holder = subprocess.Popen(
        [sys.executable, "-c", ("import sys, time\nfrom flamerecon.run.lock import acquire\n"
         f"acquire({str(run)!r}); print('held', flush=True); time.sleep(600)")],
        stdout=subprocess.PIPE, text=True, env=repo_env())
    assert holder.stdout.readline().strip() == "held"
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=60)
    assert (run / ".lock").exists()  # SIGKILL left the file: it must not stick
    return lambda: None


LOCKS = {
    "run folder in use": (_held_by_a_live_process, 2,
                          (r"run: run folder in use by pid 4242 on host elsewhere since now \(\.lock is "
                          r"locked\); wait for that run to end or write into another folder")),
    "lock file of a dead process": (_left_by_a_dead_process, 0, ""),
    "holder killed with SIGKILL": (_holder_killed, 0, ""),
}


@pytest.mark.parametrize("case", list(LOCKS))
def test_run_folder_lock(case, tmp_path, capsys):
    make, status, message = LOCKS[case]
    run = tmp_path / "run"
    done = make(run)
    try:
        code, line = outcome(capsys, tiny_cfg(), run)
    finally:
        done()
    assert code == status, line
    if status:
        assert re.search(message, line), line
        assert not (run / FAILED_FILE).exists()  # the folder belongs to the other run
        assert not (run / "density.npz").exists()
    else:
        assert (run / "metrics.json").is_file() and not (run / ".lock").exists()


def test_second_train_py_into_a_folder_in_use_changes_nothing_there(tmp_path):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("the first run's config\n")
    fd = os.open(run / ".lock", os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        proc = subprocess.run([sys.executable, str(REPO / "train.py"), *TINY, f"hydra.run.dir={run}"],
                              capture_output=True, text=True, env=repo_env(), timeout=300, check=False)
    finally:
        os.close(fd)
    assert proc.returncode == 2, proc.stderr
    assert f"{ERROR}{run}: run folder in use" in proc.stderr and "Traceback" not in proc.stderr
    assert (run / ".hydra" / "config.yaml").read_text() == "the first run's config\n"
    assert sorted(p.name for p in run.iterdir()) == [".hydra", ".lock"]


# ---------------------------------------------------------------------------------------------
# family: no held-out view (every camera fitted), view names that are paths

NO_HOLDOUT = {
    "holdout=[]": lambda root: tiny_cfg("holdout=[]"),
    "scene=nerf naming none": lambda root: nerf_cfg(write_nerf(root)),
}


@pytest.mark.parametrize("case", list(NO_HOLDOUT))
def test_no_held_out_view_fits_every_camera_and_says_nothing_measured_it(case, tmp_path, capsys):
    """A capture that holds out nothing (``holdout=[]``, or a scene naming no default) is fitted
    to all its cameras; the summary says no camera measured the result and how to measure it."""
    cfg = NO_HOLDOUT[case](tmp_path / "capture")
    (tmp_path / "run").mkdir()
    code, line = outcome(capsys, cfg, tmp_path / "run")
    assert code == 0, line
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    cameras = json.loads((tmp_path / "run" / "cameras.json").read_text())["cameras"]
    assert metrics["heldout"] == {} and sorted(metrics["train"]) == sorted(c["name"] for c in cameras)
    said = summary_table(metrics)
    assert f"none: all {len(cameras)} cameras fitted" in said and "leave_one_out=true" in said


SLASHED = [f"./a/cam0{i}" for i in range(3)] + ["./b/cam00", "./b/cam01"]
VIEW_PATHS = {
    "held out 'b/cam01'": ("holdout=['b/cam01']", ["b_cam01.png"]),
    "held out 'a/cam00' and 'b/cam00'": ("holdout=['a/cam00','b/cam00']", ["a_cam00.png", "b_cam00.png"]),
}


@pytest.mark.parametrize("case", list(VIEW_PATHS))
def test_view_names_with_slashes_become_safe_file_names(case, tmp_path, capsys):
    holdout, files = VIEW_PATHS[case]
    root = write_nerf(tmp_path / "capture", SLASHED)
    code, line = outcome(capsys, nerf_cfg(root, holdout), tmp_path / "run")
    assert code == 0, line
    assert sorted(p.name for p in (tmp_path / "run" / "renders").iterdir()) == files
    cams = json.loads((tmp_path / "run" / "cameras.json").read_text())["cameras"]
    assert {c["name"] for c in cams} == {p[2:] for p in SLASHED}
    code, line = script_outcome(capsys, "render", [str(tmp_path / "run"), "--camera",
                                                   str(tmp_path / "run" / "cameras.json"), "--device", "cpu"])
    assert code == 0, line
    assert (tmp_path / "run" / "renders" / "camera_b_cam01.png").is_file()


# ---------------------------------------------------------------------------------------------
# family: options out of their range, refused before any work

OPTIONS = {
    "non-positive ray step": ("projector.step=0", r"projector\.step: got 0; projector\.step must be >= 0\.01"),
    "negative ray step": ("projector.step=-0.5", r"projector\.step: got -0\.5; projector\.step must be >= 0\.01"),
    "vanishing ray step": ("projector.step=1e-9", r"projector\.step: got 1e-09"),
    "zero iteration budget": ("solver.max_iters=0", r"solver\.max_iters: got 0; .* must be an integer >= 1"),
    "negative iteration budget": ("solver.max_iters=-5", r"solver\.max_iters: got -5"),
    "NaN tolerance": ("solver.tol=nan", r"solver\.tol: got nan; solver\.tol must be >= 0"),
    "negative hull margin": ("hull.margin_voxels=-1", r"hull\.margin_voxels: got -1; .* integer >= 0"),
    "negative threads": ("threads=-2", r"threads: got -2; threads must be an integer >= 1 or null"),
    "zero threads": ("threads=0", r"threads: got 0"),
    "negative checkpoint.every": ("checkpoint.every=-1", r"checkpoint\.every: got -1; .* integer >= 0"),
    "quoted number": ("solver.max_iters='100'",
                      (r"solver\.max_iters: got the string '100' \(quoted on the command line\?\); .* write "
                      r"solver\.max_iters=100 without quotes")),
    "quoted float": ("projector.step='0.5'", r"projector\.step: got the string '0\.5'"),
    "unknown silhouette.method": ("silhouette.method=canny",
                                  r"silhouette\.method: unknown method 'canny'; .* one of otsu, threshold"),
    "fractional cells": ("hull.margin_voxels=1.5", r"hull\.margin_voxels: got 1\.5"),
    "negative divergence factor": ("checkpoint.divergence_factor=-1", r"checkpoint\.divergence_factor: got -1"),
    "infinite time budget": ("solver.max_seconds=inf", r"solver\.max_seconds: got inf; .* > 0 or null"),
    "zero photometry rounds": ("photometry.rounds=0", r"photometry\.rounds: got 0"),
    "negative eval_every": ("log.eval_every=-1", r"log\.eval_every: got -1"),
    "boolean as a number": ("photometry.fit_gain=1", r"photometry\.fit_gain: got 1; .* true or false"),
    "unknown device": ("device=gpu", r"device: got 'gpu'; device must be auto, cpu, cuda or cuda:N"),
    "null budget for fista": ("solver.max_iters=null", r"solver\.max_iters: got None; solver fista needs"),
    "relax outside (0, 2)": ("solver=sart solver.relax=2", r"solver\.relax: got 2; .* > 0 and < 2"),
    "grid of two numbers": ("grid.resolution=[8,8]", r"grid\.resolution: got \[8, 8\]"),
    "bad export format": ("export.formats=[vtk]", r"export\.formats: got \['vtk'\]"),
    "negative scene frame": ("scene.frame=-1", r"scene\.frame: got -1"),
}


@pytest.mark.parametrize("case", list(OPTIONS))
def test_options_are_checked_before_any_work(case, tmp_path, capsys, monkeypatch):
    override, message = OPTIONS[case]
    cfg = tiny_cfg(*override.split())
    monkeypatch.setattr(pipeline, "load_scene", lambda *a: pytest.fail("the scene was loaded"))
    (tmp_path / "run").mkdir()
    code, line = outcome(capsys, cfg, tmp_path / "run")
    assert code == 2 and re.search(message, line), line
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [FAILED_FILE]


@pytest.mark.e2e
@pytest.mark.parametrize("case", [*OPTIONS, *LEAKS])
def test_train_py_says_a_refusal_in_one_line_and_nothing_else(case, tmp_path):
    """The tables above as a user meets them, through ``python train.py``: the one error line
    is all that is printed (no composed config, no log line before it; issue 38's regression),
    exit status 2, no run folder left."""
    if case in OPTIONS:
        args, message = [*TINY, *OPTIONS[case][0].split()], OPTIONS[case][1]
    else:
        make, holdout, message = LEAKS[case]
        root = make(tmp_path / "capture")
        args = ["scene=nerf", f"scene.root={root}", "grid.resolution=16", "solver.max_iters=10", "log.eval_every=0",
                holdout or "holdout=[cam04]"]
    line = refused_line([*args, f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert re.search(message, line), line
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------------------------
# family: write failures (disk full, read-only), nothing lost

def fill(folder: Path) -> None:
    """Write into ``folder`` until its file system is full."""
    with open(folder / "filler", "wb") as f, contextlib.suppress(OSError):
        while True:
            f.write(b"\0" * 65536)
            f.flush()
    with contextlib.suppress(OSError):
        (folder / "filler2").write_bytes(b"\0" * 4096)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("finished") / "run"
    reconstruct(tiny_cfg(), run)
    (run / ".hydra").mkdir()
    OmegaConf.save(tiny_cfg(), run / ".hydra" / "config.yaml")
    return run


def _copy_run(finished_run, folder) -> Path:
    run = folder / "run"
    shutil.copytree(finished_run, run)
    return run


def _snapshot(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


WRITE_FAILURES = {
    "evaluate.py on a read-only file system": ("ro", "evaluate", [], r"cannot write \(errno 30 EROFS"),
    "export.py on a read-only file system": ("ro", "export", ["--format", "raw"],
                                              r"cannot write \(errno 30 EROFS"),
    "evaluate.py on a full file system": ("full", "evaluate", [], r"cannot write \(errno 28 ENOSPC"),
    "export.py on a full file system": ("full", "export", ["--format", "raw"], r"cannot write \(errno 28 ENOSPC"),
}


@pytest.mark.parametrize("case", list(WRITE_FAILURES))
def test_write_failures_of_the_scripts(case, tmp_path, capsys, finished_run):
    kind, name, args, message = WRITE_FAILURES[case]
    with tmpfs(tmp_path / "fs") as fs:
        run = _copy_run(finished_run, fs)
        if kind == "ro":
            subprocess.run(["mount", "-o", "remount,ro", str(fs)], check=True)
        else:
            fill(fs)
        before = _snapshot(run)
        argv = [str(run), *args] + (["--device", "cpu", "--no-native"] if name == "evaluate" else [])
        code, line = script_outcome(capsys, name, argv)
        assert code == 2 and re.search(f"{run}/.*{message}", line), line
        assert _snapshot(run) == before  # nothing lost, nothing half-written


def _full_checkpoint(monkeypatch):
    def no_space(*args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:783] . PytorchStreamWriter failed "
                           "writing file data/0: file write failed")

    monkeypatch.setattr(checkpoint.torch, "save", no_space)
    full = os.statvfs_result((4096, 4096, 100, 0, 0, 100, 0, 0, 0, 255))
    monkeypatch.setattr("flamerecon.outputs.atomic.os.statvfs", lambda path: full)


def _full_density(monkeypatch):
    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("flamerecon.outputs.atomic.np.savez", no_space)


def _read_only_run_folder(monkeypatch):
    real_open = os.open

    def refuse(path, flags, *args, **kwargs):
        if str(path).endswith(".lock"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr("flamerecon.run.lock.os.open", refuse)


RUN_WRITE_FAILURES = {
    "disk full at a checkpoint (torch.save's RuntimeError)": (
        _full_checkpoint, ["checkpoint.every=5", "solver.max_iters=20", "solver.tol=0"],
        r"run/checkpoint\.pt: cannot write \(errno 28 ENOSPC: No space left on device\); free space"),
    "disk full at density.npz": (_full_density, [],
                                 r"run/density\.npz: cannot write \(errno 28 ENOSPC"),
    "read-only run folder": (_read_only_run_folder, [], r"run/\.lock: cannot write \(errno 30 EROFS"),
}


@pytest.mark.parametrize("case", list(RUN_WRITE_FAILURES))
def test_write_failures_during_the_run(case, tmp_path, capsys, monkeypatch):
    patch, overrides, message = RUN_WRITE_FAILURES[case]
    patch(monkeypatch)
    code, line = outcome(capsys, tiny_cfg(*overrides), tmp_path / "run")
    assert code == 2 and re.search(message, line), line
    assert not list((tmp_path / "run").glob(".*.tmp*"))  # no half-written temporaries left


def test_train_py_into_a_read_only_file_system(tmp_path):
    with tmpfs(tmp_path / "fs") as fs:
        subprocess.run(["mount", "-o", "remount,ro", str(fs)], check=True)
        proc = subprocess.run([sys.executable, str(REPO / "train.py"), *TINY, f"hydra.run.dir={fs}/run"],
                              capture_output=True, text=True, env=repo_env(), timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith(ERROR)]
    assert errors == [(f"{ERROR}{fs}/run: cannot write (errno 30 EROFS: Read-only file system); "
                      "the file system is read-only: write elsewhere")], proc.stderr
    assert "Traceback" not in proc.stderr


# ---------------------------------------------------------------------------------------------
# family: FAILED where the README promises it, never in a finished run's folder

def _bug_after_the_folder_exists(monkeypatch, tmp_path):
    def boom(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr("flamerecon.fit.reconstruct.build", boom)
    return tiny_cfg(), tmp_path / "run", None


def _resume_a_finished_run(monkeypatch, tmp_path):
    run = tmp_path / "finished"
    reconstruct(tiny_cfg(), run)
    (run / ".hydra").mkdir()
    OmegaConf.save(tiny_cfg(), run / ".hydra" / "config.yaml")
    return OmegaConf.create({"resume": str(run)}), tmp_path / "run", run


FAILED = {
    "unexpected exception in a single run": (
        _bug_after_the_folder_exists, 2,
        r"run: unexpected ZeroDivisionError: a bug; the traceback is in .*run/FAILED", "Traceback"),
    "resume= on a finished run": (
        _resume_a_finished_run, 2, r"checkpoint\.pt: no checkpoint; the run has finished", "no checkpoint"),
}


@pytest.mark.parametrize("case", list(FAILED))
def test_failed_marker(case, tmp_path, capsys, monkeypatch):
    make, status, message, recorded = FAILED[case]
    cfg, own, good = make(monkeypatch, tmp_path)
    own.mkdir()  # as Hydra makes it
    before = None if good is None else _snapshot(good)
    code, line = outcome(capsys, cfg, own)
    assert code == status and re.search(message, line), line
    assert recorded in (own / FAILED_FILE).read_text()
    if good is not None:
        assert _snapshot(good) == before and not (good / FAILED_FILE).exists()


# ---------------------------------------------------------------------------------------------
# family: resume=RUN_DIR with other overrides

SOLVE = ["grid.resolution=12", "solver.tol=0", "checkpoint.every=10", "solver.max_iters=30",
         "solver.check_every=5"]


@pytest.fixture(scope="module")
def interrupted_run(tmp_path_factory):
    """A run stopped by SIGINT at iteration 15 (checkpoint.pt holds its state)."""
    run = tmp_path_factory.mktemp("interrupted") / "run"
    with pytest.raises(Interrupted):
        reconstruct(tiny_cfg(*SOLVE), run, watch=interrupt_at(15))
    (run / ".hydra").mkdir()
    OmegaConf.save(tiny_cfg(*SOLVE), run / ".hydra" / "config.yaml")
    return run


RESUMES = {
    "more iterations": (["solver.max_iters=40"], 0, "", 40),
    "a time budget": (["solver.max_seconds=600"], 0, "", 30),
    "checkpoints more often": (["checkpoint.every=5"], 0, "", 30),
    "the same value again": (["solver.max_iters=30", "grid.resolution=12"], 0, "", 30),
    "another grid": (["grid.resolution=14"], 2,
                     (r"resume=.*run: grid\.resolution=14 would change the problem the run was started with; "
                     r"resume takes only solver\.max_iters, solver\.max_seconds, checkpoint\.every"), None),
    "another solver and frame": (["solver=adam", "scene.frame=3", "solver.max_iters=40"], 2,
                                 r"resume=.*: solver=adam, scene\.frame=3 would change the problem", None),
}


@pytest.mark.parametrize("case", list(RESUMES))
def test_resume_with_overrides(case, tmp_path, capsys, interrupted_run):
    overrides, status, message, iterations = RESUMES[case]
    run = tmp_path / "run"
    shutil.copytree(interrupted_run, run)
    now = tiny_cfg(*SOLVE, *overrides, f"resume={run}")
    before = _snapshot(run)
    (tmp_path / "command").mkdir()  # this command's own run folder, as Hydra makes it
    code, line = outcome(capsys, now, tmp_path / "command", overrides=[*overrides, f"resume={run}"])
    assert code == status, line
    if status:
        assert re.search(message, line), line
        assert _snapshot(run) == before  # refused: the interrupted run is left as it was
        assert (tmp_path / "command" / FAILED_FILE).is_file()
    else:
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["solver"]["iterations"] == iterations
        assert not (run / "checkpoint.pt").exists() and not (run / FAILED_FILE).exists()


# ---------------------------------------------------------------------------------------------
# family: symbolic link loops

def _loop(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(path.name, path)


def _camera_folder_loop(tmp_path):
    _loop(tmp_path / "train00")
    return lambda: read_camera_frame(tmp_path, "train00.mp4", 0)


def _nerf_image_loop(tmp_path):
    root = write_nerf(tmp_path / "capture")
    (root / "images" / "cam02.png").unlink()
    _loop(root / "images" / "cam02.png")
    return lambda: load_scene(OmegaConf.create({"name": "nerf", "root": str(root)}))


def _root_loop(tmp_path):
    _loop(tmp_path / "data")
    return lambda: load_scene(OmegaConf.create({"name": "nerf", "root": str(tmp_path / "data")}))


LOOPS = {
    "camera folder": (_camera_folder_loop, (r"train00: a symbolic link loop \(following it leads back to "
                                           r"itself\); point the link at the real video")),
    "NeRF image": (_nerf_image_loop, r"images/cam02\.png: a symbolic link loop"),
    "scene.root": (_root_loop, r"config: scene\.root: '.*data' is a symbolic link loop"),
}


@pytest.mark.parametrize("case", list(LOOPS))
def test_symbolic_link_loops_are_named(case, tmp_path):
    make, message = LOOPS[case]
    with pytest.raises(SceneError, match=message) as info:
        make(tmp_path)()
    assert info.value.exit_code == 2


# ---------------------------------------------------------------------------------------------
# family: every script ends the same way (one line, exit status 2)

def _other_scenes_density(run: Path, channels: int = 3, cells: int = 16) -> None:
    scene = tiny_synthetic()
    save_density(run / "density.npz", np.zeros((channels, cells, cells, cells), np.float32),
                 scene.bbox_min, scene.bbox_max, ["cam00"])


def _evaluate_channels(tmp_path, finished_run):
    run = _copy_run(finished_run, tmp_path)
    _other_scenes_density(run, channels=1)
    return [str(run), "--device", "cpu"]


def _evaluate_grid(tmp_path, finished_run):
    run = _copy_run(finished_run, tmp_path)
    _other_scenes_density(run, cells=12)
    return [str(run), "--device", "cpu"]


def _evaluate_views(tmp_path, finished_run):
    run = _copy_run(finished_run, tmp_path)
    scene = tiny_synthetic()
    with np.load(run / "density.npz") as f:
        density = f["density"]
    save_density(run / "density.npz", density, scene.bbox_min, scene.bbox_max, ["r_0", "r_1"])
    return [str(run), "--device", "cpu"]


def _plain(*argv):
    return lambda tmp_path, finished_run: [a.replace("RUN", str(finished_run)) for a in argv]


NO_CUDA = [pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")]
SCRIPTS = [  # (case, script, argv maker, message)
    ("evaluate: density of a gray scene", "evaluate", _evaluate_channels,
     (r"density\.npz: field 'density' has 1 channel\(s\) but scene 'synthetic' of .*config\.yaml has 3; "
     r"the density was made for another scene")),
    ("evaluate: density on another grid", "evaluate", _evaluate_grid,
     r"density\.npz: field 'density' is a 12x12x12 grid .* but .*config\.yaml gives \d+x16x\d+ cells"),
    ("evaluate: density fitted to other views", "evaluate", _evaluate_views,
     r"density\.npz: field 'views': .*\['r_0', 'r_1'\]"),
    ("evaluate: not a run folder", "evaluate", _plain("/nonexistent/run"), r"config\.yaml: not found"),
    ("render: --device cuda without a GPU", "render", _plain("RUN", "--device", "cuda"),
     r"--device: 'cuda' was asked for but torch sees no CUDA device; use auto or cpu"),
    ("evaluate: --device cuda without a GPU", "evaluate", _plain("RUN", "--device", "cuda"),
     r"--device: 'cuda' was asked for"),
    ("render: bad orbit", "render", _plain("RUN", "--camera", "orbit:30"), r"orbit:ANGLE,ELEV"),
    ("render: zero width", "render", _plain("RUN", "--width", "0"), r"--width: got 0; give a number >= 1"),
    ("benchmark: --grid 0", "benchmark", _plain("--grid", "0"), r"--grid: 0 is not a grid size; give N >= 2"),
    ("benchmark: --budget 0", "benchmark", _plain("--budget", "0"), r"--budget: got 0\.0"),
    ("benchmark: unknown solver", "benchmark", _plain("--solvers", "nope"),
     r"--solvers: unknown solver 'nope'"),
    ("export: no density", "export", _plain("/nonexistent"), r"/nonexistent.*density\.npz"),
    ("export: unknown format (argparse)", "export", _plain("RUN", "--format", "vtu"),
     r"argument --format: invalid choice: 'vtu'.*; see .* --help"),
    ("assemble: no sweep folder", "assemble", _plain("/nonexistent"), r"/nonexistent: no"),
    ("leave_one_out: unknown view", "leave_one_out", _plain(*TINY, "--views", "nope"),
     r"leave-one-out: unknown view 'nope'"),
    ("cross_validate: unknown key", "cross_validate", _plain("no_such_key=1"), r"config: .*no_such_key"),
]


@pytest.mark.parametrize(("name", "make", "message"), [
    pytest.param(*case[1:], id=case[0], marks=NO_CUDA if "cuda" in case[0] else []) for case in SCRIPTS])
def test_scripts_end_with_one_line_and_status_2(name, make, message, tmp_path, capsys, finished_run,
                                                monkeypatch):
    monkeypatch.chdir(tmp_path)  # default output folders land here
    code, line = script_outcome(capsys, name, make(tmp_path, finished_run))
    assert code == 2 and re.search(message, line), line


# ---------------------------------------------------------------------------------------------
# family: what torch or kornia would have said, said with the field's name

def _init_from_a_gray_run(tmp_path, capsys):
    gray = tmp_path / "gray"
    gray.mkdir()
    _other_scenes_density(gray, channels=1)
    (tmp_path / "run").mkdir()
    return outcome(capsys, tiny_cfg(f"init={gray}"), tmp_path / "run")


def _render_camera_without_focal_length(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    _other_scenes_density(run)
    cam = {"name": "c", "K": np.zeros((3, 3)).tolist(), "world_to_camera": np.eye(4).tolist(),
           "width": 8, "height": 8}
    (tmp_path / "cams.json").write_text(json.dumps([cam]))
    return script_outcome(capsys, "render", [str(run), "--camera", str(tmp_path / "cams.json")])


INTERNALS = {
    "init= from a run of other channels": (_init_from_a_gray_run,
                                           r"init: .*gray holds 1 channel\(s\), this run's images 3"),
    "render: camera file with K = 0": (_render_camera_without_focal_length,
                                       r"cams\.json: camera c: K: focal lengths must be positive"),
}


@pytest.mark.parametrize("case", list(INTERNALS))
def test_library_errors_become_field_named(case, tmp_path, capsys):
    make, message = INTERNALS[case]
    code, line = make(tmp_path, capsys)
    assert code == 2 and re.search(message, line), line


def test_file_stems_stay_unique():
    from flamerecon.outputs.names import file_stems

    assert file_stems(["train/r_0", "test/r_0", "train_r_0", "../x", ".hidden"]) == [
        "train_r_0", "test_r_0", "train_r_0-2", "_x", "hidden"]


def test_leave_one_out_checks_the_options_first(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("flamerecon.run.leave_one_out.load_scene", lambda *a: pytest.fail("loaded"))
    code, line = script_outcome(capsys, "leave_one_out", [*TINY, "projector.step=0", "--out",
                                                         str(tmp_path / "loo")])
    assert code == 2 and line.startswith("projector.step: got 0"), line


def _no_vtk():
    raise ImportError("writing .vti needs the 'vtk' package; install the optional exporters")


BEFORE_THE_SOLVE = {  # cases that used to fail only after the work, or with a reader's traceback
    "export=vti without vtk": (["export=vti"], r"export\.formats: writing \.vti needs the 'vtk' package"),
    "init= of a folder without density": (["init=/nonexistent/run"],
                                          r"init: /nonexistent/run.*no density file.*give a finished run"),
    "solver=lars on more hull voxels than solver.max_voxels": (
        ["solver=lars", "solver.max_voxels=10"], r"^solver=lars: the problem has \d+ unknowns .* solver\.max_voxels=10"),
    "a box that misses the flame (an empty hull)": (
        ["grid.bbox=[[0.5,0.5,0.5],[0.6,0.6,0.6]]"],
        (r"the visual hull on the \d+x\d+x\d+ grid is empty; .*check that the box \[0\.5, 0\.5, 0\.5\]"
         r"\.\.\[0\.6, 0\.6, 0\.6\] \(grid\.bbox\) holds the flame")),
}


@pytest.mark.parametrize("case", list(BEFORE_THE_SOLVE))
def test_refused_before_the_work(case, tmp_path, capsys, monkeypatch):
    overrides, message = BEFORE_THE_SOLVE[case]
    monkeypatch.setattr("flamerecon.outputs.export._vtk", _no_vtk)
    monkeypatch.setattr(RunHook, "solve", lambda *a, **k: pytest.fail("solved"))
    monkeypatch.setattr("flamerecon.fit.reconstruct.build", lambda *a, **k: pytest.fail("built an operator"))
    (tmp_path / "run").mkdir()
    code, line = outcome(capsys, tiny_cfg(*overrides), tmp_path / "run")
    assert code == 2 and re.search(message, line), line


def test_lars_solves_a_small_problem_end_to_end(tmp_path, capsys):
    """LARS knows no iteration count ahead (solver.max_iters: null): the run's progress takes it
    as unknown, and the exact path is written like any solver's result."""
    (tmp_path / "run").mkdir()
    code, line = outcome(capsys, tiny_cfg("solver=lars", "solver.max_voxels=5000", "grid.resolution=8"),
                      tmp_path / "run")
    assert (code, line) == (0, "")
    assert (tmp_path / "run" / "density.npz").is_file()
