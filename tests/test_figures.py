"""Pictures on tiny volumes: values, orientation and files read back with their own readers."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.geometry.axes import turn_from_y, up_vector
from flamerecon.geometry.cameras import camera_centers, project_points
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.outputs.export import save_density
from flamerecon.outputs.figures import (
    BAR_LABEL_PX,
    BAR_PX,
    TITLE_PX,
    brightest_index,
    centroid_index,
    figure_layout,
    framing_distance,
    grid_of,
    heldout_figure,
    hull_masks,
    montage,
    orbit_cameras,
    overlay_mask,
    project_along,
    render_views,
    slice_panels,
    slices_figure,
    support_box,
    to_rgb8,
    top_view,
    turntable_frames,
    views_around,
    write_gif,
    write_mp4,
    write_png,
)
from tests.helpers import repo_env, tiny_synthetic

REPO = Path(__file__).resolve().parents[1]
LO = np.array([0.0, 0.0, 0.0])
HI = np.array([2.0, 4.0, 1.0])  # nx, ny, nz = 4, 8, 2 -> voxel size 0.5 in every direction


def _blob() -> np.ndarray:
    """(1, nz=2, ny=8, nx=4) with one bright voxel at (k, j, i) = (1, 6, 3)."""
    vol = np.zeros((1, 2, 8, 4), dtype=np.float32)
    vol[0, 1, 6, 3] = 2.0
    vol[0, 0, 0, 0] = 1.0
    return vol


def test_project_along_is_line_integral_in_world_units():
    vol = _blob()
    along_y = project_along(vol, LO, HI, "y")
    assert along_y.shape == (1, 2, 4)  # (C, nz, nx)
    assert along_y[0, 1, 3] == pytest.approx(2.0 * 0.5)
    assert along_y.sum() == pytest.approx(vol.sum() * 0.5)
    assert project_along(vol, LO, HI, "x").shape == (1, 2, 8)
    assert project_along(torch.from_numpy(vol), LO, HI, "z")[0, 6, 3] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="axis"):
        project_along(vol, LO, HI, "up")


def test_top_view_and_to_rgb8():
    img = top_view(_blob(), LO, HI, up="y")
    assert img.shape == (2, 4, 3) and img.dtype == np.uint8
    brightest = np.unravel_index(img.sum(axis=2).argmax(), img.shape[:2])
    assert brightest == (1, 3)  # row = z index, column = x index
    rgb = to_rgb8(np.stack([np.full((2, 2), v) for v in (1.0, 0.5, 0.0)]))
    assert rgb[0, 0].tolist() == [255, 128, 0]
    # an empty volume maps to the colormap's bottom colour everywhere (no division by zero)
    bottom = cv2.applyColorMap(np.zeros((1, 1), np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]
    assert (to_rgb8(np.zeros((1, 3, 3))) == bottom).all()


def test_slices_figure_png(tmp_path):
    pytest.importorskip("matplotlib")
    path = slices_figure(tmp_path / "slices.png", _blob(), LO, HI, index=(3, 6, 1))
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] > img.shape[0] > 100
    with pytest.raises(ValueError, match="outside"):
        slices_figure(tmp_path / "bad.png", _blob(), LO, HI, index=(4, 0, 0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slices.png"]


def test_overlay_mask_tints_inside_and_outlines():
    image = np.zeros((3, 20, 30), dtype=np.float32)
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:15, 10:20] = True
    out = overlay_mask(image, mask, color=(0, 255, 0), alpha=0.5)
    assert out.shape == (20, 30, 3)
    assert out[10, 15].tolist() == [0, 128, 0]  # inside: half-tinted
    assert out[5, 15].tolist() == [0, 255, 0]  # border: full outline
    assert out[2, 2].tolist() == [0, 0, 0]  # outside: untouched
    with pytest.raises(ValueError, match="mask"):
        overlay_mask(image, mask[:10])


def test_montage_layout():
    tiles = [np.full((4, 5, 3), 10 * n, dtype=np.uint8) for n in range(5)]
    sheet = montage(tiles, columns=3)
    assert sheet.shape == (8, 15, 3)
    assert sheet[5, 6, 0] == 40 and sheet[5, 12, 0] == 0  # tile 4 at row 1 col 1; empty slot


def test_png_mp4_gif_read_back(tmp_path):
    frames = [np.full((32, 48, 3), (20 * t, 100, 200 - 20 * t), dtype=np.uint8) for t in range(6)]
    write_png(tmp_path / "f.png", frames[2])
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "f.png"))[..., ::-1], frames[2])

    write_mp4(tmp_path / "t.mp4", frames, fps=10)
    capture = cv2.VideoCapture(str(tmp_path / "t.mp4"))
    assert capture.get(cv2.CAP_PROP_FRAME_COUNT) == 6
    assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (48, 32)
    ok, first = capture.read()
    capture.release()
    assert ok and np.abs(first[..., ::-1].astype(int) - frames[0]).mean() < 8  # lossy codec

    from PIL import Image

    write_gif(tmp_path / "t.gif", frames, fps=10)
    with Image.open(tmp_path / "t.gif") as gif:
        assert gif.n_frames == 6 and gif.size == (48, 32)
        gif.seek(3)
        assert np.abs(np.asarray(gif.convert("RGB")).astype(int) - frames[3]).max() <= 8
    with pytest.raises(ValueError, match="frame 1"):
        write_gif(tmp_path / "bad.gif", [frames[0], frames[1][:8]])


def test_orbit_cameras_look_at_target_with_up_upwards():
    target = torch.tensor([0.0, 1.0, 0.0])
    cams = orbit_cameras([0.0, 90.0, 180.0], elevation_deg=30.0, distance=2.0, target=target,
                         width=64, height=48, fov_deg=40.0)
    centres = camera_centers(cams)
    np.testing.assert_allclose(torch.linalg.norm(centres - target, dim=1), 2.0, rtol=1e-5)
    np.testing.assert_allclose(centres[:, 1], 1.0 + 2.0 * np.sin(np.radians(30)), rtol=1e-5)
    np.testing.assert_allclose(centres[0], [0.0, 2.0, np.sqrt(3)], atol=1e-5)  # azimuth 0: +z
    np.testing.assert_allclose(centres[1], [np.sqrt(3), 2.0, 0.0], atol=1e-5)  # 90: +x
    uv, depth = project_points(cams, torch.stack([target, target + torch.tensor([0, 0.2, 0])]))
    np.testing.assert_allclose(uv[:, 0], [[32.0, 24.0]] * 3, atol=1e-4)  # target at the centre
    assert (uv[:, 1, 1] < 24.0).all()  # a point above the target appears above the centre
    assert (depth > 0).all()


def test_orbit_cameras_take_azimuths_as_a_number_a_list_an_array_or_a_tensor():
    given = [45, np.int64(45), [45.0], np.array([45.0]), torch.tensor([45.0]), torch.tensor(45.0)]
    centres = [camera_centers(orbit_cameras(a, 10.0, 2.0, (0.0, 0.0, 0.0))) for a in given]
    for c in centres:
        np.testing.assert_allclose(c, centres[0], atol=1e-6)


def test_framing_distance_sees_the_whole_box():
    lo, hi = np.array([-1.0, 0.0, -1.0]), np.array([1.0, 3.0, 1.0])
    dist = framing_distance(lo, hi, fov_deg=40.0)
    cams = orbit_cameras(np.arange(0, 360, 45), 20.0, dist, (lo + hi) / 2, 80, 80, 40.0)
    corners = torch.tensor([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=torch.float32)
    uv, _ = project_points(cams, corners)
    assert (uv >= 0).all() and (uv <= 80).all()


# --- renders through the projector -------------------------------------------------------------

BOX = (np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5]))


def _cube(n: int = 8) -> torch.Tensor:
    return torch.ones(1, n, n, n)


def _off_centre_blob(n: int = 12) -> torch.Tensor:
    """(1, n, n, n) uniform small density plus a bright block on the +x side."""
    vol = torch.full((1, n, n, n), 0.05)
    vol[0, n // 2 - 1:n // 2 + 1, n // 2 - 1:n // 2 + 1, n - 3:n - 1] = 1.0
    return vol


def test_render_views_integrates_in_world_units():
    cams = orbit_cameras([0.0, 90.0], 0.0, 3.0, (0, 0, 0), width=33, height=33, fov_deg=30)
    images = render_views(_cube(), *BOX, cams)
    assert images.shape == (2, 1, 33, 33)
    # the centre ray crosses the unit cube along its axis: integral of 1 over length 1
    np.testing.assert_allclose(images[:, 0, 16, 16], [1.0, 1.0], rtol=2e-2)
    assert images[:, 0, 0, 0].abs().max() == 0  # corner rays miss the box


def test_render_orientation_left_right_flip_on_opposite_sides():
    cams = orbit_cameras([0.0, 180.0], 0.0, 3.0, (0, 0, 0), width=41, height=41, fov_deg=30)
    images = render_views(_off_centre_blob(), *BOX, cams)[:, 0]
    column_mass = images.sum(dim=1)  # (B, W)
    centroid = (column_mass * (torch.arange(41) + 0.5)).sum(1) / column_mass.sum(1)
    assert centroid[0] > 20.5 > centroid[1]  # +x to the right seen from +z, left from -z


def test_views_around_and_turntable_shapes():
    sheet = views_around(_off_centre_blob(), *BOX, n=10, width=24, height=16, columns=5)
    assert sheet.shape == (32, 120, 3) and sheet.max() > 0
    frames = turntable_frames(_off_centre_blob(), *BOX, n_frames=4, width=24, height=16)
    assert len(frames) == 4 and frames[0].shape == (16, 24, 3)
    assert not np.array_equal(frames[1], frames[3])  # 90 and 270 degrees differ


def test_hull_masks_and_overlay():
    hull = torch.zeros(8, 8, 8, dtype=torch.bool)
    hull[2:6, 2:6, 2:6] = True
    cams = orbit_cameras([0.0], 0.0, 3.0, (0, 0, 0), width=33, height=33, fov_deg=30)
    masks = hull_masks(hull, grid_of(_cube(), *BOX), cams)
    assert masks.shape == (1, 33, 33)
    assert masks[0, 16, 16] and not masks[0, 2, 2]
    out = overlay_mask(np.zeros((3, 33, 33), np.float32), masks[0].numpy())
    assert out[16, 16, 1] > 0 and out[2, 2].sum() == 0


def test_the_heldout_figure_has_titles_and_a_colour_bar_for_the_error():
    rendered = torch.full((3, 240, 300), 0.5)
    captured = rendered.clone()
    captured[:, 0, 0] = 1.0  # one wrong pixel, error 0.5
    figure = heldout_figure(rendered, captured, "cam03")
    assert figure.shape == (TITLE_PX + 240, 3 * 300 + BAR_PX + BAR_LABEL_PX, 3) and figure.dtype == np.uint8
    assert figure[:TITLE_PX, :900].max() > 128  # "rendered cam03", "captured", "|error|" written above
    panels = figure[TITLE_PX:]
    assert (panels[5:, :300] == panels[5:, 300:600]).all()
    error = panels[:, 600:900]
    assert error[0, 0].sum() > error[20, 20].sum()  # the one wrong pixel stands out
    bar = panels[:, 900:900 + BAR_PX].astype(int).sum(-1)
    assert bar[0, 0] > bar[len(bar) // 2, 0] > bar[-1, 0]  # bright (the largest error) at the top
    np.testing.assert_array_equal(panels[0, 600 + 0], panels[0, 900])  # the bar's top is that error's colour
    assert figure[TITLE_PX:, 900 + BAR_PX:].max() > 128  # the scale's labels


@pytest.mark.parametrize("height, width", [(96, 96), (48, 64), (1920, 1080)])
def test_the_heldout_figure_reads_at_any_capture_size(height, width):
    """A small capture's panels are enlarged by a whole factor to at least 240 px (each pixel a
    block, its values kept); a full-resolution one keeps its size and its titles grow with it."""
    rendered = torch.rand(1, height, width)
    figure = heldout_figure(rendered, rendered, "cam12", 31.5, 20.1)
    layout = figure_layout(height, width)
    H, W = height * layout.scale, width * layout.scale
    assert H >= 240 and (layout.scale == 1 or (height * (layout.scale - 1) < 240))
    assert figure.shape[1] == 3 * W + layout.bar_px + layout.bar_label_px
    strip = figure.shape[0] - H
    assert strip in (layout.title_px, 2 * layout.title_px) and layout.title_px >= TITLE_PX * H / 240 - 1
    shown = figure[strip:, :W, 0].astype(float)
    expected = np.repeat(np.repeat((rendered[0].numpy() * 255 + 0.5).astype(np.uint8), layout.scale, 0), layout.scale, 1)
    np.testing.assert_array_equal(shown, expected)
    lit = (figure[:strip, :W] > 128).any(-1)
    assert lit.any(1).sum() >= 0.3 * layout.title_px  # the title's letters are as tall as the strip allows


def test_slices_pass_through_the_centre_of_mass_upright():
    vol = np.zeros((1, 2, 8, 4), dtype=np.float32)
    vol[0, 1, 5:7, 3] = 1.0  # a short upright bar off the box centre, at (i, k) = (3, 1), j = 5..6
    assert centroid_index(vol) in ((3, 6, 1), (3, 5, 1))
    panels = slice_panels(vol[0], LO, HI, centroid_index(vol), up="y")
    # y upward in the vertical planes, every axis running forward
    # (the horizontal plane seen from above, +y towards the viewer: x to the right, -z upwards)
    assert [(h, v) for _, h, v, _ in panels] == [((0, 1.0), (1, 1.0)), ((2, 1.0), (1, 1.0)), ((0, 1.0), (2, -1.0))]
    for plane, h, v, title in panels:
        assert plane.max() == 1.0, title  # every plane cuts the bar
        assert plane.shape == (vol.shape[3 - v[0]], vol.shape[3 - h[0]])  # rows along the vertical axis
    assert panels[0][0][5:7, 3].tolist() == [1.0, 1.0]  # the bar stands up in the xy plane


def test_the_slices_figure_has_a_colour_bar(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    made = []
    real = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (made.append(fig), real(fig, *a, **k))[1])
    slices_figure(tmp_path / "slices.png", _blob(), LO, HI)
    axes = made[0].axes
    assert len(axes) == 4  # three planes and the colour bar
    assert [a.get_xlabel()[0] + a.get_ylabel()[0] for a in axes[:3]] == ["xy", "zy", "xz"]
    assert all(a.get_xlabel().endswith(" (world units)") for a in axes[:3])
    assert axes[3].get_ylabel() == "density (image units per world unit)"
    assert "brightest region" in made[0].get_suptitle()


def test_support_box_and_empty_volume():
    vol = torch.zeros(1, 4, 4, 4)
    vol[0, 1, 2, 3] = 5.0  # (k, j, i)
    near, far = support_box(vol, *BOX)
    np.testing.assert_allclose(near, [0.25, 0.0, -0.25])
    np.testing.assert_allclose(far, [0.5, 0.25, 0.0])
    near, far = support_box(torch.zeros(1, 4, 4, 4), *BOX)
    np.testing.assert_allclose(near, BOX[0])


def _run_render(*args) -> subprocess.CompletedProcess:
    env = repo_env()
    return subprocess.run([sys.executable, str(REPO / "scripts" / "render.py"), *map(str, args)],
                          check=False, capture_output=True, text=True, env=env)


@pytest.mark.slow
@pytest.mark.e2e
def test_render_script_orbit_calibration_turntable_figures(tmp_path):
    pytest.importorskip("matplotlib")
    save_density(tmp_path / "density.npz", _off_centre_blob(10).repeat(3, 1, 1, 1), *BOX, ["a"])
    cams = orbit_cameras([45.0], 10.0, 3.0, (0, 0, 0), width=20, height=16, fov_deg=30)
    (tmp_path / "cameras.json").write_text(json.dumps({"cameras": [{
        "name": "side", "K": cams.intrinsics[0, :3, :3].tolist(),
        "world_to_camera": cams.extrinsics[0].tolist(), "width": 20, "height": 16}]}))
    proc = _run_render(tmp_path, "--camera", "orbit:30,10", "--camera", "orbit:0,0,3",
                       "--camera", tmp_path / "cameras.json", "--turntable", "3", "--figures",
                       "--width", "24", "--height", "16", "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    renders = tmp_path / "renders"
    names = sorted(p.name for p in renders.iterdir())
    framed = [n for n in names if n.startswith("orbit_az30_el10_d")]  # distance chosen to frame
    assert len(framed) == 1
    assert set(names) - set(framed) == {"orbit_az0_el0_d3.png", "camera_side.png", "turntable.mp4",
                                        "turntable.gif", "top_view.png", "views_10.png",
                                        "slices.png"}
    assert cv2.imread(str(renders / "camera_side.png")).shape == (16, 20, 3)
    assert cv2.imread(str(renders / "views_10.png")).shape == (32, 120, 3)
    # the calibration-file camera renders what render_views gives for the same camera
    expected = to_rgb8(render_views(_off_centre_blob(10).repeat(3, 1, 1, 1), *BOX, cams)[0])
    np.testing.assert_array_equal(cv2.imread(str(renders / "camera_side.png"))[..., ::-1], expected)


@pytest.mark.parametrize(("args", "message"), [
    (["--camera", "orbit:30"], "orbit:ANGLE,ELEV"),
    (["--camera", "orbit:a,b"], "not numbers"),
    (["--camera", "CAMFILE"], "'K'"),
])
def test_render_script_errors_name_the_problem(tmp_path, capsys, args, message):
    spec = importlib.util.spec_from_file_location("render_script", REPO / "scripts" / "render.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    save_density(tmp_path / "density.npz", _cube(4), *BOX, [])
    (tmp_path / "cams.json").write_text(json.dumps([{"name": "c", "width": 4, "height": 4}]))
    args = [str(tmp_path / "cams.json") if a == "CAMFILE" else a for a in args]
    assert script.main([str(tmp_path), *args]) == 2
    assert message in capsys.readouterr().err


def test_a_held_out_figure_carries_its_psnr_and_the_black_floor(monkeypatch, tmp_path):
    """renders/VIEW.png is read alone: its title holds the view's PSNR (as metrics.json has it)
    and the black image's."""
    from flamerecon.evaluate import scores as scores_module
    from flamerecon.evaluate.scores import score, write_renders

    seen = {}

    def figure(rendered, captured, view, psnr=None, black=None):
        seen[view] = (psnr, black)
        return np.zeros((4, 4, 3), np.uint8)

    monkeypatch.setattr(scores_module, "heldout_figure", figure)
    scene = tiny_synthetic()
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    volume = torch.rand(3, *grid.shape) * 0.1
    metrics, held = score(scene, volume, grid, [0, 1, 2, 3], [4], 0.5)
    write_renders(tmp_path, held, scene, [4])
    assert seen["cam04"] == pytest.approx((metrics["heldout"]["cam04"]["psnr"], metrics["heldout"]["cam04"]["psnr_black"]))


def test_the_top_view_is_a_figure_with_axes_and_a_colour_bar(tmp_path):
    pytest.importorskip("matplotlib")
    from flamerecon.outputs.figures import top_view_figure

    density = np.zeros((3, 6, 8, 10), np.float32)
    density[:, 2:4, :, 3:7] = 1.0
    path = top_view_figure(tmp_path / "top_view.png", density, (0, 0, 0), (1.0, 0.8, 0.6), title="run")
    image = cv2.imread(str(path))
    assert image.shape == (440, 520, 3)  # a labelled figure, not the 8 x 10 projection blown up
    assert (image[..., 2].astype(int) - image[..., 0] > 60).any()  # the inferno colours of the density


def test_slices_cut_the_brightest_region_not_the_empty_centre_of_mass():
    """Two lobes side by side: the centre of mass falls in the empty gap between them, the
    slices go through the brighter lobe."""
    vol = np.zeros((1, 12, 12, 24), dtype=np.float32)
    vol[0, 4:8, 4:8, 2:6] = 1.0
    vol[0, 4:8, 4:8, 18:22] = 1.5
    i, j, k = centroid_index(vol)
    assert vol[0, k, j, i] == 0  # the gap
    i, j, k = brightest_index(vol)
    assert 18 <= i < 22 and 4 <= j < 8 and 4 <= k < 8
    assert all(plane.max() > 0 for plane, *_ in slice_panels(vol[0], LO, HI, (i, j, k), up="+y"))


@pytest.mark.parametrize("up", ["+z", "-x", "-y"])
def test_a_scene_turned_to_another_up_draws_the_same_top_view_slices_and_orbits(up):
    """The synthetic flame's truth turned from y-up to ``up`` (box and volume turned together):
    the top view and the slices are the same pictures, and so are the orbit renders."""
    scene = fr.load_scene("synthetic", width=40, height=30, phantom_resolution=32)
    turned = fr.load_scene("synthetic", width=40, height=30, phantom_resolution=32, up=up)
    box, box2 = (scene.bbox_min, scene.bbox_max), (turned.bbox_min, turned.bbox_max)
    np.testing.assert_array_equal(top_view(turned.truth, *box2, up=up), top_view(scene.truth, *box, up="+y"))
    index = brightest_index(scene.truth)
    Q = turn_from_y(up).numpy()
    centre = np.asarray(box[0]) + (np.asarray(index) + 0.5) * (np.subtract(box[1], box[0]) / scene.truth.shape[:0:-1])
    moved = Q @ centre
    index2 = tuple(int(n) for n in np.floor((moved - box2[0]) / (np.subtract(box2[1], box2[0]) / turned.truth.shape[:0:-1])))
    one = slice_panels(scene.truth.sum(0).numpy(), np.asarray(box[0]), np.asarray(box[1]), index, "+y")
    two = slice_panels(turned.truth.sum(0).numpy(), np.asarray(box2[0]), np.asarray(box2[1]), index2, up)
    for (a, *_), (b, *_) in zip(one, two):
        np.testing.assert_array_equal(a, b)
    around = views_around(scene.truth, *box, n=4, width=24, height=16, columns=4)
    around2 = views_around(turned.truth, *box2, n=4, width=24, height=16, columns=4, up=up_vector(up))
    assert np.abs(around.astype(int) - around2.astype(int)).max() <= 2  # float noise of the renders


@pytest.mark.parametrize("up", ["+y", "-y", "+z", "-x"])
def test_the_horizontal_slice_is_seen_from_above_not_mirrored(up):
    """Right by up in the picture, its viewer stands on the up side: right x up = the up axis."""
    *_, (_, h, v, _) = slice_panels(np.zeros((4, 5, 6), np.float32), np.zeros(3), np.ones(3), (1, 1, 1), up)

    def vector(direction):
        out = np.zeros(3)
        out[direction[0]] = direction[1]
        return out

    np.testing.assert_array_equal(np.cross(vector(h), vector(v)), up_vector(up))
