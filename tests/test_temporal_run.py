"""``scene.frames=[first,last]`` end to end on the tiny synthetic flame over three frames: the
per-frame folders, what scripts/assemble.py makes of them, the coupling's effect, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from itertools import pairwise

import numpy as np
from hydra import compose, initialize_config_dir

from flamerecon.errors import ConfigError
from flamerecon.outputs.export import load_density
from flamerecon.run.joint_frames import run_frames
from tests.helpers import FAST, REPO, repo_env
from tests.helpers import TINY as TINY_SCENE

TINY = [*TINY_SCENE, *FAST]  # the tiny config with the short solve

FRAMES = ["scene.frames=[0,2]", "solver=tv", "solver.max_iters=40"]


def cfg(*overrides: str):
    with initialize_config_dir(str(REPO / "conf"), version_base="1.3"):
        return compose("train", overrides=[*TINY, *FRAMES, *overrides])


def test_cli_writes_frames_that_assemble_reads(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, str(REPO / "train.py"), *TINY, *FRAMES, "temporal.l2=0.02",
         f"hydra.run.dir={run}"],
        capture_output=True, text=True, env=repo_env(), timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "tv+temporal" in proc.stdout
    for t in range(3):
        folder = run / "frames" / f"{t:06d}"
        assert {"density.npz", "cameras.json", "metrics.json"} <= {p.name for p in folder.iterdir()}
        metrics = json.loads((folder / "metrics.json").read_text())
        assert metrics["solver"]["temporal"]["l2_rel"] == 0.02
        assert "volume" in metrics  # the synthetic truth of that frame scored it
    top = json.loads((run / "metrics.json").read_text())
    assert sorted(top["frames"]) == ["000000", "000001", "000002"]
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "assemble.py"), str(run / "frames"),
                           "--no-vti"], capture_output=True, text=True, env=repo_env(), timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    with np.load(run / "frames" / "sequence.npz") as seq:
        assert seq["frames"].tolist() == [0, 1, 2]
        assert seq["density"].shape[0] == 3
        np.testing.assert_array_equal(seq["density"][1], load_density(run / "frames" / "000001").density)
    csv = (run / "frames" / "sequence_metrics.csv").read_text().splitlines()
    assert len(csv) == 4 and "heldout.cam" in csv[0]


def test_coupling_pulls_neighbouring_frames_together(tmp_path):
    def step_change(folder):
        vols = [load_density(folder / "frames" / f"{t:06d}").density for t in range(3)]
        return sum(float(np.abs(b - a).sum()) for a, b in pairwise(vols))

    run_frames(cfg("device=cpu", "temporal.l2=0"), tmp_path / "free")
    run_frames(cfg("device=cpu", "temporal.l2=0", "temporal.tv=0.3"), tmp_path / "tied")
    assert step_change(tmp_path / "tied") < 0.5 * step_change(tmp_path / "free")


def test_bad_frames_and_unsupported_options_are_refused(tmp_path):
    for overrides, field in ((["scene.frames=[3,1]"], "scene.frames"),
                             (["scene.frames=[0]"], "scene.frames"),
                             (["solver=sart"], "solver.name"),
                             (["grid.levels=[8]"], "grid.levels"),
                             (["select.auto=true"], "select.auto"),
                             (["temporal.l2=0.1", "temporal.motion=optical"], "temporal.motion")):
        try:
            run_frames(cfg(*overrides), tmp_path)
        except ConfigError as err:
            assert str(err).startswith(field + ":"), err
        else:
            raise AssertionError(f"{overrides} was accepted")
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *TINY, "scene.frames=[2,1]",
                           f"hydra.run.dir={tmp_path / 'bad'}"],
                          capture_output=True, text=True, env=repo_env(), timeout=300, check=False)
    assert proc.returncode == 2
    assert "flamerecon: error: scene.frames: need 0 <= first <= last" in proc.stderr


def test_each_frame_goes_through_the_runs_debias_step(tmp_path):
    """A joint solve keeps the single run's steps after the solve: each frame gets its own gain."""
    run_frames(cfg("device=cpu", "debias.method=gain"), tmp_path / "run")
    for t in range(3):
        metrics = json.loads((tmp_path / "run" / "frames" / f"{t:06d}" / "metrics.json").read_text())
        record = metrics["solver"]["debias"]
        assert record["method"] == "gain" and len(record["gain"]) == 3  # one per colour channel
        assert all(g > 1.0 for g in record["gain"])  # tv and L1 shrink: the unbiased level is higher


def test_the_python_api_solves_frames_jointly_as_the_cli_does(tmp_path):
    """fr.reconstruct_frames takes typed options and no Hydra: the same densities, bit for bit,
    as the run layer's scene.frames run (whose folders hold them after the same debias)."""
    from omegaconf import OmegaConf

    from flamerecon.run.config import options_from_config

    composed = cfg("device=cpu", "temporal.l2=0.02")
    run_frames(composed, tmp_path / "run")
    scene = OmegaConf.to_container(composed.scene, resolve=True)
    scene.pop("frames")
    code = (
        "import sys, json, numpy as np, flamerecon as fr\n"
        "scene, options = json.loads(sys.argv[1]), json.loads(sys.argv[2])\n"
        "scenes = [fr.load_scene({**scene, 'frame': t}) for t in range(3)]\n"
        "o = fr.ReconstructionOptions.from_dict(options)\n"
        "rec = fr.reconstruct_frames(scenes, o, fr.JointFramesOptions(l2=0.02))\n"
        "np.save(sys.argv[3], np.stack([f.density.cpu().numpy() for f in rec.frames]))\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'omegaconf')))\n")
    options = options_from_config(composed).as_dict()
    done = subprocess.run([sys.executable, "-c", code, json.dumps(scene), json.dumps(options),
                           str(tmp_path / "api.npy")],
                          check=False, cwd=REPO, env=repo_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
    api = np.load(tmp_path / "api.npy")
    for t in range(3):
        np.testing.assert_array_equal(api[t], load_density(tmp_path / "run" / "frames" / f"{t:06d}").density)
