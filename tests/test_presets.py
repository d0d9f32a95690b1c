"""Presets and real captures in the library: ``fr.preset(scene, *overrides)`` is the command
line's composition of the same conf/ files, ``fr.load_scene(name)`` loads what ``scene=<name>``
loads, novel views and exports are public, and on a real ScalarFlow frame ``fr.reconstruct`` of a
loaded CLI run returns the CLI's density bit for bit while a second frame reads the capture's
calibration file instead of fitting it again."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.errors import ConfigError
from flamerecon.fit import capture_calibration
from flamerecon.fit.reconstruct import calibrated_scene
from flamerecon.outputs.export import read_raw, save_density
from flamerecon.run.folder import RUN_LAYER_KEYS
from flamerecon.scenes import SceneError, cache
from tests.helpers import REPO, TINY, repo_env

SCENES = sorted(p.stem for p in (REPO / "conf" / "scene").glob("*.yaml"))
REAL = REPO / ".." / "shared" / "data" / "scalarflow_real"
needs_real = pytest.mark.skipif(not (REAL / "info.json").is_file(),
                                reason=f"the ScalarFlow capture is not at {REAL}")


def hydra_options(*overrides: str) -> fr.ReconstructionOptions:
    """What the command line reconstructs with, composed by Hydra here, independently."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=list(overrides))
    return fr.ReconstructionOptions.from_dict(OmegaConf.to_container(cfg, resolve=True), ignore=RUN_LAYER_KEYS)


@pytest.mark.parametrize("scene", SCENES)
def test_a_preset_is_the_command_lines_composition_of_its_scene(scene):
    assert fr.preset(scene) == hydra_options(f"scene={scene}")
    overrides = ("solver=fista", "grid.resolution=48", "calibration.refine=pose", "calibration.frames=[1,2]")
    assert fr.preset(scene, *overrides) == hydra_options(f"scene={scene}", *overrides)


def test_the_scalarflow_preset_brings_its_capture_settings_not_the_synthetic_defaults():
    found = fr.preset("scalarflow")
    assert found != fr.ReconstructionOptions() and fr.preset("synthetic") == fr.ReconstructionOptions()
    assert (found.solver.name, found.grid.resolution, found.calibration.refine) == ("tv", 128, "pose")
    assert found.calibration.frames == (30, 70) and found.debias.method == "refit"


@pytest.mark.parametrize("args, message", [
    (("flame",), r"^preset\.scene: got 'flame'; .* one of \[.*'scalarflow'"),
    (("synthetic", "solver=nope"), r"^preset\.overrides: .*nope"),
    (("synthetic", "solver.max_iters=0"), r"^solver\.max_iters: got 0; "),
    (("synthetic", "scene=scalarflow"), r"^preset\.overrides: 'scene=scalarflow' is not an override"),
])
def test_a_bad_preset_is_one_line_naming_what_to_fix(args, message):
    with pytest.raises(ConfigError, match=message) as err:
        fr.preset(*args)
    assert "\n" not in str(err.value)


def test_load_scene_takes_a_presets_scene_node_a_loader_name_or_a_mapping():
    small = {"width": 48, "height": 36, "n_cameras": 5, "phantom_resolution": 32}
    by_preset = fr.load_scene("synthetic", **small)
    assert by_preset.meta["config"]["noise"] == 0.01  # conf/scene/synthetic.yaml's
    assert torch.equal(by_preset.images, fr.load_scene({"name": "synthetic", **small}).images)
    with pytest.raises(SceneError, match="scene.root: no data folder given"):
        fr.load_scene("opencv")  # its preset's root is ??? : the user gives it
    with pytest.raises(SceneError, match="scene.root: no data folder given"):
        fr.load_scene("pinf")  # a loader without a preset


def test_novel_views_and_exports_are_public(tmp_path):
    pytest.importorskip("skimage")
    scene = fr.load_scene("synthetic", width=48, height=36, n_cameras=5, phantom_resolution=32)
    rec = fr.reconstruct(scene, fr.preset("synthetic", *TINY[:1], "grid.resolution=16", "solver.max_iters=20",
                                          "device=cpu"))
    centre = tuple(0.5 * (a + b) for a, b in zip(rec.grid.bbox_min, rec.grid.bbox_max))
    eye = (centre[0], centre[1] + 0.3, centre[2] + 3.0)
    one = fr.look_at_camera(eye, centre, width=40, height=30)
    ring = fr.orbit_cameras([0, 90, 180], 10.0, 3.0, centre, width=40, height=30)
    assert fr.render(rec.density, rec.grid, one).shape == (1, 3, 30, 40)
    views = fr.render(rec.density, rec.grid, ring)
    assert views.shape == (3, 3, 30, 40) and bool((views.amax((1, 2, 3)) > 0.05).all())
    written = fr.export(rec, tmp_path / "out" / "flame", ["raw", "mesh"], iso=0.2)
    assert [p.name for p in written] == ["flame.raw", "flame.raw.json", "flame.ply", "flame.obj"]
    header = (tmp_path / "out" / "flame.ply").read_bytes().split(b"end_header")[0].decode()
    assert "element vertex" in header and "element face" in header
    save_density(tmp_path / "density.npz", rec.density, rec.grid.bbox_min, rec.grid.bbox_max, [])
    (again, _) = fr.export(tmp_path, tmp_path / "again", "raw")  # a run folder (or its density.npz)
    np.testing.assert_array_equal(read_raw(again)[0], read_raw(written[0])[0])
    np.testing.assert_array_equal(read_raw(again)[0], rec.density.numpy())


@pytest.mark.slow
@needs_real
def test_load_scene_finds_the_real_capture_at_the_command_lines_resolution():
    scene = fr.load_scene("scalarflow")
    assert scene.meta["config"]["frame"] == 59 and scene.meta["config"]["downscale"] == 4
    assert scene.image_size == (480, 270) and len(scene.views) == 5  # 1920x1080 / 4


#: both doors get the same reduced settings: a 32-cell grid, a short solve, a one-round camera
#: fit on frame 25 itself at 24 cells; one thread (the same summation order in both processes)
REAL_SETTINGS = ["threads=1", "device=cpu", "grid.resolution=32", "solver.max_iters=20",
                 "calibration.resolution=24", "calibration.frames=[25]", "calibration.rounds=1",
                 "calibration.iterations=1", "calibration.max_rays=2000", "debias.iterations=3",
                 "log.eval_every=0"]


@pytest.fixture(scope="module")
def real_cli_run(tmp_path_factory):
    """``python train.py scene=scalarflow scene.frame=25`` (reduced) in a subprocess; the
    capture's calibration file goes where the session's cache folder is (tests/conftest.py)."""
    run = tmp_path_factory.mktemp("scalarflow") / "run"
    proc = subprocess.run([sys.executable, "train.py", "scene=scalarflow", "scene.frame=25", *REAL_SETTINGS,
                           f"hydra.run.dir={run}"], cwd=REPO, env=repo_env(), capture_output=True, text=True,
                          timeout=900, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "fitted now, kept in" in proc.stdout
    return run


def counted_fits(monkeypatch) -> list:
    fits = []
    real = capture_calibration.refine
    monkeypatch.setattr(capture_calibration, "refine", lambda *a, **k: fits.append(1) or real(*a, **k))
    return fits


@pytest.mark.slow
@needs_real
def test_reconstruct_of_a_loaded_cli_run_is_the_clis_density_bit_for_bit(real_cli_run, monkeypatch):
    fits = counted_fits(monkeypatch)
    run = fr.load_run(real_cli_run, "cpu")
    assert run.options == fr.preset("scalarflow", "scene.frame=25", *REAL_SETTINGS)
    rec = fr.reconstruct(run.scene, run.options)
    assert not fits and rec.calibration["source"] == "read"
    assert rec.calibration["file"] == run.calibration["file"] and Path(run.calibration["file"]).is_file()
    np.testing.assert_array_equal(rec.density.numpy(), run.density.numpy())


@pytest.mark.slow
@needs_real
def test_a_second_frame_after_other_work_reads_the_captures_calibration(real_cli_run, monkeypatch):
    """Many large synthetic cache entries later, frame 40 through the API reads the file the
    CLI's frame 25 wrote; nothing is fitted."""
    monkeypatch.setattr(cache, "MAX_ENTRIES", 4)
    for n in range(12):
        cache.cached("synthetic", {"filler": n}, lambda: {"x": torch.zeros(250_000)}, [cache])
    fits = counted_fits(monkeypatch)
    scene = fr.load_scene("scalarflow", frame=40)
    refined, record = calibrated_scene(scene, fr.preset("scalarflow", *REAL_SETTINGS), torch.device("cpu"))
    kept = json.loads((real_cli_run / "metrics.json").read_text())["calibration"]["file"]
    assert not fits and (record["source"], record["file"]) == ("read", kept)
    assert not torch.equal(refined.cameras.extrinsics, scene.cameras.extrinsics)
