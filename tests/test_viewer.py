"""``flamerecon view`` (flamerecon/viewer/): its camera conventions against flamerecon's own, what it
loads from a run and a multirun, the command's clean stop on Ctrl-C, ``fr.view``, and the page in
a real browser: headless Chromium (Debian's ``chromium``) driven by Playwright, waiting for the
first render, moving the camera through the page, toggling slices and the iso-surface. The
browser test writes the README's screenshot where ``FLAMERECON_README_SHOTS`` names a folder.
Skipped with the reason where viser, Playwright or Chromium is missing."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.errors import RunFolderError
from flamerecon.geometry.cameras import look_at_camera, project_points
from flamerecon.run.pipeline import reconstruct
from flamerecon.viewer.content import frames_of
from flamerecon.viewer.server import Viewer, browser_camera, rotation_wxyz
from tests.helpers import REPO, TINY, repo_env

needs_viser = pytest.mark.skipif(find_spec("viser") is None,
                                 reason="the viewer needs viser: pip install 'flamerecon[view]'")

CHROMIUM = os.environ.get("FLAMERECON_CHROMIUM", "/usr/bin/chromium")
#: the flags a shared, offline machine needs (no GPU, no sandbox as root, nothing fetched)
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--enable-unsafe-swiftshader"]
#: the run the browser sees: the synthetic flame, smaller than the default run
SHOWN = ["scene.width=160", "scene.height=120", "scene.phantom_resolution=48", "grid.resolution=32",
         "solver.max_iters=150", "log.eval_every=0", "device=cpu"]


def cli_run_folder(run_dir: Path, overrides: list[str]) -> Path:
    """A run folder as ``python train.py`` leaves it (with ``.hydra/config.yaml``), made in
    this process."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    reconstruct(cfg, run_dir)
    (run_dir / ".hydra").mkdir(exist_ok=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    return run_dir


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    return cli_run_folder(tmp_path_factory.mktemp("tiny_run"), [*TINY, "solver.max_iters=10", "log.eval_every=0"])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(condition, seconds: float, what: str):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        found = condition()
        if found:
            return found
        time.sleep(0.1)
    pytest.fail(f"waited {seconds:.0f} s for {what}")


# --- conventions ------------------------------------------------------------------------------


def test_a_browser_camera_is_the_same_camera_to_flamerecon():
    """viser's camera (camera-to-world wxyz and position, OpenCV axes, vertical fov) built into
    a kornia camera sees what flamerecon's look_at_camera sees: the same extrinsics, and the
    target at the image centre."""
    eye, target = torch.tensor([0.7, 1.9, -2.5]), torch.tensor([0.1, 0.4, 0.2])
    reference = look_at_camera(eye, target, (0.0, 1.0, 0.0), width=64, height=48, fov_deg=50.0)
    w2c = reference.extrinsics[0].double().numpy()
    camera = browser_camera(rotation_wxyz(w2c[:3, :3].T), eye.numpy(), np.radians(50.0), 64, 48)
    torch.testing.assert_close(camera.extrinsics, reference.extrinsics, atol=1e-5, rtol=0)
    torch.testing.assert_close(camera.intrinsics, reference.intrinsics, atol=1e-4, rtol=0)
    uv, _ = project_points(camera, target[None])
    torch.testing.assert_close(uv.reshape(2), torch.tensor([32.0, 24.0]), atol=1e-3, rtol=0)


@pytest.mark.parametrize("seed", range(4))
def test_rotation_wxyz_round_trips_through_the_matrix(seed):
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    rotation = browser_camera(q, np.zeros(3), 1.0, 8, 8).extrinsics[0, :3, :3].double().numpy().T
    back = rotation_wxyz(rotation)
    np.testing.assert_allclose(back * np.sign(back[0]), q * np.sign(q[0]), atol=1e-6)


# --- what it loads ----------------------------------------------------------------------------


def test_a_run_folder_is_one_frame_with_its_scores(tiny_run):
    frames = frames_of(tiny_run, "cpu")
    assert len(frames) == 1
    frame = frames[0]
    saved = np.load(tiny_run / "density.npz")["density"]
    np.testing.assert_array_equal(frame.density.numpy(), saved)
    assert [frame.scene.views[v] for v in frame.holdout] == ["cam04"]
    assert frame.scores["cam04"]["psnr"] > frame.scores["cam04"]["psnr_black"]
    np.testing.assert_allclose(frame.up, [0, 1, 0], atol=0.2)  # the synthetic rig stands upright


def test_a_multirun_is_a_sequence_in_frame_order(tiny_run, tmp_path):
    for job, frame in (("0", 7), ("1", 3)):
        shutil.copytree(tiny_run, tmp_path / job)
        config = OmegaConf.load(tmp_path / job / ".hydra" / "config.yaml")
        config.scene.frame = frame  # as python train.py -m scene.frame=7,3 leaves it
        OmegaConf.save(config, tmp_path / job / ".hydra" / "config.yaml")
    frames = frames_of(tmp_path, "cpu")
    assert frames.labels == ["frame 3", "frame 7"]
    assert frames[1].label == "frame 7" and frames[1].density.shape == frames[0].density.shape


def test_a_folder_that_holds_no_run_is_named(tmp_path):
    with pytest.raises(RunFolderError, match=rf"{tmp_path}: neither a run folder"):
        frames_of(tmp_path)
    with pytest.raises(RunFolderError, match="nowhere: no such folder"):
        frames_of(tmp_path / "nowhere")


# --- the server -------------------------------------------------------------------------------


@needs_viser
def test_fr_view_serves_the_page_and_stops(tiny_run):
    import flamerecon as fr

    viewer = fr.view(fr.load_run(tiny_run, "cpu"), port=free_port(), device="cpu")
    try:
        page = urllib.request.urlopen(viewer.url, timeout=30).read().decode()
        assert "<html" in page.lower() and len(viewer.frames) == 1
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(viewer.url, timeout=5)


@needs_viser
@pytest.mark.e2e
def test_the_command_prints_where_to_look_and_stops_on_ctrl_c(tiny_run):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "flamerecon", "view", str(tiny_run), "--port", str(port),
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=repo_env(), cwd=REPO)
    try:
        lines = []
        while not any("Ctrl-C" in line for line in lines):
            line = proc.stdout.readline()
            assert line, f"the viewer ended early: {proc.stderr.read()[-2000:]}"
            lines.append(line)
        text = "".join(lines)
        assert f"open http://localhost:{port}" in text
        assert f"ssh -N -L {port}:localhost:{port}" in text
        assert "<html" in urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30).read().decode().lower()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "flamerecon view: stopped" in out and "Traceback" not in err


def test_a_bad_folder_ends_the_command_in_one_line(tmp_path):
    from flamerecon.viewer.command import main

    assert main([str(tmp_path / "missing"), "--port", str(free_port())]) == 2


# --- in a real browser ------------------------------------------------------------------------


def chromium_missing() -> str | None:
    if not Path(CHROMIUM).is_file():
        return f"no Chromium at {CHROMIUM} (apt-get install chromium; or set FLAMERECON_CHROMIUM)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright is not installed: pip install 'flamerecon[view]'"
    return None


def screenshot(page) -> np.ndarray:
    """The page as (H, W, 3) uint8 RGB."""
    import cv2

    png = np.frombuffer(page.screenshot(), np.uint8)
    return cv2.imdecode(png, cv2.IMREAD_COLOR)[..., ::-1]


def flame_pixels(image: np.ndarray) -> float:
    """The share of the scene's part of a screenshot (left of the panel) in flame colours."""
    scene = image[:, :700].astype(int)
    return float(((scene[..., 0] > 90) & (scene[..., 0] > scene[..., 2] + 40)).mean())


@needs_viser
@pytest.mark.slow
@pytest.mark.e2e
def test_the_viewer_in_a_real_browser(tmp_path):
    if chromium_missing():
        pytest.skip(chromium_missing())
    from playwright.sync_api import sync_playwright

    run = cli_run_folder(tmp_path / "run", SHOWN)
    viewer = Viewer(run, port=free_port(), device="cpu", log=print)
    try:
        with sync_playwright() as driver:
            browser = driver.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS, headless=True)
            page = browser.new_page(viewport={"width": 1100, "height": 700})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=60_000)

            def full_renders() -> int:
                return sum(r.kind == "full" for r in viewer.renders)

            wait_for(full_renders, 120, "the first full-resolution render")
            client = next(iter(viewer.clients.values())).client
            time.sleep(1.5)  # the image's way to the page
            for close in page.locator("button.mantine-Notification-closeButton").all():
                close.click()  # viser's note that WebGL runs in software here
            time.sleep(0.5)
            first = screenshot(page)
            assert first[:, :700].std() > 10, "the page is blank"
            assert flame_pixels(first) > 0.01, "no flame on the page"
            shots = os.environ.get("FLAMERECON_README_SHOTS")
            if shots:
                import cv2

                cv2.imwrite(str(Path(shots) / "viewer.png"), first[..., ::-1])

            before, renders = client.camera.position.copy(), full_renders()
            page.mouse.move(350, 350)
            page.mouse.down()
            page.mouse.move(520, 320, steps=12)
            page.mouse.up()
            wait_for(lambda: full_renders() > renders and np.linalg.norm(client.camera.position - before) > 1e-3,
                     120, "a full render after the camera moved")
            time.sleep(1.5)
            moved = screenshot(page)
            assert np.abs(moved[:, :700].astype(int) - first[:, :700]).mean() > 2, "the view did not change"
            assert flame_pixels(moved) > 0.005, "the flame left the view"

            page.get_by_text("slices", exact=True).click()
            wait_for(lambda: viewer.show_slices.value, 30, "the slices' toggle")
            page.get_by_text("iso-surface", exact=True).click()
            wait_for(lambda: viewer.show_mesh.value, 30, "the iso-surface's toggle")
            time.sleep(2)
            toggled = screenshot(page)
            assert np.abs(toggled[:, :700].astype(int) - moved[:, :700]).mean() > 1, "the toggles show nothing"
            if shots:
                import cv2

                cv2.imwrite(str(Path(shots) / "viewer_slices.png"), toggled[..., ::-1])
            browser.close()
    finally:
        viewer.stop()
