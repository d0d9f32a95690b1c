"""OpenVDB export (flamerecon/outputs/vdb.py), read back by OpenVDB's own reader: its Python
bindings (Debian's python3-openvdb, module ``pyopenvdb``, or ``openvdb`` in later releases) for
the system interpreter, run as a subprocess since they are built for that Python, not this venv's.
Skipped with the reason where they are absent (``.ci/run`` installs them where it can)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from flamerecon.outputs.export import (
    Density,
    export_density,
    load_density,
    sample_origin,
    save_density,
    voxel_size,
)
from flamerecon.outputs.vdb import FILE_VERSION, vdb_bytes, write_vdb
from tests.helpers import repo_env, tiny_cfg

REPO = Path(__file__).resolve().parents[1]
#: the interpreter that has OpenVDB's Python bindings
OPENVDB_PYTHON = os.environ.get("FLAMERECON_OPENVDB_PYTHON", "/usr/bin/python3")
# Reads every grid of a .vdb with OpenVDB, prints JSON: per grid its name, class, active voxel
# count, min/max, active bounding box, where indices (0,0,0) and (1,2,3) lie in the world, and
# its values densely as nested lists over (i, j, k) from index (0, 0, 0) to argv[2] (nx, ny, nz).
READER = r"""
import json, sys
try:
    import pyopenvdb as vdb
except ImportError:
    import openvdb as vdb
import numpy as np
grids, _ = vdb.readAll(sys.argv[1])
shape = json.loads(sys.argv[2])
out = []
for g in grids:
    dense = np.zeros(shape, np.float32)
    g.copyToArray(dense, ijk=(0, 0, 0))
    out.append({"name": g.name, "class": str(g.gridClass), "active": g.activeVoxelCount(),
                "minmax": list(g.evalMinMax()), "bbox": [list(c) for c in g.evalActiveVoxelBoundingBox()],
                "world0": list(g.transform.indexToWorld((0, 0, 0))),
                "world123": list(g.transform.indexToWorld((1, 2, 3))),
                "voxel": list(g.transform.voxelSize()), "values": dense.tolist()})
print(json.dumps(out))
"""


@lru_cache(maxsize=1)
def openvdb_missing() -> str | None:
    """Why OpenVDB's reader cannot run here, or None."""
    try:
        found = subprocess.run([OPENVDB_PYTHON, "-c", "import pyopenvdb"], capture_output=True, timeout=60, check=False)
        if found.returncode != 0:
            found = subprocess.run([OPENVDB_PYTHON, "-c", "import openvdb"], capture_output=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"{OPENVDB_PYTHON} cannot run ({err}); install python3-openvdb"
    if found.returncode != 0:
        return f"OpenVDB's Python bindings are not installed for {OPENVDB_PYTHON} (apt-get install python3-openvdb)"
    return None


def read_with_openvdb(path: Path, shape_xyz) -> dict:
    """{grid name: what OpenVDB reads} (see READER), ``values`` as an array (nx, ny, nz)."""
    if openvdb_missing():
        pytest.skip(openvdb_missing())
    proc = subprocess.run([OPENVDB_PYTHON, "-c", READER, str(path), json.dumps(list(shape_xyz))],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "WARN" not in proc.stderr and "ERROR" not in proc.stderr, proc.stderr  # a misread is a warning
    return {g["name"]: {**g, "values": np.array(g["values"], np.float32)} for g in json.loads(proc.stdout)}


def sparse_volume(num_channels: int, shape=(11, 21, 13), seed=0) -> np.ndarray:
    """(C, nz, ny, nx) with distinct values, zeros outside a box (some whole 8^3 leaves empty)
    and a zero plane inside it, over several leaves and not a multiple of 8 on any axis."""
    rng = np.random.default_rng(seed)
    volume = np.zeros((num_channels, *shape), np.float32)
    volume[:, 1:10, 9:20, 2:12] = rng.random((num_channels, 9, 11, 10)) + 0.01
    volume[:, :, :, 5] = 0
    return volume


@pytest.mark.parametrize("num_channels", [1, 3])
def test_openvdb_reads_the_grids_back_exactly_in_the_world_frame(tmp_path, num_channels):
    volume = sparse_volume(num_channels)
    lo, hi = np.array([-0.5, 0.0, 1.0]), np.array([0.8, 4.2, 2.1])  # cells 0.1 x 0.2 x 0.1
    (path,) = export_density(Density(volume, lo, hi, []), tmp_path / "density", ["vdb"])
    assert path == tmp_path / "density.vdb"
    nz, ny, nx = volume.shape[1:]
    grids = read_with_openvdb(path, (nx, ny, nz))
    expected = {"density": volume.mean(0)} if num_channels > 1 else {"density": volume[0]}
    if num_channels == 3:
        expected.update(zip("RGB", volume))
    assert sorted(grids) == sorted(expected)
    origin, size = sample_origin(lo, hi, volume.shape), voxel_size(lo, hi, volume.shape)
    for name, values in expected.items():
        grid = grids[name]
        assert grid["class"] == "FOG_VOLUME" or "fog" in grid["class"].lower()
        np.testing.assert_array_equal(grid["values"], values.transpose(2, 1, 0))  # index (i, j, k) = voxel (k, j, i)
        assert grid["active"] == np.count_nonzero(values)
        assert grid["minmax"][1] == pytest.approx(float(values.max()))
        nonzero = np.argwhere(values.transpose(2, 1, 0) != 0)
        assert grid["bbox"] == [nonzero.min(0).tolist(), nonzero.max(0).tolist()]
        np.testing.assert_allclose(grid["world0"], origin, rtol=0, atol=1e-12)
        np.testing.assert_allclose(grid["world123"], origin + size * [1, 2, 3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(grid["voxel"], size, rtol=1e-12)


def test_an_empty_density_and_a_cubic_cell_read_back(tmp_path):
    empty = np.zeros((1, 4, 5, 6), np.float32)
    path = write_vdb(tmp_path / "empty.vdb", empty, [0.0, 0.0, 0.0], [0.25] * 3, ["density"])
    grid = read_with_openvdb(path, (6, 5, 4))["density"]
    assert grid["active"] == 0 and not grid["values"].any()
    np.testing.assert_allclose(grid["world123"], [0.25, 0.5, 0.75])


def test_the_file_starts_as_openvdb_files_do():
    data = vdb_bytes([("density", np.ones((2, 2, 2), np.float32))], [0, 0, 0], [1, 1, 1])
    assert data[:8] == b" BDV\0\0\0\0" and int.from_bytes(data[8:12], "little") == FILE_VERSION
    assert data[21:57].count(b"-") == 4  # the file's UUID, as text


def test_a_runs_vdb_holds_the_maximum_of_its_density(tmp_path):
    if openvdb_missing():
        pytest.skip(openvdb_missing())
    from flamerecon.run.pipeline import reconstruct

    reconstruct(tiny_cfg("export=vdb"), tmp_path)
    saved = load_density(tmp_path)
    C, nz, ny, nx = saved.density.shape
    grids = read_with_openvdb(tmp_path / "density.vdb", (nx, ny, nz))
    assert grids["density"]["minmax"][1] == pytest.approx(float(saved.density.mean(0).max() if C > 1
                                                                else saved.density.max()), rel=1e-6)
    channels = [grids[n]["minmax"][1] for n in ("RGB" if C == 3 else ["density"])]
    assert max(channels) == pytest.approx(float(saved.density.max()), rel=1e-6)


@pytest.mark.e2e
def test_the_export_script_writes_a_vdb(tmp_path):
    volume = sparse_volume(1)
    save_density(tmp_path / "density.npz", volume, [0, 0, 0], [1.3, 2.1, 1.1], ["a"])
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "export.py"), str(tmp_path), "--format", "vdb"],
                          capture_output=True, text=True, env=repo_env(), check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [str(tmp_path / "density.vdb")]
    grid = read_with_openvdb(tmp_path / "density.vdb", (13, 21, 11))["density"]
    np.testing.assert_array_equal(grid["values"], volume[0].transpose(2, 1, 0))


@pytest.mark.e2e
def test_blender_renders_the_vdb_by_the_readmes_steps(tmp_path):
    """examples/blender_flame.py (the README's three steps) in Blender, where it is installed:
    a blob of emission in the middle of the box is a bright middle on a black image."""
    import shutil

    import cv2

    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Blender is not installed (apt-get install blender)")
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n) for n in (12, 20, 12)), indexing="ij")
    blob = np.exp(-4 * (x**2 + (y / 1.5) ** 2 + z**2)).astype(np.float32)[None]
    save_density(tmp_path / "density.npz", blob, [0, 0, 0], [0.6, 1.0, 0.6], ["a"])
    export_density(load_density(tmp_path), tmp_path / "density", ["vdb"])
    proc = subprocess.run([blender, "-b", "--python-exit-code", "1", "-P", str(REPO / "examples" / "blender_flame.py"),
                           "--", str(tmp_path / "density.vdb"), str(tmp_path / "flame.png"), "--size", "48x64",
                           "--samples", "4"], capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    image = cv2.imread(str(tmp_path / "flame.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    assert image.shape == (64, 48)
    assert image[24:40, 16:32].mean() > 40 and image[:6, :6].mean() < 10


def test_a_run_whose_scene_knows_its_unit_exports_a_vdb_in_metres(tmp_path):
    """scene.unit (metres per world unit) places the VDB's voxels in metres: a 0.5 mm-unit
    capture is millimetres tall in Blender, not metres; the values stay density.npz's."""
    if openvdb_missing():
        pytest.skip(openvdb_missing())
    from flamerecon.run.pipeline import reconstruct

    reconstruct(tiny_cfg("export=vdb", "++scene.unit=0.0005"), tmp_path)
    saved = load_density(tmp_path)
    nz, ny, nx = saved.density.shape[1:]
    grid = read_with_openvdb(tmp_path / "density.vdb", (nx, ny, nz))["density"]
    size = voxel_size(saved.bbox_min, saved.bbox_max, saved.density.shape)
    np.testing.assert_allclose(grid["voxel"], size * 0.0005, rtol=1e-9)
    np.testing.assert_allclose(grid["world0"], sample_origin(saved.bbox_min, saved.bbox_max, saved.density.shape) * 0.0005,
                               rtol=0, atol=1e-12)
