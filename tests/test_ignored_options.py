"""An option is never ignored, nor chosen by a rule nobody sees (issue 38, family 5): an option
the command line gives wins over a preset's rule that would override it, and is said where the
rule still holds; an option that does nothing in the combination is refused before any work.

One table of runs (``run_task`` as ``train.py`` runs it: the overrides the command line gives,
the options a scene preset sets, the exit status, the words of the one line, the iterations of
the run's own level), then ``calibration.frames=auto`` on a capture whose frame numbers have a
gap."""

from __future__ import annotations

import json
import logging
import re

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.fit.refine_cameras import auto_frames
from flamerecon.geometry.cameras import K_of
from flamerecon.run.hook import RunHook
from flamerecon.run.runner import run_task
from flamerecon.scenes import capture_frames, load_scene
from tests.helpers import REPO, tiny_config, tiny_synthetic
from tests.helpers.views import write_png

ERROR = "flamerecon: error: "
#: a ladder rung that runs on the tiny synthetic scene (its own downscale is 1)
RUNG = ["ladder.rungs=[[2,8]]", "solver.tol=0", "log.eval_every=0"]
#: a short weight selection (a preset's select.auto)
SELECTION = ["select.folds=2", "select.iterations=5"]

# (what the command line gives, what a preset set (not given), status, words of the line or of the
# output, iterations on the run's own level or None)
RUNS = {
    "solver.max_iters given, a preset's ladder.final_iterations": (
        [*RUNG, "solver.max_iters=3"], ["ladder.final_iterations=12"], 0,
        r"ladder\.final_iterations: the preset's 12 set to null: solver\.max_iters=3, given on the command line", 3),
    "the preset's ladder.final_iterations alone: the rule holds, said": (
        [*RUNG], ["solver.max_iters=5", "ladder.final_iterations=12"], 0,
        (r"ladder\.final_iterations=12: the run's own level solves 12 iterations after the ladder's rungs, not "
        r"solver\.max_iters=5"), 12),
    "solver.max_iters given, a preset's ladder.iterations": (
        [*RUNG, "solver.max_iters=3"], ["ladder.iterations=7"], 0,
        r"ladder\.iterations: the preset's 7 set to null: solver\.max_iters=3, given on the command line, wins", 3),
    "both given: ladder.final_iterations holds on the run's own level": (
        [*RUNG, "solver.max_iters=3", "ladder.final_iterations=7"], [], 0, r"ladder\.final_iterations=7: ", 7),
    "solver.l1_rel given, a preset's select.auto": (
        ["solver.l1_rel=0.05", "log.eval_every=0"], ["select.auto=true", *SELECTION], 0,
        r"select\.auto: the preset's true set to false: solver\.l1_rel=0\.05, given on the command line, wins", 10),
    "a preset's select.auto alone: the weights chosen, said": (
        ["log.eval_every=0"], ["select.auto=true", *SELECTION], 0, r"held-out PSNR", 10),
    "select.auto and solver.l1_rel both given": (
        ["select.auto=true", "solver.l1_rel=0.05"], [], 2,
        (r"solver\.l1_rel: given with select\.auto=true, which chooses the solver's weights from select\.candidates, "
         r"so solver\.l1_rel would not be used; give one of them"), None),
    "holdout and scene.holdout both given": (
        ["holdout=[cam01]", "++scene.holdout=[cam02]"], [], 2,
        (r"scene\.holdout: given with holdout=\['cam01'\], which holds out its own views in place of the scene's, so "
        r"scene\.holdout would not be used; give one of them"), None),
    "calibration.file and calibration.refine both given": (
        ["calibration.file=cameras.json", "calibration.refine=pose"], [], 2,
        (r"calibration\.refine: given with calibration\.file=cameras\.json, which reads the cameras from the file in "
        r"place of a camera fit, so calibration\.refine would not be used"), None),
    "uncertainty.scale without uncertainty.enabled": (
        ["uncertainty.scale=5"], [], 2,
        (r"uncertainty\.scale: got 5, which does nothing without the confidence \(uncertainty\.enabled=true\); set "
        r"that too or drop uncertainty\.scale from the command line"), None),
    "a preset's uncertainty.scale without uncertainty.enabled": (["log.eval_every=0"], ["uncertainty.scale=1.82"], 0,
                                                                 r"held-out PSNR", 10),
    "ladder.final_iterations given, no rung runs": (
        ["ladder.final_iterations=50"], [], 2, r"ladder\.final_iterations: got 50, which does nothing without a rung",
        None),
    "a rung finer than the run's own grid": (
        ["ladder.rungs=[[2,32]]"], [], 2,
        (r"ladder\.rungs: rung \[2, 32\] \(\d+x32x\d+ cells\) is finer than the run's own grid \(\d+x16x\d+ cells, "
        r"grid\.resolution\); .* give grid\.resolution at least 32, or drop the rung"), None),
    "a rung as fine as the run's own grid (coarser images)": ([*RUNG[1:], "ladder.rungs=[[2,16]]"], [], 0,
                                                              r"held-out PSNR", 10),
    "the confidence with one training camera": (
        ["uncertainty.enabled=true", "holdout=[1,2,3,4]"], [], 2,
        (r"uncertainty\.enabled: the confidence needs at least two training cameras .* this run trains on 1; hold "
        r"out fewer cameras"), None),
    "the confidence with one training camera, weights only": (
        ["uncertainty.enabled=true", "uncertainty.members=weights", "holdout=[0,1,2,3]"], [], 2,
        r"uncertainty\.enabled: the confidence needs at least two training cameras", None),
}


@pytest.mark.parametrize("case", list(RUNS))
def test_an_option_given_is_never_ignored(case, tmp_path, capsys, caplog, monkeypatch):
    given, preset, status, words, iterations = RUNS[case]
    cfg = tiny_config("solver.max_iters=10", *preset, *given)
    if status:  # refused before any work: no solve
        monkeypatch.setattr(RunHook, "solve", lambda *a, **k: pytest.fail("solved"))
    caplog.set_level(logging.INFO)
    try:
        run_task(cfg, tmp_path / "run", overrides=given)
        code = 0
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    assert code == status, err
    if status:
        lines = err.splitlines()
        assert out == "" and len(lines) == 1 and lines[0].startswith(ERROR), out + err
        assert re.search(words, lines[0]), lines[0]
        assert not (tmp_path / "run" / "density.npz").exists()
        return
    assert re.search(words, out + caplog.text), out + caplog.text
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["solver"]["iterations"] == iterations
    if "select.auto" in case:  # the selection ran only where no weight was given
        assert ("selection" in metrics["solver"]) == ("alone" in case), metrics["solver"].keys()
    if "ladder" in case and "both" not in case:
        assert next(level["iterations"] for level in metrics["solver"]["levels"]) == (
            3 if "max_iters given" in case else 5)  # the rung: the solver's max_iters


# ---------------------------------------------------------------------------------------------
# calibration.frames=auto counts frame numbers, not files


def frame_capture(root, frames: list[int]):
    """The tiny synthetic flame as an OpenCV capture (calibration.json) whose camera folders
    hold the frames ``frames`` (each the same images)."""
    root.mkdir(parents=True, exist_ok=True)
    scene = tiny_synthetic()
    K, E = K_of(scene.cameras), scene.cameras.extrinsics
    H, W = scene.image_size
    cameras = [{"name": name, "K": K[i].tolist(), "R": E[i, :3, :3].tolist(), "t": E[i, :3, 3].reshape(3, 1).tolist(),
                "width": W, "height": H} for i, name in enumerate(scene.views)]
    (root / "calibration.json").write_text(json.dumps({"cameras": cameras, "holdout": [scene.views[-1]],
                                                       "bbox": [list(scene.bbox_min), list(scene.bbox_max)]}))
    for name, image in zip(scene.views, scene.images):
        rgb = (image.permute(1, 2, 0).clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        for t in frames:
            write_png(root / name / f"{t:06d}.png", rgb)
    return root


FRAME_NUMBERS = {  # frames on disk: the calibration frames auto chooses
    "0-74": (list(range(75)), (30, 69)),
    "50, 51, 53 (a gap)": ([50, 51, 53], (51, 53)),
    "one frame, 7": ([7], (7,)),
    "10-19 and 40": ([*range(10, 20), 40], (14, 19)),  # positions 4 and 9 of 11
}


@pytest.mark.parametrize("case", list(FRAME_NUMBERS))
def test_auto_calibration_frames_are_frame_numbers_the_capture_has(case, tmp_path):
    frames, chosen = FRAME_NUMBERS[case]
    root = frame_capture(tmp_path, frames)
    scene = load_scene(OmegaConf.create({"name": "opencv", "root": str(root), "frame": frames[-1]}))
    assert capture_frames(scene) == frames
    assert auto_frames(capture_frames(scene)) == chosen
    assert set(chosen) <= set(frames)


@pytest.mark.slow
def test_a_run_with_auto_calibration_frames_on_a_gap(tmp_path, capsys):
    """The issue's case end to end: camera folders holding frames 50, 51 and 53 (it gave
    'frame 1: no file'); the cameras are fitted to 51 and 53."""
    root = frame_capture(tmp_path / "capture", [50, 51, 53])
    given = ["scene=opencv", f"scene.root={root}", "scene.frame=53", "grid.resolution=12", "select.auto=false",
             "calibration.iterations=1", "calibration.rounds=1", f"calibration.folder={tmp_path / 'cal'}",
             "solver.max_iters=10", "log.eval_every=0", "device=cpu"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=given)
    run_task(cfg, tmp_path / "run", overrides=given)
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["calibration"]["frames"] == [51, 53], metrics["calibration"]
