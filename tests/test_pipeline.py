"""End to end on a tiny synthetic flame: the real Hydra config, shrunk; the run folder's
contract (README, "The run folder"); TensorBoard's own reader; ``python train.py`` as a user runs it;
``scripts/evaluate.py`` reproducing the run's numbers; bad holdouts refused by name."""

from __future__ import annotations

import json
import math
import runpy
import sys

import cv2
import numpy as np
import pytest
from tensorboard.backend.event_processing import event_accumulator as ea

from flamerecon.operators.projector import MatrixFreeOperator
from flamerecon.outputs.figures import figure_layout
from flamerecon.run.pipeline import evaluate, reconstruct
from flamerecon.scenes import SceneError
from flamerecon.scenes.synthetic import ring_cameras
from tests.helpers import HELDOUT, REPO, SMALLER, TRAIN, VIEWS, CliRun, tiny_config
from tests.helpers.interrupts import stop_handlers


@pytest.fixture(scope="module")
def composed_run(tmp_path_factory):
    """reconstruct() on the composed config: (run folder, returned metrics)."""
    run_dir = tmp_path_factory.mktemp("composed")
    return run_dir, reconstruct(tiny_config(), run_dir)


@pytest.fixture(scope="module", autouse=True)
def cli_runs(request, tmp_path_factory):
    """``python train.py`` with fista and with adam, started in the background when this
    module's first test starts, so that they run while the in-process tests do (not started
    when no command-line test of this module is selected, e.g. under ``-m "not e2e"``)."""
    if not any(item.module is request.module and item.get_closest_marker("e2e")
               for item in request.session.items):
        yield {}
        return
    base = tmp_path_factory.mktemp("cli")
    runs = {name: CliRun(base / name, f"solver={name}") for name in ("fista", "adam")}
    yield runs
    for run in runs.values():
        run.stop()


@pytest.fixture(scope="module")
def cli_run(cli_runs):
    """The finished fista run: (run folder, completed process)."""
    run = cli_runs["fista"]
    return run.run_dir, run.result()


def check_metrics_schema(metrics: dict, solver: str) -> None:
    assert set(metrics["heldout"]) == set(HELDOUT)
    assert set(metrics["train"]) == set(TRAIN)
    for per_view in (*metrics["heldout"].values(), *metrics["train"].values()):
        assert {"psnr", "ssim"} <= set(per_view)
        assert 10.0 < per_view["psnr"] < 80.0 and 0.0 < per_view["ssim"] <= 1.0
    s = metrics["solver"]
    assert {"name", "iterations", "seconds", "objective"} <= set(s)
    assert s["name"] == solver
    assert isinstance(s["iterations"], int) and 1 <= s["iterations"] <= 30
    assert s["seconds"] > 0 and math.isfinite(s["objective"]) and s["objective"] >= 0
    assert set(metrics["volume"]) == {"rel_l2", "iou"}
    assert 0.0 <= metrics["volume"]["rel_l2"] < 1.0 and 0.0 < metrics["volume"]["iou"] <= 1.0


# --------------------------------------------------------------------------- run folder


@pytest.mark.slow
def test_metrics_json_is_what_reconstruct_returns_and_follows_the_schema(composed_run):
    run_dir, metrics = composed_run
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(metrics))
    check_metrics_schema(on_disk, "fista")
    # the fit explains the views better than a black image does
    for per_view in (*on_disk["heldout"].values(), *on_disk["train"].values()):
        assert per_view["psnr"] > per_view["psnr_black"] + 5


@pytest.mark.slow
def test_density_npz_holds_the_volume_its_box_and_the_training_views(composed_run):
    run_dir, _ = composed_run
    with np.load(run_dir / "density.npz") as f:
        density, lo, hi, views = f["density"], f["bbox_min"], f["bbox_max"], f["views"]
    assert density.dtype == np.float32
    assert density.shape == (3, 11, 16, 11)  # 16 cells along y (1.5), 11 along x and z (1.0)
    assert density.min() >= 0 and density.max() > 0
    assert np.allclose(lo, [-0.5, 0.0, -0.5]) and np.allclose(hi, [0.5, 1.5, 0.5])
    assert views.tolist() == TRAIN


@pytest.mark.slow
def test_cameras_json_lists_every_camera_with_its_calibration_and_split(composed_run):
    run_dir, _ = composed_run
    cams = json.loads((run_dir / "cameras.json").read_text())["cameras"]
    assert [c["name"] for c in cams] == VIEWS
    assert [c["split"] for c in cams] == ["train"] * 4 + ["holdout"]
    expected = ring_cameras(5, 48, 36)
    for i, c in enumerate(cams):
        K, E = np.array(c["K"]), np.array(c["world_to_camera"])
        assert K.shape == (3, 3) and E.shape == (4, 4)
        assert (c["width"], c["height"]) == (48, 36)
        assert np.allclose(K, expected.intrinsics[i, :3, :3].numpy())
        assert np.allclose(E, expected.extrinsics[i].numpy(), atol=1e-6)
        assert np.allclose(E[:3, :3] @ E[:3, :3].T, np.eye(3), atol=1e-5)
        assert np.allclose(E[3], [0, 0, 0, 1])


@pytest.mark.slow
def test_renders_show_each_heldout_view_rendered_captured_and_error(composed_run):
    run_dir, _ = composed_run
    assert sorted(p.name for p in (run_dir / "renders").iterdir()) == ["cam04.png"]
    figure = cv2.imread(str(run_dir / "renders" / "cam04.png"))
    # the 48 x 36 panels enlarged to read (at least 240 px tall), titles above, a colour bar right
    layout = figure_layout(36, 48)
    H, W = 36 * layout.scale, 48 * layout.scale
    assert layout.scale == 7 and figure.shape[1] == 3 * W + layout.bar_px + layout.bar_label_px
    strip = figure.shape[0] - H
    assert strip in (layout.title_px, 2 * layout.title_px)
    assert figure[:layout.title_px, :3 * W].max() > 128  # the titles are written
    panel = figure[strip:]
    rendered, captured = (panel[:, W * i:W * (i + 1)].astype(float) for i in range(2))
    flame = captured.max(-1) > 60
    assert flame.sum() > 20  # the flame is there
    assert np.abs(rendered - captured)[flame].mean() < 0.2 * captured[flame].mean()


@pytest.mark.slow
def test_tensorboard_reader_finds_scalars_and_images(composed_run):
    run_dir, metrics = composed_run
    acc = ea.EventAccumulator(str(run_dir), size_guidance={ea.SCALARS: 0, ea.IMAGES: 0})
    acc.Reload()
    tags = acc.Tags()
    assert {"solve/objective", "solve/data", "solve/l1", "solve/nonzero_fraction",
            "eval/heldout_psnr"} <= set(tags["scalars"])
    assert {"heldout/cam04", "density/top_view"} <= set(tags["images"])
    objective = acc.Scalars("solve/objective")
    assert len(objective) >= 3 and objective[-1].value <= objective[0].value
    psnr = acc.Scalars("eval/heldout_psnr")
    assert [e.step for e in psnr][:3] == [10, 20, 30]  # every log.eval_every iterations
    assert psnr[-1].value == pytest.approx(metrics["heldout"]["cam04"]["psnr"], abs=1e-4)
    image = acc.Images("heldout/cam04")[-1]
    layout = figure_layout(36, 48)
    assert image.width == 3 * 48 * layout.scale + layout.bar_px + layout.bar_label_px
    assert image.height in (36 * layout.scale + layout.title_px, 36 * layout.scale + 2 * layout.title_px)
    assert len(acc.Images("density/top_view")) >= 3  # the top view over iterations


# --------------------------------------------------------------------------- the command line


@pytest.mark.slow
@pytest.mark.e2e
def test_train_py_runs_as_a_subprocess_and_prints_the_table(cli_run):
    run_dir, proc = cli_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    for row in ("held-out PSNR [dB]", "held-out SSIM", "training PSNR [dB]",
                "volume rel. L2 / IoU", "solver", "iterations", "seconds"):
        assert row in out, out
    metrics = json.loads((run_dir / "metrics.json").read_text())
    check_metrics_schema(metrics, "fista")
    assert f"{metrics['heldout']['cam04']['psnr']:.2f}" in out
    assert (run_dir / ".hydra" / "config.yaml").is_file()
    assert (run_dir / "density.npz").is_file() and (run_dir / "renders" / "cam04.png").is_file()
    # the composed config's main nodes open the output, with the overrides and where all of it is
    head = out[out.index("config (overrides: "):]
    assert f"all of it: {run_dir / '.hydra' / 'config.yaml'}" in head.splitlines()[0]
    assert "\n  solver:\n    name: fista\n" in head and "\n  grid:\n    resolution: 16\n" in head
    assert out.index("config (overrides: ") < out.index("held-out PSNR [dB]")


@pytest.mark.slow
@pytest.mark.e2e
def test_the_subprocess_run_matches_the_composed_run(cli_run, composed_run):
    (run_dir, _), (_, metrics) = cli_run, composed_run
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk["heldout"]["cam04"]["psnr"] == pytest.approx(metrics["heldout"]["cam04"]["psnr"], abs=1e-3)


@pytest.mark.slow
@pytest.mark.e2e
def test_evaluate_reproduces_the_heldout_psnr_of_a_finished_run(cli_run, capsys):
    run_dir, proc = cli_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    before = json.loads((run_dir / "metrics.json").read_text())
    (run_dir / "metrics.json").unlink()
    again = evaluate(run_dir, device="cpu")
    assert again["heldout"]["cam04"]["psnr"] == pytest.approx(before["heldout"]["cam04"]["psnr"], abs=1e-6)
    assert again["volume"]["rel_l2"] == pytest.approx(before["volume"]["rel_l2"], abs=1e-6)
    assert json.loads((run_dir / "metrics.json").read_text())["solver"] == before["solver"]
    # and the script does the same from the command line
    (run_dir / "metrics.json").unlink()
    argv = sys.argv
    sys.argv = ["scripts/evaluate.py", str(run_dir), "--device", "cpu"]
    try:  # the script installs its stop-signal handlers: pytest's own are put back after it
        with stop_handlers(), pytest.raises(SystemExit) as stop:
            runpy.run_path(str(REPO / "scripts" / "evaluate.py"), run_name="__main__")
    finally:
        sys.argv = argv
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert "held-out PSNR [dB]" in out
    assert "native resolution: not scored separately; the run works at its capture's own resolution" in out
    script = json.loads((run_dir / "metrics.json").read_text())
    assert script["heldout"]["cam04"]["psnr"] == pytest.approx(before["heldout"]["cam04"]["psnr"], abs=1e-6)


def test_evaluate_names_a_folder_that_is_not_a_run(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.yaml"):
        evaluate(tmp_path)


@pytest.mark.slow
@pytest.mark.e2e
def test_adam_runs_through_the_command_line(cli_runs):
    run = cli_runs["adam"]
    proc = run.result()
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "adam" in proc.stdout
    check_metrics_schema(json.loads((run.run_dir / "metrics.json").read_text()), "adam")


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("holdout, named", [
    ("[cam09]", "cam09"),
    ("[cam00,cam01,cam02,cam03,cam04]", "every view"),
    ("[7]", "view index 7"),
])
def test_a_bad_holdout_is_refused_with_a_message_naming_it(tmp_path, holdout, named):
    with pytest.raises(SceneError, match=named) as err:
        reconstruct(tiny_config(*SMALLER, f"holdout={holdout}"), tmp_path)
    assert "holdout" in str(err.value)
    assert not (tmp_path / "density.npz").exists()


def test_holdout_takes_names_indices_and_negative_indices(small_scene):
    assert small_scene.split(None) == ([0, 1, 2, 3, 4], [5])
    assert small_scene.split(["cam02", 4]) == ([0, 1, 3, 5], [2, 4])
    assert small_scene.split([-1, "cam05"]) == ([0, 1, 2, 3, 4], [5])
    assert small_scene.split("3") == ([0, 1, 2, 4, 5], [3])


@pytest.mark.slow
def test_both_backends_reconstruct_the_same_volume(tmp_path, monkeypatch):
    # the same step for both (the matrix-free solvers' own is a cheaper upper bound of ||A||^2):
    # what is compared is the operator
    monkeypatch.setattr(MatrixFreeOperator, "costly_products", False)
    runs = {}
    for backend in ("matrix_free", "assembled"):
        cfg = tiny_config(*SMALLER, f"projector.backend={backend}", "solver.max_iters=5")
        runs[backend] = reconstruct(cfg, tmp_path / backend)
    a = np.load(tmp_path / "matrix_free" / "density.npz")["density"]
    b = np.load(tmp_path / "assembled" / "density.npz")["density"]
    assert b.max() > 0
    assert np.abs(a - b).max() <= 1e-3 * b.max()
    assert runs["matrix_free"]["solver"]["objective"] == pytest.approx(
        runs["assembled"]["solver"]["objective"], rel=1e-4)
