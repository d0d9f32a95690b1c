"""A command refused before any work says why in one line on stderr, prints nothing else (the
composed config comes only once the checks have passed), exits with status 2 and leaves no
folder behind: no run folder under outputs/, no sweep folder under multirun/.

Hydra's own refusals become flamerecon's: a misspelt key or config-group option gets the
closest one ("did you mean"), a launcher of the missing ``[sweep]`` extra the pip command."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.helpers import FAST, REPO, SMALLER, TINY, repo_env

#: hides the [sweep] extra's launchers from Hydra, as in an install without it
NO_SWEEP = ("import sys; sys.modules['hydra_plugins.hydra_joblib_launcher'] = None; "
            "sys.modules['hydra_plugins.hydra_submitit_launcher'] = None; ")

# (command line after train.py, without the [sweep] extra?, the one stderr line (a regex))
REFUSED = {
    "misspelt key": (["solver.l11=3"], False, r"solver\.l11: no such option; did you mean solver\.l1\?"),
    "misspelt top-level key": (["sed=1"], False, r"sed: no such option; did you mean seed\?"),
    "misspelt group": (["solvr=fista"], False, r"solvr: no such option; did you mean solver\?"),
    "misspelt group option": (["solver=fistaa"], False, r"solver=fistaa: no such option; did you mean fista\?"),
    "misspelt key of a scene": (["scene=scalarflow", "scene.rot=1"], False,
                                r"scene\.rot: no such option; did you mean scene\.root\?"),
    "misspelt key in a sweep": (["-m", "solver.l11=1,2"], False, r"solver\.l11: no such option; did you mean solver\.l1\?"),
    "override syntax": (["solver.l1=[1"], False, r"config: no viable alternative at input '\[1'.*--cfg job"),
    "joblib without the extra": (["-m", "hydra/launcher=joblib", "seed=1,2"], True,
                                 r"hydra/launcher=joblib: that launcher is not installed; pip install -e \"\.\[sweep\]\""),
    "slurm without the extra": (["-m", "hydra/launcher=slurm", "seed=1,2"], True,
                                r"hydra/launcher=slurm: that launcher is not installed; pip install -e \"\.\[sweep\]\""),
    "option out of range": (["solver.l1=-1"], False, r"solver\.l1: got -1; solver\.l1 must be >= 0"),
    "unknown held-out view": ([*TINY, *SMALLER, *FAST, "holdout=[cam99]"], False, r"holdout: unknown view 'cam99'"),
    "missing data folder": (["scene=scalarflow", "scene.root=/nonexistent"], False, r"/nonexistent/info\.json: .*not found"),
    # found once the scene is loaded, still before any work: no config, no log line before it (issue 38)
    "unknown held-out view, the default scene": (["holdout=[no_such_camera]"], False,
                                                 r"holdout: unknown view 'no_such_camera'; scene 'synthetic' has views"),
    "held-out view index out of range": ([*TINY, *SMALLER, "holdout=[7]"], False, r"holdout: view index 7 is out of range"),
    "every view held out": ([*TINY, *SMALLER, "holdout=[0,1,2,3,4]"], False, r"holds out every view"),
    "silhouette threshold above every pixel": ([*TINY, *SMALLER, "silhouette.threshold=0.99"], False,
                                               r"silhouette\.threshold=0\.99 is above every pixel of view 'cam00'"),
    "confidence with one training camera": ([*TINY, *SMALLER, "holdout=[1,2,3,4]", "uncertainty.enabled=true"], False,
                                            r"uncertainty\.enabled: the confidence needs at least two training cameras"),
    "a calibration file that is not there": ([*TINY, *SMALLER, "calibration.file=/nonexistent/cameras.json"], False,
                                             r"calibration\.file: /nonexistent/cameras\.json does not exist"),
    "a box no camera sees": ([*TINY, *SMALLER, "grid.bbox=[[100,100,100],[101,101,101]]"], False,
                             r"view 'cam00': the camera does not see the box"),
}


@pytest.mark.e2e
@pytest.mark.parametrize("case", list(REFUSED))
def test_a_refused_command_says_why_in_one_line_and_leaves_no_folder(case, tmp_path):
    args, no_sweep, line = REFUSED[case]
    if no_sweep:
        command = [sys.executable, "-W", "ignore", "-c", NO_SWEEP + f"sys.argv = ['train.py', *{args!r}]; "
                   "from flamerecon.run.train import main; main()"]
    else:
        command = [sys.executable, str(REPO / "train.py"), *args]
    proc = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, env=repo_env(),
                          timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == "" and len(proc.stderr.splitlines()) == 1, proc.stdout + proc.stderr  # nothing else printed
    assert proc.stderr.startswith("flamerecon: error: ")
    assert re.search(line, proc.stderr), proc.stderr
    assert list(tmp_path.iterdir()) == []  # no outputs/<date>/<time>, no multirun/<date>/<time>


def test_a_refusal_keeps_a_folder_that_held_something_before(tmp_path):
    """Only folders the command made go: a run folder named on the command line that already
    holds files (taken with overwrite=true: it is not empty) keeps them, and the FAILED file
    that says why."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine\n")
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), "solver.l1=-1", "overwrite=true",
                           f"hydra.run.dir={run}"],
                          cwd=tmp_path, capture_output=True, text=True, env=repo_env(), timeout=300, check=False)
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert (run / "notes.txt").read_text() == "mine\n"
    assert "solver.l1: got -1" in (run / "FAILED").read_text()
