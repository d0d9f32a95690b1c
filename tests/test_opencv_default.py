"""``scene=opencv`` as a user with their own capture runs it: the default chooses its weights
from the training views (select.auto), fits the hull's background rays and debiases; here on
the tiny synthetic flame written out as an OpenCV calibration and frame folders."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from flamerecon.geometry.cameras import K_of
from flamerecon.run.pipeline import reconstruct
from tests.helpers import REPO, tiny_synthetic
from tests.helpers.views import write_png

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The tiny synthetic flame's cameras and images as calibration.json + NAME/000000.png."""
    root = tmp_path_factory.mktemp("opencv_capture")
    scene = tiny_synthetic()
    K, E = K_of(scene.cameras), scene.cameras.extrinsics
    H, W = scene.image_size
    cameras = [{"name": name, "K": K[i].tolist(), "R": E[i, :3, :3].tolist(),
                "t": E[i, :3, 3].reshape(3, 1).tolist(), "width": W, "height": H}
               for i, name in enumerate(scene.views)]
    box = [list(scene.bbox_min), list(scene.bbox_max)]
    (root / "calibration.json").write_text(json.dumps(
        {"cameras": cameras, "holdout": [scene.views[-1]], "bbox": box}))
    for name, image in zip(scene.views, scene.images):
        rgb = (image.permute(1, 2, 0).clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        write_png(root / name / "000000.png", rgb)
    return root, scene


def test_the_opencv_default_chooses_its_weights_and_debiases(capture, tmp_path):
    root, scene = capture
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[
            "scene=opencv", f"scene.root={root}", "grid.resolution=16", "device=cpu",
            "select.iterations=10", "select.folds=2", "solver.max_iters=30", "log.eval_every=0"])
    assert (cfg.solver.name, cfg.select.auto, cfg.debias.method, cfg.projector.rays) == (
        "tv", True, "gain", "hull")
    assert cfg.calibration.refine == "pose"
    metrics = reconstruct(cfg, tmp_path / "run")
    assert metrics["calibration"]["refine"] == "pose"
    assert set(metrics["calibration"]["cameras"]) == set(scene.views[:-1])  # the training cameras refined
    selection = metrics["solver"]["selection"]
    candidates = [c["overrides"] for c in selection["candidates"]]
    assert selection["chosen"] in candidates and len(candidates) == len(cfg.select.candidates.tv)
    best = max(selection["candidates"], key=lambda c: c["psnr"])
    assert best["overrides"] == selection["chosen"]
    assert all(len(c["folds"]) == 2 for c in selection["candidates"])
    assert metrics["solver"]["debias"]["method"] == "gain"
    held = metrics["heldout"][scene.views[-1]]
    assert held["psnr"] > held["psnr_black"] + 3  # it predicts the unseen camera
    assert "the capture's calibration" in selection["source"]  # chosen on calibration.frames, kept in its file
    assert selection["frames"] == list(cfg.calibration.frames) or cfg.calibration.frames == "auto"
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["solver"]["selection"]["chosen"] == selection["chosen"]
    assert torch.isfinite(torch.tensor(held["psnr"]))


def test_a_later_frame_reads_the_capture_s_cameras_and_weights(capture, tmp_path):
    """The camera fit and the weights are the capture's: a second run of it reads both from the
    calibration file (no fit, no selection) and solves with the same weights."""
    root, _ = capture
    overrides = ["scene=opencv", f"scene.root={root}", "grid.resolution=16", "device=cpu", "select.iterations=10",
                 "select.folds=2", "solver.max_iters=30", "log.eval_every=0", f"calibration.folder={tmp_path / 'cal'}"]
    runs = []
    for k in range(2):
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
            runs.append(reconstruct(compose("train", overrides=overrides), tmp_path / f"run{k}"))
    first, later = runs
    assert (first["calibration"]["source"], later["calibration"]["source"]) == ("fitted", "read")
    assert later["solver"]["selection"]["chosen"] == first["solver"]["selection"]["chosen"]
    assert later["solver"]["l1"] == first["solver"]["l1"] and "selection" not in later["timing"]


def test_auto_calibration_frames_are_spread_over_the_capture(tmp_path):
    from flamerecon.fit.refine_cameras import auto_frames
    from flamerecon.scenes.frames import source_frames

    assert auto_frames(range(75)) == (30, 69) and auto_frames([0]) == (0,) and auto_frames([0, 1]) == (0, 1)
    assert auto_frames([50, 51, 53]) == (51, 53)  # frame numbers, not positions (issue 38)
    folder = tmp_path / "cam0"
    folder.mkdir()
    for t in range(12):
        (folder / f"{t:06d}.png").write_bytes(b"")
    (folder / "notes.txt").write_text("not a frame")
    assert source_frames(folder / "000003.png") == list(range(12))
    assert source_frames(tmp_path / "single.png") is None
