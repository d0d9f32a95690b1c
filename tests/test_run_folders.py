"""Run folders (issue 33): a folder that holds a previous run (or anything else) is refused
unless ``overwrite=true``, which removes that run's files and nothing else; ``resume=RUN`` runs
in RUN itself (no stray ``outputs/DATE/TIME``, the run's ``.hydra/`` kept); nothing is written
through a symbolic link out of the run folder. One table over the Hydra callback that decides
before any work, then the writers and the command line end to end."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.errors import OutputError
from flamerecon.outputs.atomic import make_subfolder
from flamerecon.run.lock import LOCK_FILE
from flamerecon.run.runner import LockRunFolder
from tests.helpers import FAST, REPO, TINY, repo_env

ERROR = "flamerecon: error: "


def hydra_config(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides), return_hydra_config=True)


def save_config(folder: Path) -> None:
    """``.hydra/config.yaml`` as Hydra writes it for the tiny config."""
    (folder / ".hydra").mkdir(parents=True)
    OmegaConf.save(hydra_config(*TINY), folder / ".hydra" / "config.yaml")


def finished(folder: Path) -> Path:
    """A folder as a finished run leaves it (its files' contents do not matter here)."""
    save_config(folder)
    for name in ("density.npz", "metrics.json", "cameras.json", "train.log", "events.out.tfevents.1.vm.1.0"):
        (folder / name).write_text("old run")
    (folder / "renders").mkdir()
    (folder / "renders" / "cam04.png").write_text("old render")
    return folder


def interrupted(folder: Path) -> Path:
    save_config(folder)
    (folder / "checkpoint.pt").write_text("state")
    return folder


def user_files(folder: Path) -> Path:
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    return folder


def linked(make, name: str = "renders"):
    def build(folder: Path) -> Path:
        make(folder)
        elsewhere = folder.parent / "elsewhere"
        elsewhere.mkdir()
        (elsewhere / "keep.png").write_text("not ours")
        target = folder / name
        if target.is_dir():
            for p in target.iterdir():
                p.unlink()
            target.rmdir()
        target.symlink_to(elsewhere)
        return folder
    return build


def nothing(folder: Path) -> Path:
    return folder


def empty(folder: Path) -> Path:
    folder.mkdir()
    return folder


# case: (make the folder, overrides, exit status (0: taken), message, what must be there after)
CASES = {
    "a new folder": (nothing, [], 0, "", []),
    "an empty folder": (empty, [], 0, "", []),
    "a finished run's folder": (finished, [], 2, (r"holds a previous run \(\.hydra, cameras\.json, density\.npz, "
                                r"events.*\); flamerecon does not write over it: .*hydra\.run\.dir=.*overwrite=true"),
                                ["density.npz", "renders/cam04.png"]),
    "an interrupted run's folder": (interrupted, [], 2, (r"holds a previous run .*continue it with resume=.*run, or "
                                    r"replace it with overwrite=true"), ["checkpoint.pt"]),
    "a folder of the user's files": (user_files, [], 2, (r"run: is not empty \(notes\.txt\); write the run into a new "
                                     r"or empty folder .*overwrite=true"), ["notes.txt"]),
    "overwrite=true on a finished run": (finished, ["overwrite=true"], 0, "", []),
    "overwrite=true keeps the user's files": (user_files, ["overwrite=true"], 0, "", ["notes.txt"]),
    "overwrite=true removes a link, never what it points to": (
        linked(finished), ["overwrite=true"], 0, "", ["../elsewhere/keep.png"]),
    "resume= where renders/ is a link": (
        linked(interrupted), ["resume={run}"], 2, (r"run/renders: is a symbolic link \(to .*elsewhere\); flamerecon "
        r"writes only inside the run folder"), ["../elsewhere/keep.png", "checkpoint.pt"]),
    "resume= where train.log is a link": (
        linked(interrupted, "train.log"), ["resume={run}"], 2, r"run/train\.log: is a symbolic link", []),
    "resume= of a folder that is no run": (user_files, ["resume={run}"], 2,
                                           (r"resume=.*run: .*run/\.hydra/config\.yaml not found; is .* a flamerecon "
                                           r"run folder\?"), ["notes.txt"]),
    "resume= of an interrupted run": (interrupted, ["resume={run}"], 0, "", ["checkpoint.pt"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_run_folder_is_checked_before_any_work(case, tmp_path, capsys):
    make, overrides, status, message, kept = CASES[case]
    run = make(tmp_path / "run")
    config = hydra_config(*TINY, f"hydra.run.dir={tmp_path / 'hydra-default'}",
                          *(o.format(run=run) for o in overrides),
                          *([] if any(o.startswith("resume=") for o in overrides) else [f"hydra.run.dir={run}"]))
    callback = LockRunFolder()
    try:
        callback.on_run_start(config)
        code = 0
    except SystemExit as stop:
        code = stop.code
    finally:
        callback._give_back()
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(ERROR)]
    assert code == status, err
    if status:
        assert len(lines) == 1 and re.search(message, lines[0]), lines
    else:
        assert not lines, lines
        assert Path(config.hydra.run.dir) == run  # resume= runs in the resumed folder
        if "overwrite=true" in overrides:
            assert not [p for p in run.iterdir() if p.name not in ("notes.txt", LOCK_FILE)], list(run.iterdir())
        if any(o.startswith("resume=") for o in overrides):
            assert config.hydra.output_subdir is None  # the run's own .hydra/ is kept
    for name in kept:
        assert (run / name).exists(), name
    assert not (tmp_path / "hydra-default").exists()  # no stray folder


def test_a_sweep_folder_is_refused_when_not_empty_and_cleared_with_overwrite(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    finished(sweep / "0")
    (sweep / "multirun.yaml").write_text("old")
    config = hydra_config(*TINY, f"hydra.sweep.dir={sweep}")
    with pytest.raises(SystemExit) as stop:
        LockRunFolder().on_multirun_start(config)
    assert stop.value.code == 2 and "holds a previous sweep (0, multirun.yaml)" in capsys.readouterr().err
    callback = LockRunFolder()
    callback.on_multirun_start(hydra_config(*TINY, f"hydra.sweep.dir={sweep}", "overwrite=true"))
    callback._give_back()
    assert [p.name for p in sweep.iterdir()] in ([], [LOCK_FILE])


def test_writers_refuse_a_linked_subfolder(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "renders").symlink_to(elsewhere)
    with pytest.raises(OutputError, match=r"run/renders: is a symbolic link .*writes only inside the run folder"):
        make_subfolder(tmp_path / "run", "renders")
    (tmp_path / "run" / "frames").write_text("a file")
    with pytest.raises(OutputError, match=r"run/frames: is a file where flamerecon writes a folder"):
        make_subfolder(tmp_path / "run", "frames")
    assert make_subfolder(tmp_path / "run", "new").is_dir() and not list(elsewhere.iterdir())


@pytest.mark.slow
@pytest.mark.e2e
def test_evaluate_never_writes_through_a_linked_renders_folder(tmp_path, capsys):
    from tests.test_bad_input import script

    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "train.py", *TINY, *FAST, f"hydra.run.dir={run}"], cwd=REPO,
                          env=repo_env(), capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "cam04.png").write_text("someone else's file")
    for p in (run / "renders").iterdir():
        p.unlink()
    (run / "renders").rmdir()
    (run / "renders").symlink_to(elsewhere)
    before = (run / "metrics.json").read_text()
    assert script("evaluate").main([str(run), "--device", "cpu", "--no-native"]) == 2
    assert "renders: is a symbolic link" in capsys.readouterr().err
    assert (elsewhere / "cam04.png").read_text() == "someone else's file"
    assert json.loads((run / "metrics.json").read_text()) == json.loads(before)


@pytest.mark.slow
@pytest.mark.e2e
def test_the_command_line_refuses_a_finished_run_and_resumes_in_place(tmp_path):
    """End to end: a second run into a finished run's folder is refused (exit 2, the folder
    unchanged), ``overwrite=true`` replaces it (one run's TensorBoard files, not two), and a
    resume started elsewhere leaves no folder in its working directory."""
    run, cwd = tmp_path / "run", tmp_path / "cwd"
    cwd.mkdir()

    def train(*overrides: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(REPO / "train.py"), *TINY, *FAST, *overrides], cwd=cwd,
                              env=repo_env(), capture_output=True, text=True, timeout=300, check=False)

    assert train(f"hydra.run.dir={run}").returncode == 0
    events = sorted(p.name for p in run.glob("events.out.tfevents.*"))
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir()}
    again = train(f"hydra.run.dir={run}")
    assert again.returncode == 2 and "holds a previous run" in again.stderr
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir()} == before
    assert train(f"hydra.run.dir={run}", "overwrite=true").returncode == 0
    now = sorted(p.name for p in run.glob("events.out.tfevents.*"))
    assert len(now) == len(events) and not set(now) & set(events)  # the new run's only
    finished_resume = train(f"resume={run}")
    assert finished_resume.returncode == 2 and "the run has finished" in finished_resume.stderr
    assert not (run / "FAILED").exists() and not list(cwd.iterdir())  # no outputs/DATE/TIME
