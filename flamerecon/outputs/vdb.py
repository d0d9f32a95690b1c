"""OpenVDB ``.vdb`` files of a density, written here in numpy (no OpenVDB library needed), for
Blender's volume import, Houdini and anything else built on OpenVDB.

The file holds float fog-volume grids (class ``fog volume``, background 0) of the standard
tree ``Tree_float_5_4_3``: ``density`` (the density itself for one channel, the channel mean
for several, what Blender's Principled Volume reads by default), and for several channels one
grid per channel (``R``, ``G``, ``B``: Blender's Attribute node reads them by name). Index
(i, j, k) is voxel (k, j, i) of the (C, nz, ny, nx) array, x fastest as in ``density.npz``; the
grid's transform maps it to its cell centre in the world, ``origin + (i, j, k) * voxel_size``
(:func:`~flamerecon.outputs.export.sample_origin`,
:func:`~flamerecon.outputs.export.voxel_size`), a ``UniformScaleTranslateMap`` for cubic cells
and a ``ScaleTranslateMap`` otherwise. Voxels that are not 0 are active; blocks of 8^3 voxels
that are all 0 are not stored.

The layout follows OpenVDB's own writer (``io::Archive::write``, file format 224, library 10.0):
uncompressed (``COMPRESS_NONE``: each node's values written whole), little-endian, with grid
offsets, and each grid's stats metadata (``file_bbox_min``/``max``, ``file_voxel_count``).
``tests/test_vdb.py`` reads the files back with OpenVDB's own reader where it is installed.
"""

from __future__ import annotations

import io
import os
import struct
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from flamerecon.outputs.atomic import atomic_path

FILE_VERSION = 224  # OPENVDB_FILE_VERSION_MULTIPASS_IO, what OpenVDB 6.1-12 write
LIBRARY_VERSION = (10, 0)
_MAGIC = 0x56444220  # "VDB "
_TREE = "Tree_float_5_4_3"
_NO_MASK_AND_ALL_VALS = 6  # io::writeCompressedValues' flag: every value follows, no mask
_LEAF, _LOWER, _UPPER = 3, 4, 5  # log2 of each node's width in its children (leaf: voxels)


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _metadata(entries: Sequence[tuple[str, str, bytes]]) -> bytes:
    """MetaMap::writeMeta: count, then per entry name, type name, value size and value."""
    out = struct.pack("<i", len(entries))
    for name, type_name, data in entries:
        out += _string(name) + _string(type_name) + struct.pack("<I", len(data)) + data
    return out


def _mask(bits: np.ndarray) -> bytes:
    """NodeMask::save: bit n (the node's linear offset, z fastest) in 64-bit little-endian words."""
    return np.packbits(bits.reshape(-1).astype(np.uint8), bitorder="little").tobytes()


def _node_values(count: int) -> bytes:
    """An internal node's tile values, all the background 0, written whole."""
    return bytes([_NO_MASK_AND_ALL_VALS]) + bytes(4 * count)


def _leaf_blocks(volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The non-empty 8^3 leaves of a (nx, ny, nz) float32 array indexed (i, j, k): their leaf
    coordinates (L, 3) (origin / 8) in the order OpenVDB writes them (depth first: root child,
    lower node, leaf, each in lexicographic order) and their values (L, 512), z fastest."""
    size = 1 << _LEAF
    padded = np.zeros([-(-n // size) * size for n in volume.shape], np.float32)
    padded[: volume.shape[0], : volume.shape[1], : volume.shape[2]] = volume
    nx, ny, nz = (n // size for n in padded.shape)
    blocks = padded.reshape(nx, size, ny, size, nz, size).transpose(0, 2, 4, 1, 3, 5).reshape(nx, ny, nz, -1)
    coords = np.argwhere(np.any(blocks != 0, axis=-1))
    lower, upper = 1 << _LOWER, 1 << (_LOWER + _UPPER)  # leaves per lower node, per root child
    keys = np.concatenate([coords // upper, (coords // lower) % (1 << _UPPER), coords % lower], axis=1)
    order = np.lexsort(keys.T[::-1])
    coords = coords[order]
    return coords, blocks[coords[:, 0], coords[:, 1], coords[:, 2]]


def _topology(coords: np.ndarray, values: np.ndarray) -> bytes:
    """Tree::writeTopology: buffer count, the root (background, tile and child counts, each
    child's origin and its nodes depth first: child mask, value mask and values, then the
    leaves' value masks)."""
    lower_leaves = 1 << _LOWER
    upper_leaves = lower_leaves << _UPPER
    upper_of = coords // upper_leaves
    roots = np.unique(upper_of, axis=0)  # lexicographic, as the root's std::map of coords
    out = struct.pack("<i", 1) + struct.pack("<f", 0.0) + struct.pack("<II", 0, len(roots))
    for root in roots:
        inside = np.all(upper_of == root, axis=1)
        local = coords[inside] - root * upper_leaves
        origin = root * upper_leaves * (1 << _LEAF)
        out += struct.pack("<3i", *origin.tolist())
        lower_of = local // lower_leaves
        children = np.zeros((1 << _UPPER,) * 3, bool)
        children[tuple(lower_of.T)] = True
        out += _mask(children) + _mask(np.zeros_like(children)) + _node_values(children.size)
        for lower in np.argwhere(children):  # offset order: x, then y, then z
            here = np.all(lower_of == lower, axis=1)
            leaves = np.zeros((lower_leaves,) * 3, bool)
            leaves[tuple((local[here] % lower_leaves).T)] = True
            out += _mask(leaves) + _mask(np.zeros_like(leaves)) + _node_values(leaves.size)
            out += b"".join(_mask(v != 0) for v in values[np.flatnonzero(inside)[here]])
    return out


def _buffers(values: np.ndarray) -> bytes:
    """Tree::writeBuffers: per leaf, in topology order, its value mask and its 512 values."""
    return b"".join(_mask(v != 0) + bytes([_NO_MASK_AND_ALL_VALS]) + v.astype("<f4").tobytes() for v in values)


def _grid(name: str, volume: np.ndarray, origin: np.ndarray, size: np.ndarray, start: int) -> bytes:
    """One grid as Archive::writeGrid writes it at file offset ``start``: descriptor (name,
    type, instance parent, stream offsets), compression flags, metadata, transform, topology
    and leaf buffers. ``volume`` (nx, ny, nz) indexed (i, j, k)."""
    coords, values = _leaf_blocks(volume)
    active = np.argwhere(volume != 0)
    lo, hi = (active.min(0), active.max(0)) if len(active) else (np.zeros(3, int), np.zeros(3, int))
    meta = _metadata([
        ("class", "string", b"fog volume"),
        ("file_bbox_max", "vec3i", struct.pack("<3i", *hi.tolist())),
        ("file_bbox_min", "vec3i", struct.pack("<3i", *lo.tolist())),
        ("file_compression", "string", b"none"),
        ("file_voxel_count", "int64", struct.pack("<q", len(active))),
        ("is_saved_as_half_float", "bool", b"\x00"),
        ("name", "string", name.encode()),
    ])
    uniform = bool(np.allclose(size, size[0], rtol=1e-9, atol=0))
    transform = _string("UniformScaleTranslateMap" if uniform else "ScaleTranslateMap")
    # ScaleTranslateMap::write: translation, scale, voxel size, 1/scale, 1/scale^2, 1/(2 scale)
    transform += np.concatenate([origin, size, np.abs(size), 1 / size, 1 / size**2, 0.5 / size]).astype("<f8").tobytes()
    head = _string(name) + _string(_TREE) + _string("")
    grid_pos = start + len(head) + 24
    body = struct.pack("<I", 0) + meta + transform + _topology(coords, values)
    block_pos = grid_pos + len(body)
    body += _buffers(values)
    return head + struct.pack("<3q", grid_pos, block_pos, grid_pos + len(body)) + body


def vdb_bytes(grids: Sequence[tuple[str, np.ndarray]], origin, size) -> bytes:
    """A whole ``.vdb`` file: ``grids`` of (name, (nz, ny, nx) float array) sharing one
    transform, sample 0 at world ``origin`` (3,), cells of ``size`` (3,) world units, xyz."""
    origin = np.asarray(origin, np.float64).reshape(3)
    size = np.asarray(size, np.float64).reshape(3)
    out = io.BytesIO()
    out.write(struct.pack("<qI", _MAGIC, FILE_VERSION) + struct.pack("<II", *LIBRARY_VERSION) + b"\x01")
    out.write(str(uuid.uuid4()).encode() + _metadata([]) + struct.pack("<i", len(grids)))
    for name, volume in grids:
        index_order = np.ascontiguousarray(np.asarray(volume, np.float32).transpose(2, 1, 0))
        out.write(_grid(name, index_order, origin, size, out.tell()))
    return out.getvalue()


def vdb_grids(density: np.ndarray, names: Sequence[str]) -> list[tuple[str, np.ndarray]]:
    """The grids :func:`write_vdb` writes for a (C, nz, ny, nx) density: ``density`` (one
    channel: itself; several: their mean), then each of several channels under its name."""
    if len(density) == 1:
        return [("density", density[0])]
    return [("density", density.mean(0)), *zip(names, density)]


def write_vdb(path: str | os.PathLike, density: np.ndarray, origin, size, names: Sequence[str]) -> Path:
    """Write :func:`vdb_grids` of ``density`` (C, nz, ny, nx) as an OpenVDB file at ``path``,
    atomically; ``origin``: world xyz of voxel (0, 0, 0)'s centre, ``size``: cell size xyz."""
    data = vdb_bytes(vdb_grids(np.asarray(density, np.float32), names), origin, size)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path
