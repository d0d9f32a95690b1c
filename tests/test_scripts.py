"""Every script in ``scripts/``: ``--help`` prints its whole docstring, one tiny real call
works, and a bad argument ends with one line naming it, exit status 2, before any work."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from flamerecon.outputs.export import save_density
from flamerecon.run.pipeline import reconstruct
from tests.helpers import FAST, REPO, TINY, tiny_cfg, tiny_config, tmpfs

SCRIPTS = sorted(p.stem for p in (REPO / "scripts").glob("*.py"))
SYNTHETIC = ["scene=synthetic", *TINY, *FAST]
PLUME = ["scene=plume", *TINY, *FAST]
#: the synthetic flame benchmark's scene (7 cameras) and every method's options, tiny
FLAME = ["scene.width=48", "scene.height=36", "scene.downscale=1", "scene.phantom_resolution=32", "grid.resolution=12",
         *FAST, "device=cpu", "calibration.rounds=1", "calibration.iterations=1", "select.iterations=5",
         "select.folds=2"]
REAL = REPO.parent / "shared" / "data" / "scalarflow_real"
ERROR = "flamerecon: error: "


def load(name: str):
    """``scripts/<name>.py`` as a module (its folder importable, as when it runs)."""
    if str(REPO / "scripts") not in sys.path:
        sys.path.insert(0, str(REPO / "scripts"))
    spec = importlib.util.spec_from_file_location(f"script_{name}", REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def call(name: str, argv: list[str]) -> int:
    """Exit status of ``scripts/<name>.py argv``, run in this process."""
    try:
        return load(name).main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A tiny train.py run folder."""
    run = tmp_path_factory.mktemp("finished") / "run"
    reconstruct(tiny_cfg(*FAST), run)
    (run / ".hydra").mkdir()
    OmegaConf.save(tiny_cfg(*FAST), run / ".hydra" / "config.yaml")
    return run


@pytest.fixture(scope="module")
def benchmark_dump(tmp_path_factory):
    """benchmark.py's problem dump of an 8^3 grid (what preconditioning_study.py reads)."""
    dump = tmp_path_factory.mktemp("dump")
    assert call("benchmark", ["--grid", "8", "--budget", "0.5", "--peers", "--solvers", "fista",
                              "--reference-iters", "20", "--dump", str(dump), "--out", str(dump / "b.json"),
                              "--device", "cpu", "--threads", "1"]) == 0
    return dump


@pytest.fixture(scope="module")
def plume_sweep(tmp_path_factory):
    """A multirun folder of three tiny train.py runs of the synthetic plume, frames 0-2."""
    folder = tmp_path_factory.mktemp("plume") / "sweep"
    for frame in (0, 1, 2):
        cfg = tiny_config("scene=plume", f"scene.frame={frame}", *FAST)
        reconstruct(cfg, folder / str(frame))
        (folder / str(frame) / ".hydra").mkdir()
        OmegaConf.save(cfg, folder / str(frame) / ".hydra" / "config.yaml")
    return folder


def sweep(tmp_path: Path) -> Path:
    """A multirun folder of two frame runs."""
    for frame in (0, 1):
        volume = np.random.default_rng(frame).random((3, 4, 4, 4)).astype(np.float32)
        (tmp_path / "sweep" / str(frame)).mkdir(parents=True)
        save_density(tmp_path / "sweep" / str(frame) / "density.npz", volume, [0, 0, 0], [1, 1, 1], ["a"],
                     frame=frame)
    return tmp_path / "sweep"


def pinf_capture(tmp_path: Path) -> Path:
    """A one-camera PINF info.json (the converter's input)."""
    import json

    (tmp_path / "pinf").mkdir()
    entry = {"file_name": "cam00.mp4", "camera_hw": [4, 6], "camera_angle_x": 0.8,
             "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "pinf" / "info.json").write_text(json.dumps({"train_videos": [entry]}))
    return tmp_path / "pinf" / "info.json"


def copied(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / "run"))


needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"no ScalarFlow capture at {REAL}")

# script -> (argv from (tmp_path, finished run, benchmark dump), what its output shows)
CALLS = {
    "assemble": (lambda t, run, dump: [str(sweep(t)), "--no-vti"], r"npz: .*sequence\.npz"),
    "benchmark": (lambda t, run, dump: ["--grid", "8", "--budget", "0.2", "--peers", "--solvers", "fista",
                                        "--reference-iters", "20", "--dump", str(dump), "--out",
                                        str(t / "new" / "b.json"), "--device", "cpu"], r"wrote .*b\.json"),
    "check_capture": (lambda t, run, dump: ["scene=opencv", f"scene.root={REPO / 'examples' / 'capture'}",
                                            "--out", str(t / "check")], r"hull IoU"),
    "convert_capture": (lambda t, run, dump: ["pinf", str(pinf_capture(t)), str(t / "converted" / "calibration.yaml")],
                        r"calibration\.yaml: 1 cameras \(cam00\)"),
    "compare_methods": (lambda t, run, dump: [*SYNTHETIC, "--frames", "0", "--method", "plain=",
                                              "--out", str(t / "new" / "c.json")], r"mean +plain"),
    "cross_validate": (lambda t, run, dump: [*SYNTHETIC, "--sweep", "solver.l1_rel=0.01", "--exclude", "cam04",
                                             "--out", str(t / "cv")], r"cross-validation \(1 settings\)"),
    "default_solve_cost": (lambda t, run, dump: ["--solvers", "fista_smooth:max_iters=3", "--repeats", "1"],
                           r"fista_smooth:max_iters=3 +3 it"),
    "evaluate": (lambda t, run, dump: [str(copied(run, t)), "--device", "cpu", "--no-native"], r"held-out PSNR"),
    "export": (lambda t, run, dump: [str(copied(run, t)), "--format", "raw"], r"density\.raw"),
    "first_run": (lambda t, run, dump: ["--frames", "0", "1", *SYNTHETIC, "calibration.refine=pose",
                                        "calibration.frames=[2]", "calibration.rounds=1", "calibration.iterations=1"],
                  r"first run \(frame \d+, cameras fitted\): .* s wall .*, detail \d\.\d+;.*\nlater frame \(frame \d+, cameras read\): .*"),
    "camera_fit_gain": (lambda t, run, dump: ["--sizes", "32x24:8:10"],
                        r"exact .*\n +32x24 +8 +10 +-?\d+\.\d\d% +-?\d+\.\d\d% +-?\d+\.\d\d%"),
    "flow": (lambda t, run, dump: [str(run), "--figures", "1", "--no-vti"],
             r"frame +0 -> 1: residual .*\n.*frame +1 -> 2: .*\nwritten: velocity\.npz in 2 run folders"),
    "flow_benchmark": (lambda t, run, dump: ["--frames", "0", "2", *PLUME], r"3 frames, 2 frame pairs in .* the flow took"),
    "predict": (lambda t, run, dump: ["--frames", "1", "1", *PLUME, "--horizons", "1", "2", "--out", str(t / "new" / "p.json"),
                                      "--figures", str(t / "figures"), "--variant", "nodiv:divergence=0"],
                (r"  2 flow .*\n  2 flow_causal .*\n  2 simulation .*\n  2 persistence .*\n  2 shift .*\n  2 reconstruction .*\n"
                 r"  2 flow:nodiv(.|\n)*velocity against the truth over the smoke: relative L2 \d\.\d+(.|\n)*written: "
                 r".*predictions_0001_k02_cam04\.png(.|\n)*written: .*simulation\.pvd")),
    "resimulate": (lambda t, run, dump: ["--frames", "0", "2", *PLUME, "--out", str(t / "new" / "r.json"), "--figures",
                                         str(t / "figures"), "--every", "2"],
                   (r"    2 +\d+\.\d\d +\d+\.\d\d +\d+\.\d\d +\d+\.\d\d +\d+\.\d{3} +\d+\.\d{3}\n"
                    r"(.|\n)*mean over frames 1-2, resimulation: held-out "
                   r"(.|\n)*written: .*resimulation_0002_cam04\.png(.|\n)*resimulation\.pvd")),
    "simulated_plume": (lambda t, run, dump: ["--frames", "16", "--pairs", "5", "5", "--window", "1", "--cells", "12",
                                              "16", "12", *SYNTHETIC, "--out", str(t / "new" / "s.json")],
                        r"uniform +\d+\.\d{3} +\d+\.\d\n(.|\n)*predicted simulation_k10 +volume relative L2"),
    "flame_benchmark": (lambda t, run, dump: ["--seeds", "0", *FLAME, "--out", str(t / "new" / "f.json")],
                        r"mean +opencv .* dB over nnls"),
    "heldout_limits": (lambda t, run, dump: [*SYNTHETIC, "--frames", "0", "--pictures", str(t / "pics")],
                       r"    0 cam04 .* -?\d\.\d{3} +-?\d\.\d{3} "),
    "leave_one_out": (lambda t, run, dump: [*TINY, *FAST, "--views", "cam00", "--out", str(t / "loo")],
                      r"cam00: PSNR"),
    "motion_eval": (lambda t, run, dump: [*SYNTHETIC, "--frames", "1", "--windows", "1,3", "--decay", "1",
                                          "--static"], r"mean +3 density s=0.01 decay=1 .*\n.*static"),
    "operator_memory": (lambda t, run, dump: ["--grid", "8", *SYNTHETIC], r"operator: \d+ rays .* nonzeros \(estimate"),
    "plan_cameras": (lambda t, run, dump: [str(copied(run, t)), "--orbit", "6"],
                     (r"azimuth about \+y \(0 deg: \+z, 90 deg: \+x\).*\n.*relative error now at [0-9.]+.*\n"
                      r"rank camera .*\n +1 orbit0\d +[0-9.]+° +-?[0-9.]+° +[0-9.]+% +[0-9.]+ ")),
    "preconditioning_study": (lambda t, run, dump: ["--grid", "8", "--iters", "20", "--variants", "lipschitz",
                                                    "--dump", str(dump)], r"lipschitz +"),
    "refine_cameras": (lambda t, run, dump: [*SYNTHETIC, "calibration.rounds=1", "--modes", "pose",
                                             "--out", str(t / "new" / "r.jsonl")], r"    0 pose "),
    "render": (lambda t, run, dump: [str(run), "--camera", "orbit:0,10", "--width", "16", "--height", "12",
                                     "--out", str(t / "renders")], r"orbit_az0_el10_.*\.png"),
    "scale_benchmark": (lambda t, run, dump: ["--scene", "synthetic", "--frame", "0", "scene.width=48",
                                              "scene.height=36", "scene.phantom_resolution=16", "solver.max_iters=5",
                                              "log.eval_every=0", "device=cpu", "--out", str(t / "new" / "s.json"),
                                              "--rungs", "4:8", "2:12"],
                        r"(?s)\s+4\s+8\s.*\n\s+2\s+12\s.*wrote .*s\.json"),
    "sequence_benchmark": (lambda t, run, dump: ["--frames", "0", "1", *SYNTHETIC],
                           r"1/2, \d+ s left\n(.|\n)*2/2, 0 s left\n(.|\n)*2 frames in .* per minute"),
    "uncertainty_check": (lambda t, run, dump: ["--frames", "0", "--out", str(t / "new" / "u.json"), *SYNTHETIC],
                          (r"    0 cam04 .*\n +cam04 against its noiseless images: coverage .*\n.*volume: rank correlation.*\n"
                           r".*against the noiseless images .*coverage")),
    "temporal_eval": (lambda t, run, dump: [*SYNTHETIC, "scene.frames=[0,1]", "--weights", "0:0", "--no-baseline"],
                      r"joint l2=0 tv=0 .* +1 "),
}
#: what a real-capture call shows where it differs from the synthetic call's (one frame here)
REAL_SHOWS = {"sequence_benchmark": r"1/1, 0 s left\n(.|\n)*1 frames in .* per minute"}
REAL_CALLS = {  # the same on the real capture
    "first_run": ["--frames", "65", "5", "scene.downscale=8", "grid.resolution=16", "solver.max_iters=5",
                  "calibration.resolution=16", "calibration.rounds=1", "calibration.iterations=1",
                  "debias.iterations=2", "log.eval_every=0", "device=cpu"],
    "sequence_benchmark": ["--frames", "0", "0", "scene.downscale=8", "grid.resolution=16", "solver.max_iters=5",
                           "calibration.refine=none", "log.eval_every=0", "device=cpu"],
}


def test_every_script_has_a_smoke_call():
    assert sorted(CALLS) == SCRIPTS


@pytest.mark.parametrize("name", SCRIPTS)
def test_help_prints_the_whole_docstring(name, capsys):
    module = load(name)
    assert call(name, ["--help"]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    assert f"usage: {name}.py" in printed
    assert " ".join(module.__doc__.split()) in printed


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_tiny_real_call(name, tmp_path, capsys, request, monkeypatch):
    monkeypatch.chdir(tmp_path)  # default output folders land here
    if name == "simulated_plume" and importlib.util.find_spec("phi") is None:
        pytest.skip("PhiFlow (pip install phiflow, a bench extra) is not installed")
    make, shows = CALLS[name]
    run = request.getfixturevalue("finished_run") if name in ("evaluate", "export", "render", "plan_cameras") else None
    run = request.getfixturevalue("plume_sweep") if name == "flow" else run
    dump = request.getfixturevalue("benchmark_dump") if name in ("benchmark", "preconditioning_study") else None
    code = call(name, make(tmp_path, run, dump))
    out, err = capsys.readouterr()
    assert code == 0, err
    assert re.search(shows, out), out


@needs_real
@pytest.mark.parametrize("name", list(REAL_CALLS))
def test_a_tiny_call_on_the_real_capture(name, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert call(name, REAL_CALLS[name]) == 0, capsys.readouterr().err
    shows = REAL_SHOWS.get(name, CALLS[name][1].replace("2 frames", "1 frames"))
    assert re.search(shows, capsys.readouterr().out)


def _file(t: Path) -> str:
    (t / "file").write_text("x")
    return str(t / "file")


# (script, argv from tmp_path (FILE: a file, RO: a read-only folder), the error line after the prefix)
BAD = [
    ("refine_cameras", ["--modes", "pose,spin"], r"argument --modes: got 'pose,spin'; give .*pose\+intrinsics"),
    ("refine_cameras", ["--frames", "3,x"], r"argument --frames: expected comma-separated frame numbers"),
    ("refine_cameras", ["--out", "TMP"], r"argument --out: .*: is a folder; give a file name"),
    ("sequence_benchmark", ["--frames", "5", "2"], r"argument --frames: FIRST 5 is after LAST 2"),
    ("sequence_benchmark", ["--protocol", "nope"], r"argument --protocol: invalid choice: 'nope'"),
    ("scale_benchmark", ["--rungs", "2x128"], r"argument --rungs: got '2x128'; give DOWNSCALE:GRID"),
    ("scale_benchmark", ["--rungs", "0:128"], r"argument --rungs: got '0:128'; the downscale must be >= 1"),
    ("sequence_benchmark", ["--every", "0"], r"argument --every: got '0'; give an integer >= 1"),
    ("sequence_benchmark", ["--frames", "-1", "2"], r"argument --frames: got '-1'; give an integer >= 0"),
    ("first_run", ["--frames", "-1", "2"], r"argument --frames: got '-1'; give an integer >= 0"),
    ("compare_methods", ["--frames", "0", "--method", "a=", "--out", "FILE/c.json"],
     r"argument --out: .*file: is a file, not a folder"),
    ("compare_methods", ["--frames", "0", "--method", "a=", "--out", "RO/c.json"],
     r"argument --out: .*c\.json: cannot write \(errno 30 EROFS"),
    ("compare_methods", ["--frames", "0", "--method", "a=", "--loo", "--out", "RO/c.json"],
     r"argument --out: .*cannot write \(errno 30 EROFS"),
    ("compare_methods", ["--frames", "", "--method", "a="], r"argument --frames: expected comma-separated"),
    ("leave_one_out", ["--out", "RO/loo"], r"argument --out: .*loo: cannot write \(errno 30 EROFS"),
    ("leave_one_out", ["--out", "FILE"], r"argument --out: .*file: is a file, not a folder; give a folder"),
    ("cross_validate", ["--out", "RO/cv"], r"argument --out: .*cv: cannot write \(errno 30 EROFS"),
    ("cross_validate", ["--sweep", "solver.l1"], r"argument --sweep: expected key=v1,v2"),
    ("benchmark", ["--out", "TMP"], r"argument --out: .*: is a folder; give a file name"),
    ("benchmark", ["--dump", "FILE"], r"argument --dump: .*file: is a file, not a folder"),
    ("render", ["RUN", "--out", "RO/renders"], r"argument --out: .*renders: cannot write \(errno 30 EROFS"),
    ("temporal_eval", ["--weights", "1"], r"argument --weights: got '1'; give L2:TV or L2:TV:shift"),
    ("temporal_eval", ["--weights", "0:0:spin"], r"argument --weights: got '0:0:spin'"),
    ("temporal_eval", ["--absorption", "-1"], r"argument --absorption: got '-1'; give an integer >= 0"),
    ("temporal_eval", ["scene=synthetic"], r"scene\.frames: not set; give the frames"),
    ("default_solve_cost", ["--solvers", "nope"], r"argument --solvers: 'nope': unknown solver 'nope'"),
    ("default_solve_cost", ["--solvers", "fista:max_iters"], r"argument --solvers: .*'max_iters' is not key=number"),
    ("default_solve_cost", ["--repeats", "0"], r"argument --repeats: got '0'; give an integer >= 1"),
    ("motion_eval", ["--windows", "1,2"], r"argument --windows: got 2; window lengths are odd"),
    ("flame_benchmark", ["--seeds", "x"], r"argument --seeds: expected comma-separated seeds >= 0, got 'x'"),
    ("flame_benchmark", ["--method", "x"], r"argument --method: expected NAME=OVERRIDES, got 'x'"),
    ("heldout_limits", ["--frames", "a"], r"argument --frames: expected comma-separated frame numbers"),
    ("assemble", ["SWEEP", "--no-such-flag"], r"unrecognized arguments: --no-such-flag"),
    ("export", ["RUN", "--iso", "x"], r"argument --iso: invalid float value: 'x'"),
    ("preconditioning_study", ["--grid", "x"], r"argument --grid: invalid int value: 'x'"),
    ("predict", ["--frames", "5", "2"], r"argument --frames: FIRST 5 is after LAST 2"),
    ("predict", ["--frames", "1", "2", "--variant", "nodiv"], r"--variant: got 'nodiv'; give NAME:KEY=VALUE"),
    ("predict", ["--frames", "1", "2", "--variant", "a:divergence=-1"], r"flow\.divergence: got -1"),
    ("predict", ["--frames", "1", "2", "flow.nope=3"], r"flow\.nope=3: not a flow option; give flow\.KEY=VALUE"),
    ("predict", ["--frames", "1", "2", "flow.control=1"], r"flow\.control: got 1; flow\.control must be an integer >= 2"),
    ("flow", ["SWEEP", "flow.smooth=-1"], r"flow\.smooth: got -1; flow\.smooth must be >= 0"),
    ("flow", ["SWEEP"], r"no run folder with density\.npz"),
    ("flow_benchmark", ["--frames", "3", "3"], r"argument --frames: FIRST 3 is not before LAST 3"),
    ("uncertainty_check", ["--frames", "-1", "--out", "u.json"], r"argument --frames: got '-1'; give an integer >= 0"),
    ("uncertainty_check", ["--frames", "1", "--out", "TMP"], r"argument --out: .*: is a folder; give a file name"),
    ("plan_cameras", [], r"give one RUN_DIR"),
    ("plan_cameras", ["--check-loo"], r"--check-loo needs --frames"),
    ("plan_cameras", ["RUN", "--noise", "-1"], r"--noise: got -1.0; give a number > 0"),
    ("plan_cameras", ["RUN", "--orbit", "100000000"], r"--orbit: .*give an integer from 3 to 360"),
]


@pytest.mark.parametrize(("name", "argv", "message"), BAD, ids=[f"{n} {' '.join(a)}" for n, a, _ in BAD])
def test_a_bad_argument_is_one_line_and_status_2(name, argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with contextlib.ExitStack() as stack:
        if any("RO" in a for a in argv):
            stack.enter_context(tmpfs(tmp_path / "ro", "ro,size=1m"))
        argv = [a.replace("FILE", _file(tmp_path)) if "FILE" in a else a for a in argv]
        argv = [a.replace("RO", str(tmp_path / "ro")).replace("TMP", str(tmp_path))
                .replace("RUN", str(tmp_path)).replace("SWEEP", str(tmp_path)) for a in argv]
        code = call(name, argv)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith(ERROR), err
    assert re.search(message, err), err


def test_flow_writes_velocities_beside_the_frames(plume_sweep, capsys):
    """scripts/flow.py on a sweep: velocity.npz in every run folder but the last, in world units
    per second at the capture's frame rate; the sequence files again with them; flow.json,
    TensorBoard scalars and the figures."""
    from flamerecon.outputs.velocity import load_velocity

    shutil.rmtree(plume_sweep / "flow_figures", ignore_errors=True)  # the smoke call's figures (module fixture)
    assert call("flow", [str(plume_sweep), "--figures", "0"]) == 0, capsys.readouterr().err
    first = load_velocity(plume_sweep / "0")
    assert first.frame == 0 and first.frame_rate == 30.0 and first.record["next_frame"] == 1
    assert first.velocity.shape[0] == 3 and np.isfinite(first.velocity).all()
    assert (plume_sweep / "1" / "velocity.npz").is_file() and not (plume_sweep / "2" / "velocity.npz").exists()
    with np.load(plume_sweep / "sequence.npz") as f:
        assert f["velocity"].shape == (2, *first.velocity.shape)
        assert f["velocity_frames"].tolist() == [0, 1]
        assert np.array_equal(f["velocity"][0], first.velocity)
    assert len(json.loads((plume_sweep / "flow.json").read_text())["pairs"]) == 2
    assert list((plume_sweep / "flow").glob("events.out.tfevents.*"))
    assert {p.name for p in (plume_sweep / "flow_figures").iterdir()} == {"velocity_slices_0000.png",
                                                                          "streamlines_0000.png"}
    if importlib.util.find_spec("vtkmodules") is not None:
        assert b'Name="velocity"' in (plume_sweep / "sequence_vti" / "frame_0000.vti").read_bytes()
