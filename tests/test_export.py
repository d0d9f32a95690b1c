"""density.npz contract and exports, each read back with its own library's reader."""

from __future__ import annotations

import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
import torch

from flamerecon.geometry.grid import VoxelGrid
from flamerecon.outputs.export import (
    DensityFileError,
    export_run,
    load_density,
    read_raw,
    sample_origin,
    save_density,
    voxel_size,
    write_nrrd,
    write_pvd,
    write_raw,
    write_vti,
)
from tests.helpers import repo_env

REPO = Path(__file__).resolve().parents[1]
needs_vtk = pytest.mark.skipif(find_spec("vtkmodules") is None,
                               reason="vtk not installed: pip install 'flamerecon[export]'")
LO = np.array([-0.5, 0.0, 1.0])
HI = np.array([0.5, 3.0, 2.0])


def _volume(num_channels: int, shape=(5, 4, 3), seed=0) -> np.ndarray:
    """(C, nz, ny, nx) with distinct values so a transposed axis cannot go unnoticed."""
    rng = np.random.default_rng(seed)
    return rng.random((num_channels, *shape)).astype(np.float32)


def _run_script(name: str, *args) -> subprocess.CompletedProcess:
    env = repo_env()
    return subprocess.run([sys.executable, str(REPO / "scripts" / name), *map(str, args)],
                          check=False, capture_output=True, text=True, env=env)


def _read_vti(path: Path):
    vtk_io = pytest.importorskip("vtkmodules.vtkIOXML")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    reader = vtk_io.vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    point_data = image.GetPointData()
    arrays = {
        point_data.GetArrayName(a): vtk_to_numpy(point_data.GetArray(a))
        for a in range(point_data.GetNumberOfArrays())
    }
    return image, arrays


# --- density.npz ---------------------------------------------------------------------------


def test_save_load_round_trip_from_torch(tmp_path):
    vol = torch.from_numpy(_volume(3))
    path = save_density(tmp_path / "density.npz", vol, LO, HI, ["cam0", "cam3"], frame=7)
    density, lo, hi, views = load_density(tmp_path)  # a run folder works as well as the file
    assert density.dtype == np.float32 and density.shape == (3, 5, 4, 3)
    np.testing.assert_array_equal(density, vol.numpy())
    np.testing.assert_array_equal(lo, LO)
    np.testing.assert_array_equal(hi, HI)
    assert views == ["cam0", "cam3"]
    with np.load(path) as f:  # plain numpy, no pickle, reads it too
        assert int(f["frame"]) == 7


def test_voxel_geometry_matches_voxel_grid():
    grid = VoxelGrid.from_box(LO, HI, (3, 4, 5))
    centres = grid.centers().double().numpy()  # (nz, ny, nx, 3)
    np.testing.assert_allclose(sample_origin(LO, HI, grid.shape), centres[0, 0, 0], rtol=1e-6)
    step = voxel_size(LO, HI, grid.shape)
    np.testing.assert_allclose(centres[4, 3, 2], sample_origin(LO, HI, grid.shape) + step * [2, 3, 4],
                               rtol=1e-6)


@pytest.mark.parametrize(
    ("arrays", "field"),
    [
        ({"bbox_min": LO, "bbox_max": HI, "views": np.array(["a"])}, "'density'"),
        ({"density": _volume(1), "bbox_max": HI, "views": np.array(["a"])}, "'bbox_min'"),
        ({"density": _volume(1), "bbox_min": LO, "bbox_max": HI}, "'views'"),
        ({"density": _volume(1)[0], "bbox_min": LO, "bbox_max": HI, "views": np.array(["a"])},
         "'density' must have shape"),
        ({"density": _volume(1), "bbox_min": LO[:2], "bbox_max": HI, "views": np.array(["a"])},
         "'bbox_min' must be 3"),
        ({"density": _volume(1), "bbox_min": HI, "bbox_max": LO, "views": np.array(["a"])},
         "'bbox_max'"),
        ({"density": _volume(1), "bbox_min": LO, "bbox_max": HI,
          "views": np.array(["a", None], dtype=object)}, "'views'"),
    ],
)
def test_bad_density_file_names_file_and_field(tmp_path, arrays, field):
    path = tmp_path / "density.npz"
    np.savez(path, **arrays)
    with pytest.raises(DensityFileError, match=field) as err:
        load_density(path)
    assert str(path) in str(err.value)


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="density.npz"):
        load_density(tmp_path)
    (tmp_path / "density.npz").write_text("not an archive")
    with pytest.raises(DensityFileError, match="density.npz"):
        load_density(tmp_path)


# --- VTK ---------------------------------------------------------------------------------------


@needs_vtk
@pytest.mark.parametrize(("num_channels", "names"), [(1, ["density"]), (3, ["R", "G", "B"])])
def test_vti_read_back_with_vtk(tmp_path, num_channels, names):
    vol = _volume(num_channels)
    write_vti(tmp_path / "v.vti", vol, LO, HI)
    image, arrays = _read_vti(tmp_path / "v.vti")
    assert image.GetDimensions() == (3, 4, 5)  # (nx, ny, nz)
    np.testing.assert_allclose(image.GetOrigin(), LO + 0.5 * (HI - LO) / [3, 4, 5])
    np.testing.assert_allclose(image.GetSpacing(), (HI - LO) / [3, 4, 5])
    assert list(arrays) == names
    assert image.GetPointData().GetScalars().GetName() == names[0]
    for c, name in enumerate(names):
        np.testing.assert_array_equal(arrays[name], vol[c].reshape(-1))
    # VTK's own point lookup: world position of the point holding voxel (k, j, i) = (4, 1, 2)
    k, j, i = 4, 1, 2
    point = image.ComputePointId([i, j, k])
    np.testing.assert_allclose(image.GetPoint(point), LO + (np.array([i, j, k]) + 0.5) *
                               (HI - LO) / [3, 4, 5])
    assert arrays[names[-1]][point] == vol[-1, k, j, i]


@needs_vtk
def test_pvd_lists_series_with_relative_paths(tmp_path):
    (tmp_path / "frames").mkdir()
    for t in range(3):
        write_vti(tmp_path / "frames" / f"f{t}.vti", _volume(1, seed=t), LO, HI)
    write_pvd(tmp_path / "s.pvd", [(t * 10, tmp_path / "frames" / f"f{t}.vti") for t in range(3)])
    root = ET.parse(tmp_path / "s.pvd").getroot()
    assert root.get("type") == "Collection"
    sets = root.find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in sets] == [0.0, 10.0, 20.0]
    assert [d.get("file") for d in sets] == [f"frames/f{t}.vti" for t in range(3)]
    for t, d in enumerate(sets):
        _, arrays = _read_vti(tmp_path / d.get("file"))
        np.testing.assert_array_equal(arrays["density"], _volume(1, seed=t).reshape(-1))


# --- NRRD --------------------------------------------------------------------------------------


@pytest.mark.parametrize("num_channels", [1, 3])
def test_nrrd_read_back_with_pynrrd(tmp_path, num_channels):
    nrrd = pytest.importorskip("nrrd")
    vol = _volume(num_channels)
    write_nrrd(tmp_path / "v.nrrd", vol, LO, HI)
    data, header = nrrd.read(str(tmp_path / "v.nrrd"), index_order="F")
    step = (HI - LO) / [3, 4, 5]
    np.testing.assert_allclose(header["space origin"], LO + 0.5 * step)
    directions = header["space directions"]
    if num_channels == 1:
        assert data.shape == (3, 4, 5)  # (x, y, z)
        np.testing.assert_array_equal(data, vol[0].transpose(2, 1, 0))
    else:
        assert data.shape == (3, 3, 4, 5)  # (channel, x, y, z)
        assert header["kinds"][0] == "RGB-color" and header["channels"] == "R,G,B"
        assert np.isnan(directions[0]).all()
        directions = directions[1:]
        np.testing.assert_array_equal(data, vol.transpose(0, 3, 2, 1))
    np.testing.assert_allclose(directions, np.diag(step))
    # index (i, j, k) -> world: origin + directions^T (i, j, k), NRRD's definition
    i, j, k = 2, 3, 4
    np.testing.assert_allclose(header["space origin"] + directions.T @ [i, j, k],
                               LO + (np.array([i, j, k]) + 0.5) * step)


# --- raw -----------------------------------------------------------------------------------


def test_raw_read_back_with_numpy_fromfile(tmp_path):
    vol = _volume(3)
    raw, header_path = write_raw(tmp_path / "v.raw", vol, LO, HI, views=["a"])
    header = json.loads(header_path.read_text())
    assert raw.stat().st_size == vol.size * 4
    data = np.fromfile(raw, dtype="<f4").reshape(header["shape"])
    np.testing.assert_array_equal(data, vol)
    np.testing.assert_allclose(header["origin"], LO + 0.5 * (HI - LO) / [3, 4, 5])
    np.testing.assert_allclose(header["voxel_size"], (HI - LO) / [3, 4, 5])
    assert header["channels"] == ["R", "G", "B"] and header["views"] == ["a"]
    again, _ = read_raw(raw)
    np.testing.assert_array_equal(again, vol)
    raw.write_bytes(raw.read_bytes()[:-4])
    with pytest.raises(DensityFileError, match="'shape'"):
        read_raw(raw)


# --- a run's exports through the script --------------------------------------------------------


@pytest.mark.e2e
@needs_vtk
def test_export_script_writes_all_formats_into_run_dir(tmp_path):
    pytest.importorskip("nrrd")
    pytest.importorskip("skimage")
    vol = _volume(3)
    save_density(tmp_path / "density.npz", vol, LO, HI, ["a", "b"])
    proc = _run_script("export.py", tmp_path, "--format", "all")
    assert proc.returncode == 0, proc.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["density.npz", "density.nrrd", "density.obj", "density.ply", "density.raw",
                     "density.raw.json", "density.vdb", "density.vti"]
    _, arrays = _read_vti(tmp_path / "density.vti")
    np.testing.assert_array_equal(arrays["G"], vol[1].reshape(-1))


@pytest.mark.e2e
def test_export_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="density.npz"):
        export_run(tmp_path, ["raw"])
    save_density(tmp_path / "density.npz", _volume(1), LO, HI, [])
    with pytest.raises(ValueError, match="vtu"):
        export_run(tmp_path, ["vtu"])
    proc = _run_script("export.py", tmp_path / "nope")
    assert proc.returncode != 0 and "nope" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("config", sorted((REPO / "conf" / "export").glob("*.yaml")),
                         ids=lambda p: p.stem)
def test_export_config_group_names_known_formats(tmp_path, config):
    yaml = pytest.importorskip("yaml")
    formats = yaml.safe_load(config.read_text())["formats"]
    save_density(tmp_path / "density.npz", _volume(1), LO, HI, [])
    if "vti" in formats:
        pytest.importorskip("vtkmodules")
    if "nrrd" in formats:
        pytest.importorskip("nrrd")
    if {"ply", "obj"} & set(formats):
        pytest.importorskip("skimage")
    written = export_run(tmp_path, formats)
    assert {p.suffix for p in written} == {f".{f}" for f in formats} | (
        {".json"} if "raw" in formats else set())


@needs_vtk
def test_a_capture_with_a_unit_exports_its_placement_in_metres(tmp_path):
    """export_density(unit=0.0005): origin, spacing, voxel size and mesh vertices in metres (a
    0.5 mm world unit), values as density.npz's; NRRD says its space units, the raw header its
    length unit."""
    pytest.importorskip("nrrd")
    pytest.importorskip("skimage")
    import nrrd

    from flamerecon.outputs.export import Density, export_density

    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n) for n in (5, 4, 3)), indexing="ij")
    vol = np.exp(-2 * (x**2 + y**2 + z**2))[None].astype(np.float32)
    unit = 0.0005
    export_density(Density(vol, LO, HI, ["a"]), tmp_path / "m", ["vti", "nrrd", "raw", "obj"], unit=unit)
    image, arrays = _read_vti(tmp_path / "m.vti")
    np.testing.assert_allclose(image.GetSpacing(), voxel_size(LO, HI, vol.shape) * unit)
    np.testing.assert_allclose(image.GetOrigin(), sample_origin(LO, HI, vol.shape) * unit)
    np.testing.assert_array_equal(arrays["density"], vol[0].reshape(-1))
    _, header = nrrd.read(str(tmp_path / "m.nrrd"))
    assert list(header["space units"]) == ["m", "m", "m"]
    np.testing.assert_allclose(header["space origin"], sample_origin(LO, HI, vol.shape) * unit)
    raw_header = json.loads((tmp_path / "m.raw.json").read_text())
    assert raw_header["length_unit"] == "m" and raw_header["metres_per_world_unit"] == unit
    np.testing.assert_allclose(raw_header["voxel_size"], voxel_size(LO, HI, vol.shape) * unit)
    lines = (tmp_path / "m.obj").read_text().splitlines()
    assert "metres" in lines[0]
    vertices = np.array([[float(v) for v in line.split()[1:]] for line in lines if line.startswith("v ")])
    assert len(vertices) and (vertices >= LO * unit - 1e-9).all() and (vertices <= HI * unit + 1e-9).all()
    assert vertices.max(0)[1] > 0.5 * HI[1] * unit  # spread through the box in metres, not shrunk to a corner
