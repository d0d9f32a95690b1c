"""One operator per capture: a frame's assembled operator taken from its capture's region
operator (the rows and columns it keeps) is the operator it would assemble itself, entry for
entry; a region is read only under the same cameras, grid and image size; ``projector.reuse``
says whether a region is built (``true``), only read (``auto``) or neither (``false``)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from flamerecon.fit import capture_operator
from flamerecon.fit.build import build
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.operators import compiled, stored
from flamerecon.scenes import load_scene
from tests.conftest import SMALL_SCENE

pytestmark = pytest.mark.skipif(not compiled.available("cpu"), reason="numba is not installed: no region operators")


def options(folder, reuse) -> ReconstructionOptions:
    base = ReconstructionOptions.from_dict({"grid": {"resolution": 20}, "projector": {"backend": "assembled"}})
    return base.replace(projector=replace(base.projector, reuse=reuse),
                        calibration=replace(base.calibration, folder=str(folder)))


def same_entries(a, b) -> bool:
    return all(torch.equal(getattr(a.A, f)(), getattr(b.A, f)()) for f in ("crow_indices", "col_indices", "values"))


@pytest.fixture
def counted(monkeypatch):
    """Calls of the region's assembly and of reads from it."""
    calls = {"assembled": 0, "read": 0}
    assemble, read = capture_operator.assemble_region, stored.read_selection

    def assembling(*args):
        calls["assembled"] += 1
        return assemble(*args)

    def reading(*args):
        calls["read"] += 1
        return read(*args)

    monkeypatch.setattr(capture_operator, "assemble_region", assembling)
    monkeypatch.setattr(stored, "read_selection", reading)
    return calls


def scene_at(frame: int, shift: float = 0.0):
    scene = load_scene({**SMALL_SCENE, "frame": frame})
    if shift:  # one camera moved: another capture's rig
        E = scene.cameras.extrinsics.clone()
        E[0, 0, 3] += shift
        scene = replace(scene, cameras=replace_cameras(scene.cameras, E))
    return scene


def replace_cameras(cams, extrinsics):
    from flamerecon.geometry.cameras import make_cameras

    return make_cameras(cams.intrinsics[:, :3, :3], extrinsics, int(cams.height[0]), int(cams.width[0]))


def test_each_frame_takes_its_rows_and_columns_from_the_region_entry_for_entry(tmp_path, counted):
    on, off = options(tmp_path, True), options(tmp_path, False)
    for frame in (0, 1, 2):
        scene = scene_at(frame)
        taken, own = build(scene, on), build(scene, off)
        assert same_entries(taken.operator, own.operator)  # the frame's own operator, bit for bit
        assert taken.operator.nnz > 1000
    assert counted["assembled"] >= 1 and counted["read"] >= 1  # the region served a later frame
    assert counted["assembled"] + counted["read"] == 3
    entries = list((tmp_path / "operators").iterdir())
    assert len(entries) == 1  # one region for the capture, grown where a frame left it


def test_a_frame_that_leaves_the_region_grows_it(tmp_path, counted, monkeypatch):
    monkeypatch.setattr(capture_operator, "REGION_GROWTH", 0.0)  # the region: the first frame's hull only
    on, off = options(tmp_path, True), options(tmp_path, False)
    first = build(scene_at(0), on)
    entry = next((tmp_path / "operators").iterdir())
    before = capture_operator.read_region(entry)["hull"].clone()
    later = scene_at(5)
    taken = build(later, on)
    assert counted["assembled"] == 2  # frame 5's hull leaves frame 0's: the region grew
    grown = capture_operator.read_region(entry)["hull"]
    assert bool((grown & before).eq(before).all()) and int(grown.sum()) > int(before.sum())
    assert same_entries(taken.operator, build(later, off).operator)
    assert first.operator.shape[0] > 0


def test_auto_reads_a_region_but_builds_none_and_false_neither(tmp_path, counted):
    scene = scene_at(0)
    build(scene, options(tmp_path, "auto"))
    assert counted == {"assembled": 0, "read": 0} and not (tmp_path / "operators").exists()
    build(scene, options(tmp_path, True))
    assert counted["assembled"] == 1
    again = build(scene, options(tmp_path, "auto"))
    assert counted["read"] == 1 and same_entries(again.operator, build(scene, options(tmp_path, False)).operator)
    build(scene, options(tmp_path, False))
    assert counted["read"] == 1  # false: not even read


def test_another_rig_grid_or_image_size_never_reads_a_stale_region(tmp_path, counted):
    build(scene_at(0), options(tmp_path, True))
    moved = scene_at(0, shift=0.05)
    build(moved, options(tmp_path, "auto"))
    coarser = options(tmp_path, "auto")
    build(scene_at(0), coarser.replace(grid=replace(coarser.grid, resolution=16)))
    smaller = load_scene({**SMALL_SCENE, "width": 48, "height": 36})
    build(smaller, options(tmp_path, "auto"))
    assert counted == {"assembled": 1, "read": 0}  # each has its own key: nothing read
