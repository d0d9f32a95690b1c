"""Iso-surface meshes of a density for Blender, ParaView and MeshLab: marching cubes
(scikit-image's, an optional package: ``pip install 'flamerecon[export]'``) written as PLY
(binary little-endian) or OBJ (text).

The surface is where the channel mean of the density equals ``iso`` times its maximum (a
level relative to the peak, since emission has no absolute unit; :data:`DEFAULT_ISO`). The field
is padded with one cell of zeros whose samples sit on the box's faces, so every surface is
closed (watertight) also where the plume leaves the box, and every vertex lies inside
``[bbox_min, bbox_max]``, in world units (the cell-centre convention of :mod:`.export`). Faces
wind counter-clockwise seen from outside: their normals point out of the plume.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from flamerecon.errors import ConfigError
from flamerecon.outputs.atomic import atomic_path

#: default level: 10% of the peak of the channel mean. On ScalarFlow frame 25 (scene=scalarflow)
#: its surface encloses 94% of the density's sum, 97% of the cells inside in one piece; at 3%
#: the faint haze around the plume adds a hundred specks, at 20% 14% of the sum is left out
DEFAULT_ISO = 0.1
_INSTALL_HINT = "install it with: pip install 'flamerecon[export]'"


def marching_cubes():
    """scikit-image's ``marching_cubes``; an ImportError saying how to install it."""
    try:
        from skimage.measure import marching_cubes as found
    except ImportError as err:
        raise ImportError(f"mesh exports (ply, obj) need the 'scikit-image' package; {_INSTALL_HINT}") from err
    return found


def iso_surface(density, bbox_min, bbox_max, iso: float = DEFAULT_ISO) -> tuple[np.ndarray, np.ndarray]:
    """The closed iso-surface of ``density`` ((C, nz, ny, nx) or (nz, ny, nx), on the box
    ``bbox_min``..``bbox_max``, world xyz) at ``iso`` times the maximum of its channel mean:
    vertices (V, 3) float32 world xyz and triangles (F, 3) int32, wound outwards. A
    :class:`~flamerecon.errors.ConfigError` names ``export.iso`` when there is no surface."""
    if not 0.0 < float(iso) < 1.0:
        raise ConfigError(f"export.iso: got {iso}; it is a fraction of the density's maximum, in (0, 1)")
    field = np.asarray(density, dtype=np.float64)
    field = field.mean(0) if field.ndim == 4 else field
    peak = float(field.max()) if field.size else 0.0
    if not np.isfinite(peak) or peak <= 0.0:
        raise ConfigError("export.iso: the density is zero (or not finite) everywhere, so it has no "
                          "iso-surface; export a volume format instead (vti, nrrd, raw, vdb)")
    padded = np.pad(field, 1)
    verts, faces, _, _ = marching_cubes()(padded, level=float(iso) * peak)
    n = np.array(field.shape[::-1], dtype=np.float64)  # (nx, ny, nz)
    c = verts[:, ::-1].astype(np.float64)  # padded sample coordinates, xyz order
    # sample i + 1 of the padded field is cell i's centre (i + 0.5 cells from bbox_min); the pad
    # samples 0 and n + 1 sit on the faces, 0 and n cells from bbox_min
    cells = np.where(c < 1, 0.5 * c, np.where(c > n, n - 0.5 + 0.5 * (c - n), c - 0.5))
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    world = lo + cells * (hi - lo) / n  # scikit-image winds (z, y, x) inwards: outwards in (x, y, z)
    return world.astype(np.float32), np.ascontiguousarray(faces, dtype=np.int32)


def write_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> Path:
    """Binary little-endian PLY of triangles ``faces`` (F, 3) over ``vertices`` (V, 3), atomically."""
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {line}" for line in comment.splitlines() if line]
    header += [f"element vertex {len(vertices)}", "property float x", "property float y", "property float z",
               f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    rows = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    rows["n"], rows["v"] = 3, faces
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
        fh.write(rows.tobytes())
    return Path(path)


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> Path:
    """Wavefront OBJ (text; 1-based ``f`` indices) of ``faces`` (F, 3) over ``vertices`` (V, 3), atomically."""
    text = io.StringIO()
    for line in comment.splitlines():
        text.write(f"# {line}\n")
    np.savetxt(text, np.asarray(vertices, dtype=np.float32), fmt="v %.9g %.9g %.9g")
    np.savetxt(text, np.asarray(faces, dtype=np.int64) + 1, fmt="f %d %d %d")
    with atomic_path(path) as tmp:
        tmp.write_text(text.getvalue(), encoding="ascii")
    return Path(path)
