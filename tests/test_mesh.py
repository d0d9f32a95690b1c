"""Iso-surface meshes (flamerecon/outputs/mesh.py): PLY and OBJ read back by VTK's readers (the
ones ParaView uses), closed and wound outwards, inside the density's box in world units; the
level, its errors, and the doors that write them (export=mesh, scripts/export.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from flamerecon.errors import ConfigError
from flamerecon.outputs.export import check_exporters, export_density, load_density, save_density
from flamerecon.outputs.mesh import DEFAULT_ISO, iso_surface, write_obj, write_ply
from flamerecon.run.pipeline import reconstruct
from tests.helpers import REPO, repo_env, tiny_cfg, tiny_synthetic

pytest.importorskip("skimage", reason="mesh exports need scikit-image: pip install 'flamerecon[export]'")


def flame():
    """The synthetic flame's true density (3, nz, ny, nx) and its box."""
    scene = tiny_synthetic()
    return scene.truth.numpy(), np.array(scene.truth_grid.bbox_min), np.array(scene.truth_grid.bbox_max)


def read_vtk(path):
    """(points (V, 3), triangles (F, 3)) of a mesh file by VTK's PLY or OBJ reader."""
    io = pytest.importorskip("vtkmodules.vtkIOPLY" if path.suffix == ".ply" else "vtkmodules.vtkIOGeometry")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    reader = io.vtkPLYReader() if path.suffix == ".ply" else io.vtkOBJReader()
    reader.SetFileName(str(path))
    reader.Update()
    mesh = reader.GetOutput()
    polys = mesh.GetPolys()
    assert (np.diff(vtk_to_numpy(polys.GetOffsetsArray())) == 3).all()  # triangles only
    points = vtk_to_numpy(mesh.GetPoints().GetData())  # float64 from the OBJ text: 9 digits hold a float32
    return points.astype(np.float32), vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3)


def assert_closed_and_outward(vertices, faces):
    """Every edge is shared by exactly two triangles that run it in opposite directions, and
    the enclosed (signed) volume is positive."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # no directed edge twice
    reverse = {tuple(e) for e in directed[:, ::-1].tolist()}
    assert reverse == {tuple(e) for e in directed.tolist()}  # each one's reverse is there
    a, b, c = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 0


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_the_flames_mesh_reads_back_in_vtk_closed_outward_and_inside_its_box(tmp_path, suffix):
    density, lo, hi = flame()
    vertices, faces = iso_surface(density, lo, hi)
    write = write_ply if suffix == ".ply" else write_obj
    points, triangles = read_vtk(write(tmp_path / f"flame{suffix}", vertices, faces, "a comment"))
    assert len(vertices) > 100 and points.shape == vertices.shape and triangles.shape == faces.shape
    np.testing.assert_array_equal(points, vertices)
    np.testing.assert_array_equal(triangles, faces)
    assert (points >= lo - 1e-6).all() and (points <= hi + 1e-6).all()
    assert_closed_and_outward(points, triangles)


def test_the_enclosed_volume_is_the_volume_above_the_level():
    """A ball of radius 0.3 (density 1 - r / 0.6, level half the peak) on 24^3 cells encloses
    the ball's volume within 2%."""
    n, lo, hi = 24, np.array([-0.5, 0.0, 1.0]), np.array([0.5, 1.0, 2.0])
    z, y, x = np.meshgrid(*[(np.arange(n) + 0.5) / n] * 3, indexing="ij")
    r = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2)
    density = np.clip(1 - r / 0.6, 0, None)
    vertices, faces = iso_surface(density[None], lo, hi, 0.5 / density.max())
    a, b, c = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    enclosed = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert enclosed == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.02)
    centre = np.linalg.norm(vertices - (lo + hi) / 2, axis=1)
    assert centre == pytest.approx(0.3, abs=0.01)


def test_a_plume_leaving_the_box_is_closed_on_its_faces():
    density = np.zeros((1, 6, 8, 10), np.float32)
    density[0, :3, 2:, 4:] = 1.0  # touches the bottom (z), top (y) and right (x) faces
    lo, hi = np.zeros(3), np.array([1.0, 0.8, 0.6])
    vertices, faces = iso_surface(density, lo, hi, 0.5)
    assert_closed_and_outward(vertices, faces)
    # beyond the outer cells' centres, halfway to the faces (where the pad samples sit), not past them
    assert vertices.min(0)[2] == pytest.approx(0.025) and vertices.max(0)[:2] == pytest.approx([0.975, 0.775])
    assert (vertices >= lo).all() and (vertices <= hi + 1e-7).all()


def test_a_level_without_a_surface_is_one_line_naming_export_iso():
    density, lo, hi = flame()
    for iso in (0.0, 1.0, -0.2, 2.0):
        with pytest.raises(ConfigError, match=r"^export\.iso: got .*; .* in \(0, 1\)"):
            iso_surface(density, lo, hi, iso)
    with pytest.raises(ConfigError, match=r"^export\.iso: the density is zero .*; export a volume format"):
        iso_surface(np.zeros_like(density), lo, hi)


def test_a_missing_scikit_image_is_named_before_the_run(monkeypatch):
    monkeypatch.setitem(sys.modules, "skimage.measure", None)
    with pytest.raises(ConfigError, match=r"export\.formats: .*scikit-image.*pip install 'flamerecon\[export\]'"):
        check_exporters(["mesh"])


def test_export_mesh_writes_the_runs_surface_at_the_configured_level(tmp_path):
    metrics = reconstruct(tiny_cfg("export=mesh", "export.iso=0.2"), tmp_path)
    assert metrics["timing"]["export"] >= 0
    saved = load_density(tmp_path)
    points, _ = read_vtk(tmp_path / "density.ply")
    expected = iso_surface(saved.density, saved.bbox_min, saved.bbox_max, 0.2)
    np.testing.assert_array_equal(points, expected[0])
    assert (tmp_path / "density.obj").is_file() and not (tmp_path / "density.vti").exists()
    assert (points >= saved.bbox_min - 1e-6).all() and (points <= saved.bbox_max + 1e-6).all()


@pytest.mark.e2e
def test_the_export_script_writes_an_obj_at_its_iso_option(tmp_path):
    density, lo, hi = flame()
    save_density(tmp_path / "density.npz", density, lo, hi, [])
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "export.py"), str(tmp_path), "--format", "obj",
                           "--iso", "0.3"], capture_output=True, text=True, env=repo_env(), check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [str(tmp_path / "density.obj")]
    points, _ = read_vtk(tmp_path / "density.obj")
    at_default = export_density(load_density(tmp_path), tmp_path / "default", ["obj"], DEFAULT_ISO)
    assert len(points) < len(read_vtk(at_default[0])[0])  # a higher level: a smaller surface
    np.testing.assert_array_equal(points, iso_surface(density, lo, hi, 0.3)[0])
