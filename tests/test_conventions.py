"""A capture's conventions as scene facts: its up axis, its unit (metres per world unit) and its
frame rate, read once by the loaders (config, else the calibration file's top level, else the
cameras for the up axis) and kept on the Scene, so that nothing downstream assumes y, metres or
30 fps."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml

import flamerecon as fr
from flamerecon.geometry.axes import (
    UP_AXES,
    axis_name,
    turn_box,
    turn_from_y,
    turn_volume,
    up_from_cameras,
    up_vector,
)
from flamerecon.geometry.units import display_length, length_name
from flamerecon.scenes.base import SceneError
from tests.helpers import REPO

EXAMPLE = REPO / "examples" / "capture"
REAL = REPO.parent / "shared" / "data" / "scalarflow_real"
SMALL = {"width": 80, "height": 60, "phantom_resolution": 48}


@pytest.mark.parametrize("given, name", [("y", "+y"), ("+Y", "+y"), ("-z", "-z"), (" x ", "+x"),
                                         ("up", None), ("", None), (1, None), ("+w", None)])
def test_axis_names_are_read_leniently_and_normalised(given, name):
    assert axis_name(given) == name


@pytest.mark.parametrize("up", UP_AXES)
def test_turning_carries_y_onto_up_as_a_proper_rotation(up):
    Q = turn_from_y(up)
    assert torch.allclose(Q @ Q.T, torch.eye(3, dtype=torch.float64))
    assert float(torch.linalg.det(Q)) == pytest.approx(1.0)
    assert torch.equal(Q @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                       torch.tensor(up_vector(up), dtype=torch.float64))


def test_a_turned_volume_holds_each_value_at_its_turned_position():
    """Voxel centres move with the world: the value at world point p of the y-up volume sits at
    Q p in the turned one (checked through the grids' own cell centres)."""
    grid = fr.VoxelGrid.from_box((-0.5, 0.0, -0.25), (0.5, 1.5, 0.25), 6)
    volume = torch.rand(2, *grid.shape)
    for up in UP_AXES:
        Q = turn_from_y(up)
        turned_grid = fr.VoxelGrid.from_box(*turn_box(grid.bbox_min, grid.bbox_max, Q), 6)
        turned = turn_volume(volume, Q)
        assert turned.shape[1:] == turned_grid.shape
        centres = grid.centers().double().reshape(-1, 3)           # (N, 3) world xyz, x fastest
        moved = centres @ Q.T
        lo = torch.tensor(turned_grid.bbox_min, dtype=torch.float64)
        index = torch.floor((moved - lo) / turned_grid.voxel_size().double()).long()  # (i, j, k)
        got = turned[:, index[:, 2], index[:, 1], index[:, 0]]
        assert torch.equal(got, volume.reshape(2, -1)), up


@pytest.mark.parametrize("up", ["+y", "+z", "-x"])
def test_cameras_say_which_axis_they_show_upwards(up):
    scene = fr.load_scene("synthetic", up=up, **SMALL)
    assert up_from_cameras(scene.cameras.extrinsics) == (up, pytest.approx(0.0, abs=1e-3))
    # a rig mounted upside down shows the opposite axis: the cameras alone cannot always say
    flipped = scene.cameras.extrinsics.clone()
    flipped[:, :2] *= -1  # each camera turned 180 degrees about its optical axis
    opposite = ("-" if up[0] == "+" else "+") + up[1]
    assert up_from_cameras(flipped)[0] == opposite


def test_cameras_that_disagree_name_no_axis():
    scene = fr.load_scene("synthetic", **SMALL)
    w2c = scene.cameras.extrinsics.clone()
    w2c[::2, :2] *= -1  # half the rig on its head
    assert up_from_cameras(w2c)[0] is None


def test_the_synthetic_flame_turned_is_the_same_capture_on_other_axes():
    """The images are the same; the box, cameras and truth turn; a reconstruction scores the
    same held-out PSNR and its density is the y-up one turned."""
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=20),
                                       solver=fr.SolverOptions().with_values(max_iters=60))
    upright = fr.load_scene("synthetic", **SMALL)
    rec = fr.reconstruct(upright, options)
    for up in ("+z", "+x"):
        scene = fr.load_scene("synthetic", up=up, **SMALL)
        assert (scene.up, scene.frame_rate, scene.unit) == (up, 30.0, None)
        assert torch.equal(scene.images, upright.images)
        Q = turn_from_y(up)
        assert (scene.bbox_min, scene.bbox_max) == turn_box(upright.bbox_min, upright.bbox_max, Q)
        assert torch.equal(scene.truth, turn_volume(upright.truth, Q))
        turned = fr.reconstruct(scene, options)
        assert fr.score(turned)["heldout"]["cam07"]["psnr"] == pytest.approx(
            fr.score(rec)["heldout"]["cam07"]["psnr"], abs=0.01)
        expected = turn_volume(rec.density, Q)
        assert float((turned.density - expected).abs().max()) < 1e-2 * float(expected.abs().max())


def _example_with(tmp_path: Path, **top) -> Path:
    root = tmp_path / "capture"
    shutil.copytree(EXAMPLE, root)
    path = root / "calibration.yaml"
    data = yaml.safe_load(path.read_text())
    data.update(top)
    path.write_text(yaml.safe_dump(data))
    return root


def test_a_calibration_file_says_its_up_unit_and_frame_rate(tmp_path):
    root = _example_with(tmp_path, up="-z", unit=0.0005, frame_rate=60)
    scene = fr.load_scene("opencv", root=str(root))
    assert (scene.up, scene.unit, scene.frame_rate) == ("-z", 0.0005, 60.0)
    assert scene.up_source.endswith("calibration.yaml: up")
    assert scene.length_unit() == "world units of 0.0005 m"
    # the config wins over the file
    scene = fr.load_scene("opencv", root=str(root), up="+x", unit=0.001, frame_rate=25)
    assert (scene.up, scene.unit, scene.frame_rate, scene.up_source) == ("+x", 0.001, 25.0, "config scene.up")


def test_a_capture_that_says_nothing_takes_its_up_from_the_cameras(tmp_path):
    scene = fr.load_scene("opencv", root=str(_example_with(tmp_path)))
    assert (scene.up, scene.unit, scene.frame_rate) == ("+y", None, None)
    assert scene.up_source.startswith("auto: the cameras' image-up direction")


@pytest.mark.parametrize("top, words", [
    ({"up": "sideways"}, "calibration.yaml: up: 'sideways' is not an axis"),
    ({"unit": -1}, "calibration.yaml: unit"),
    ({"frame_rate": 0}, "calibration.yaml: frame_rate"),
])
def test_bad_conventions_in_a_file_name_the_file_and_the_field(tmp_path, top, words):
    with pytest.raises(SceneError, match=words.replace(".", r"\.")):
        fr.load_scene("opencv", root=str(_example_with(tmp_path, **top)))


def test_cameras_at_two_frame_rates_are_refused(tmp_path):
    root = tmp_path / "pinf"
    root.mkdir()
    scene = fr.load_scene("synthetic", n_cameras=3, **SMALL)
    entries = []
    for i, name in enumerate(scene.views):
        folder = root / name
        folder.mkdir()
        fr.save_image(folder / "000000.png", scene.images[i])
        c2w = fr.geometry.cameras.opencv_w2c_to_opengl_c2w(scene.cameras.extrinsics[i]).tolist()
        entries.append({"file_name": f"{name}.mp4", "camera_angle_x": 0.8, "camera_hw": [60, 80],
                        "transform_matrix": c2w, "frame_rate": 30 if i < 2 else 60})
    (root / "info.json").write_text(json.dumps({"train_videos": entries}))
    with pytest.raises(SceneError, match=r"train_videos\[2\]\.frame_rate: the cameras run at 30 and 60 frames"):
        fr.load_scene("scalarflow", root=str(root), frame=0)


@pytest.mark.parametrize("unit, name", [(1.0, "m"), (0.001, "mm"), (0.01, "cm"), (None, "world units"),
                                        (0.0005, "world units of 0.0005 m")])
def test_lengths_are_named_by_the_unit(unit, name):
    assert length_name(unit) == name


@pytest.mark.skipif(not (REAL / "info.json").is_file(), reason=f"the ScalarFlow capture is not in {REAL}")
def test_scalarflow_is_y_up_metric_at_its_own_frame_rate():
    scene = fr.load_scene("scalarflow")
    assert (scene.up, scene.unit, scene.frame_rate) == ("+y", 1.0, 30.0)


@pytest.mark.parametrize("unit, extent, expected", [(None, 2.0, (1.0, "world units")), (1.0, 0.74, (100.0, "cm")),
                                                    (0.0005, 96, (0.5, "mm")), (1.0, 3.0, (1.0, "m"))])
def test_figures_show_lengths_in_a_unit_that_suits_them(unit, extent, expected):
    factor, name = display_length(unit, extent)
    assert (pytest.approx(factor), name) == expected
