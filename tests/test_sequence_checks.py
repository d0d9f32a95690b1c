"""Sequences checked before any work, by the names a user gave (issue 38, family 4): a sweep
whose frames differ in box, grid or training cameras is refused by scripts/flow.py in one line
naming the two frames and the field, before any velocity is fitted and with nothing written;
predict.py checks the capture's length before reconstructing; an override after a list option
is an override; advection is bounded like every iteration count; ``fr.estimate_flow`` takes a
multirun folder's path and refuses a single run's clearly; cameras at two frame rates are named
(the loader refuses them; tests/test_conventions.py reads them)."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys

import pytest
import torch
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.errors import ArgumentError
from flamerecon.fit.option_rules import MAX_STEPS
from flamerecon.run.pipeline import reconstruct
from tests.helpers import FAST, REPO, tiny_config

ERROR = "flamerecon: error: "
REAL = REPO.parent / "shared" / "data" / "scalarflow_real"
#: frame 1's overrides (frame 0 has none) and what the refusal must name
MIXED = {
    "box": (["grid.bbox=[[-0.5,0,-0.5],[0.5,1.4,0.5]]"], (r"frame 1 \(.*\): its grid box \(bbox_max\) .* differs from "
            r"frame 0 \(.*\)'s")),
    "grid": (["grid.resolution=12"], r"frame 1 \(.*\): its grid resolution \(nz, ny, nx\) \(.*\) differs from frame 0"),
    "holdout": (["holdout=[cam00]"], r"frame 1 \(.*\): its training cameras \(holdout\) .*cam04.* differs from frame 0"),
}


def call(name: str, argv: list[str]) -> int:
    """Exit status of ``scripts/<name>.py argv``, run in this process."""
    if str(REPO / "scripts") not in sys.path:
        sys.path.insert(0, str(REPO / "scripts"))
    spec = importlib.util.spec_from_file_location(f"script_{name}", REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    try:
        return module.main(argv)
    except SystemExit as stop:
        return stop.code


def plume_run(folder, frame: int, *overrides: str) -> None:
    cfg = tiny_config("scene=plume", f"scene.frame={frame}", *FAST, *overrides)
    reconstruct(cfg, folder)
    (folder / ".hydra").mkdir()
    OmegaConf.save(cfg, folder / ".hydra" / "config.yaml")


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    """{name: a multirun folder of plume frames 0 and 1}: ``good`` (one setting), and one per
    :data:`MIXED` case (frame 1 reconstructed otherwise)."""
    root = tmp_path_factory.mktemp("sequences")
    plume_run(root / "frame0", 0)
    out = {}
    for name, overrides in {"good": [], **{n: o for n, (o, _) in MIXED.items()}}.items():
        shutil.copytree(root / "frame0", root / name / "0")
        plume_run(root / name / "1", 1, *overrides)
        out[name] = root / name
    return out


def written(sweep) -> list[str]:
    """What scripts/flow.py writes into a sweep, found there."""
    names = ["flow.json", "flow", "flow_figures", "sequence.npz", "0/velocity.npz"]
    return [n for n in names if (sweep / n).exists()]


@pytest.mark.parametrize("case", sorted(MIXED))
def test_flow_refuses_frames_that_are_not_one_sequence_before_any_work(case, sweeps, capsys):
    code = call("flow", [str(sweeps[case])])
    out, err = capsys.readouterr()
    assert code == 2 and not out, out
    assert len(err.splitlines()) == 1 and err.startswith(ERROR), err
    assert re.search(MIXED[case][1], err), err
    assert written(sweeps[case]) == []


# (what is called, the error it raises, what the message names)
API_CASES = {
    "advect ten million frames": (lambda s: fr.advect(torch.rand(1, 4, 4, 4), torch.zeros(3, 4, 4, 4), 10**7),
                                  ArgumentError, (f"advect.steps: got 10000000; advect.steps must be at most "
                                                 f"{MAX_STEPS:_}")),
    "advect a fraction of a frame": (lambda s: fr.advect(torch.rand(1, 4, 4, 4), torch.zeros(3, 4, 4, 4), 0.5),
                                     ArgumentError, "advect.steps: got 0.5"),
    "estimate_flow of one run folder": (lambda s: fr.estimate_flow(str(s["good"] / "0")), ArgumentError,
                                        "is one run folder .* a flow needs two or more"),
    "estimate_flow of no folder": (lambda s: fr.estimate_flow(str(s["good"] / "none")), ArgumentError,
                                   "estimate_flow.frames: .*no such sweep folder"),
    "estimate_flow of mixed boxes": (lambda s: fr.estimate_flow(s["box"]), ArgumentError,
                                     r"estimate_flow.frames\[1\] \(frame 1\): its grid box"),
    "estimate_flow of mixed cameras": (lambda s: fr.estimate_flow(s["holdout"]), ArgumentError,
                                       r"estimate_flow.frames\[1\] \(frame 1\): its training cameras"),
}


@pytest.mark.parametrize("case", sorted(API_CASES))
def test_the_python_api_refuses_by_the_names_it_was_given(case, sweeps):
    make, error, message = API_CASES[case]
    with pytest.raises(error, match=message):
        make(sweeps)


def test_estimate_flow_takes_a_multirun_folder(sweeps):
    flow = fr.estimate_flow(sweeps["good"], fr.FlowOptions(iters=3, control=4))
    assert flow.frames == [0] and flow.pairs[0].u.shape == (3, *flow.grid.shape)


def two_rates(root) -> str:
    """A PINF capture (frames 0 and 1) whose third camera runs at 60 frames per second, the others at 30."""
    scene = fr.load_scene("synthetic", n_cameras=3, width=80, height=60, phantom_resolution=48)
    entries = []
    for i, name in enumerate(scene.views):
        for frame in (0, 1):
            fr.save_image(root / name / f"{frame:06d}.png", scene.images[i])
        c2w = fr.geometry.cameras.opencv_w2c_to_opengl_c2w(scene.cameras.extrinsics[i]).tolist()
        entries.append({"file_name": f"{name}.mp4", "camera_angle_x": 0.8, "camera_hw": [60, 80],
                        "transform_matrix": c2w, "frame_rate": 30 if i < 2 else 60})
    (root / "info.json").write_text(json.dumps({"train_videos": entries}))
    return str(root)


# (script, argv, the line's message): overrides after a list option, cameras at two frame rates
SCRIPT_CASES = [
    ("predict", ["--frames", "1", "1", "--horizons", "1", "2", "scene=plume", "flow.control=1"],
     "flow.control: got 1"),
    ("predict", ["--frames", "1", "1", "--horizons", "1", "20000", "scene=plume"], "argument --horizons: 20000 "),
    ("flow", ["SWEEP", "--figures", "0", "flow.control=1"], "flow.control: got 1"),
    ("predict", ["--frames", "0", "0", "--horizons", "1", "scene=scalarflow", "scene.root=TWO_RATES"],
     "frame_rate: the cameras run at 30 and 60 frames per second"),
]


@pytest.mark.parametrize(("name", "argv", "message"), SCRIPT_CASES, ids=[" ".join(a) for _, a, _ in SCRIPT_CASES])
def test_a_script_names_what_it_was_given(name, argv, message, sweeps, capsys, tmp_path):
    argv = [a.replace("SWEEP", str(sweeps["good"])) for a in argv]
    argv = [a.replace("TWO_RATES", two_rates(tmp_path)) if "TWO_RATES" in a else a for a in argv]
    code = call(name, argv)
    out, err = capsys.readouterr()
    assert code == 2 and not out, out
    assert len(err.splitlines()) == 1 and err.startswith(ERROR) and message in err, err


@pytest.mark.skipif(not REAL.is_dir(), reason="the real capture is not in ../shared/data")
def test_predict_checks_the_captures_end_before_reconstructing(capsys):
    code = call("predict", ["--frames", "70", "74", "--horizons", "1", "30"])
    out, err = capsys.readouterr()
    assert code == 2 and not out, out
    assert len(err.splitlines()) == 1 and "needs frame 104, which the capture does not have" in err, err
