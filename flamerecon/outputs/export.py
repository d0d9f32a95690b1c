"""The density file of a run (``density.npz``) and its exports for other tools.

``density.npz`` is the source of truth (README, "The run folder"): ``density`` float32 (C, nz, ny, nx), x varies
fastest; ``bbox_min`` and ``bbox_max`` world xyz (3,); ``views`` the names of the views fitted.
Voxel (k, j, i) is the cell whose corner nearest ``bbox_min`` is ``bbox_min + (i, j, k) * size``
with ``size = (bbox_max - bbox_min) / (nx, ny, nz)``; its value sits at the cell centre. Every
export therefore puts sample 0 at ``origin = bbox_min + size / 2`` with spacing ``size``.

Exports (all written atomically):

- VTK image data ``.vti`` (ParaView), one point-data array per channel, and a ``.pvd``
  time-series index over several of them; needs the optional ``vtk`` package;
- NRRD ``.nrrd`` with space origin and directions; needs the optional ``pynrrd`` package;
- raw little-endian float32 ``.raw`` with a JSON header ``.raw.json`` that says how to read it;
- OpenVDB ``.vdb`` float grids in the world frame (Blender, Houdini;
  :mod:`flamerecon.outputs.vdb`, no extra package);
- an iso-surface mesh as ``.ply`` and/or ``.obj`` (:mod:`flamerecon.outputs.mesh`, needs the
  optional ``scikit-image`` package); ``mesh`` names both, ``all`` every format.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from flamerecon.errors import ConfigError, FlameReconError
from flamerecon.outputs.atomic import atomic_path, save_npz_atomic, write_json_atomic
from flamerecon.outputs.mesh import DEFAULT_ISO, iso_surface, marching_cubes, write_obj, write_ply
from flamerecon.outputs.vdb import write_vdb

DENSITY_FILE = "density.npz"
#: a run's confidence volume, in density.npz's format (:mod:`flamerecon.evaluate.uncertainty`)
UNCERTAINTY_FILE = "uncertainty.npz"
FORMATS = ("vti", "nrrd", "raw", "vdb", "ply", "obj")
#: the formats of a volume (the others are its iso-surface)
VOLUME_FORMATS = ("vti", "nrrd", "raw", "vdb")
#: names for several formats at once
ALIASES = {"all": FORMATS, "mesh": ("ply", "obj")}
_RESERVED = ("density", "bbox_min", "bbox_max", "views")
_INSTALL_HINT = "install the optional exporters with: pip install 'flamerecon[export]'"


class DensityFileError(FlameReconError, ValueError):
    """A density file that is missing a field or holds a field of the wrong shape or type."""


class Density(NamedTuple):
    """What ``density.npz`` holds; unpacks as ``density, bbox_min, bbox_max, views``."""

    density: np.ndarray  # float32 (C, nz, ny, nx)
    bbox_min: np.ndarray  # float64 (3,) world xyz
    bbox_max: np.ndarray  # float64 (3,) world xyz
    views: list[str]


def voxel_size(bbox_min, bbox_max, shape: Sequence[int]) -> np.ndarray:
    """Cell size (3,) in world units, xyz order, for a volume of array shape (..., nz, ny, nx)."""
    nz, ny, nx = shape[-3:]
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    return (hi - lo) / np.array([nx, ny, nz], dtype=np.float64)


def sample_origin(bbox_min, bbox_max, shape: Sequence[int]) -> np.ndarray:
    """World xyz (3,) of the centre of voxel (0, 0, 0): where image-data formats put sample 0."""
    return np.asarray(bbox_min, dtype=np.float64) + 0.5 * voxel_size(bbox_min, bbox_max, shape)


def channel_names(num_channels: int) -> list[str]:
    """``density`` for one channel, ``R, G, B`` for three, ``c0, c1, ...`` otherwise."""
    if num_channels == 1:
        return ["density"]
    if num_channels == 3:
        return ["R", "G", "B"]
    return [f"c{c}" for c in range(num_channels)]


def sigma_names(num_channels: int) -> list[str]:
    """The channel names of a confidence volume: each density channel's, ``_sigma`` appended."""
    return [f"{name}_sigma" for name in channel_names(num_channels)]


def density_path(run_dir_or_file: str | os.PathLike) -> Path:
    """``RUN_DIR/density.npz`` for a run folder, the path itself for a file."""
    path = Path(run_dir_or_file)
    return path / DENSITY_FILE if path.is_dir() else path


def _as_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):  # torch tensor on any device
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _check(where: str, density: np.ndarray, bbox_min: np.ndarray, bbox_max: np.ndarray) -> None:
    if density.ndim != 4 or min(density.shape) < 1:
        raise DensityFileError(
            f"{where}: field 'density' must have shape (C, nz, ny, nx), got {density.shape}"
        )
    if not np.issubdtype(density.dtype, np.floating):
        raise DensityFileError(f"{where}: field 'density' must be floating point, got {density.dtype}")
    for name, box in (("bbox_min", bbox_min), ("bbox_max", bbox_max)):
        if box.shape != (3,) or not np.issubdtype(box.dtype, np.number):
            raise DensityFileError(
                f"{where}: field '{name}' must be 3 numbers (world xyz), got {box.dtype} {box.shape}"
            )
        if not np.all(np.isfinite(box)):
            raise DensityFileError(f"{where}: field '{name}' is not finite: {box}")
    if np.any(bbox_max <= bbox_min):
        raise DensityFileError(f"{where}: 'bbox_max' {bbox_max} must exceed 'bbox_min' {bbox_min}")


def save_density(
    path: str | os.PathLike, density, bbox_min, bbox_max, views: Iterable[str], **extra
) -> Path:
    """Write ``density.npz`` atomically.

    density: (C, nz, ny, nx) array or tensor (any device), stored as float32;
    bbox_min, bbox_max: world xyz (3,); views: names of the views fitted;
    extra: further arrays to keep beside them (e.g. ``frame``, ``iteration``).
    """
    path = Path(path)
    vol = _as_numpy(density).astype(np.float32, copy=False)
    lo = _as_numpy(bbox_min).astype(np.float64).reshape(-1)
    hi = _as_numpy(bbox_max).astype(np.float64).reshape(-1)
    _check(str(path), vol, lo, hi)
    names = np.array([str(v) for v in views], dtype=np.str_)
    if names.size == 0:
        names = np.zeros(0, dtype="<U1")
    arrays = {k: _as_numpy(v) for k, v in extra.items()}
    return save_npz_atomic(path, density=vol, bbox_min=lo, bbox_max=hi, views=names, **arrays)


def load_density(path: str | os.PathLike) -> Density:
    """Read and check ``density.npz`` (or a run folder holding one).

    Raises FileNotFoundError for a missing file and DensityFileError naming the file and the
    field for anything else wrong.
    """
    path = density_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no density file (expected {DENSITY_FILE} of a run)")
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as err:  # numpy raises several types for a damaged or foreign file
        raise DensityFileError(f"{path}: not a readable .npz archive ({err})") from err
    with archive:
        fields = {}
        for name in _RESERVED:
            if name not in archive.files:
                raise DensityFileError(
                    f"{path}: missing field '{name}' (has {sorted(archive.files)})"
                )
            try:
                fields[name] = archive[name]
            except ValueError as err:  # object arrays need pickle, which is refused
                raise DensityFileError(f"{path}: field '{name}' cannot be read ({err})") from err
    vol, lo, hi = fields["density"], fields["bbox_min"], fields["bbox_max"]
    _check(str(path), vol, lo, hi)
    views = fields["views"]
    if views.ndim != 1 or not (views.dtype.kind in "US" or views.size == 0):
        raise DensityFileError(
            f"{path}: field 'views' must be a 1-D array of names, got {views.dtype} {views.shape}"
        )
    names = [v.decode() if isinstance(v, bytes) else str(v) for v in views.tolist()]
    return Density(vol.astype(np.float32, copy=False), lo.astype(np.float64), hi.astype(np.float64), names)


# ---------------------------------------------------------------------------------------------
# VTK image data


def _vtk():
    try:
        from vtkmodules.util import numpy_support
        from vtkmodules.vtkCommonDataModel import vtkImageData
        from vtkmodules.vtkIOXML import vtkXMLImageDataWriter
    except ImportError as err:
        raise ImportError(f"writing .vti needs the 'vtk' package; {_INSTALL_HINT}") from err
    return numpy_support, vtkImageData, vtkXMLImageDataWriter


def write_vti(
    path: str | os.PathLike, density, bbox_min, bbox_max, names: Sequence[str] | None = None,
    vectors: Mapping[str, Any] | None = None,
) -> Path:
    """VTK XML image data: point data sampled at voxel centres, one float32 array per channel.

    density: (C, nz, ny, nx); origin = centre of voxel (0, 0, 0), spacing = voxel size.
    The first channel is the active scalar (what ParaView colours by first). ``vectors``:
    {name: (3, nz, ny, nx) components x, y, z} written as 3-component arrays (the first is the
    active vectors: ParaView's Glyph and Stream Tracer filters take it).
    """
    numpy_support, vtkImageData, vtkXMLImageDataWriter = _vtk()
    vol = np.ascontiguousarray(_as_numpy(density), dtype=np.float32)
    num_channels, nz, ny, nx = vol.shape
    names = list(names) if names is not None else channel_names(num_channels)
    if len(names) != num_channels:
        raise ValueError(f"{path}: {len(names)} channel names for {num_channels} channels")
    image = vtkImageData()
    image.SetDimensions(nx, ny, nz)
    image.SetOrigin(*sample_origin(bbox_min, bbox_max, vol.shape))
    image.SetSpacing(*voxel_size(bbox_min, bbox_max, vol.shape))
    for c, name in enumerate(names):
        # (nz, ny, nx) in C order is x fastest, then y, then z: VTK's point order.
        array = numpy_support.numpy_to_vtk(vol[c].reshape(-1), deep=True)
        array.SetName(name)
        image.GetPointData().AddArray(array)
    image.GetPointData().SetActiveScalars(names[0])
    for k, (name, field) in enumerate((vectors or {}).items()):
        field = np.ascontiguousarray(_as_numpy(field), dtype=np.float32)
        if field.shape != (3, nz, ny, nx):
            raise ValueError(f"{path}: vectors '{name}' of shape {field.shape}, the density's grid needs (3, {nz}, {ny}, {nx})")
        array = numpy_support.numpy_to_vtk(np.ascontiguousarray(field.reshape(3, -1).T), deep=True)
        array.SetName(name)
        image.GetPointData().AddArray(array)
        if k == 0:
            image.GetPointData().SetActiveVectors(name)
    path = Path(path)
    with atomic_path(path) as tmp:
        writer = vtkXMLImageDataWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputData(image)
        writer.SetDataModeToAppended()
        writer.EncodeAppendedDataOff()  # raw binary, zlib-compressed by default
        if writer.Write() != 1:
            raise OSError(f"{path}: VTK could not write the image data")
    return path


def write_pvd(path: str | os.PathLike, datasets: Iterable[tuple[float, str | os.PathLike]]) -> Path:
    """ParaView's time-series index: ``datasets`` of (time, file), files relative to ``path``'s
    folder where they lie inside it. ParaView opens the ``.pvd`` as one animated dataset."""
    path = Path(path)
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    for time, file in datasets:
        file = Path(file)
        if file.is_absolute():
            try:
                file = file.relative_to(path.parent.resolve())
            except ValueError:
                pass
        ET.SubElement(
            collection, "DataSet", timestep=repr(float(time)), group="", part="0", file=file.as_posix()
        )
    ET.indent(root)
    data = ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n"
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


# ---------------------------------------------------------------------------------------------
# NRRD


def write_nrrd(
    path: str | os.PathLike,
    density,
    bbox_min,
    bbox_max,
    names: Sequence[str] | None = None,
    encoding: str = "gzip",
    units: str | None = None,
) -> Path:
    """NRRD volume; world placement in ``space origin`` (centre of voxel 0) and ``space
    directions`` (one voxel step along x, y, z), in a plain 3-D space (no anatomical frame);
    ``units`` (e.g. ``m``) names the length unit in ``space units``.

    One channel: a 3-D volume, NRRD axes (x, y, z). Several: a 4-D one whose first (fastest)
    NRRD axis is the channel, kind ``RGB-color`` for three channels, ``vector`` otherwise;
    channel names are in the ``channels`` key. ``nrrd.read(index_order="F")`` gives the
    array as (C, nx, ny, nz), or (nx, ny, nz) for one channel.
    """
    try:
        import nrrd
    except ImportError as err:
        raise ImportError(f"writing .nrrd needs the 'pynrrd' package; {_INSTALL_HINT}") from err
    vol = np.asarray(_as_numpy(density), dtype=np.float32)
    num_channels = vol.shape[0]
    names = list(names) if names is not None else channel_names(num_channels)
    if len(names) != num_channels:
        raise ValueError(f"{path}: {len(names)} channel names for {num_channels} channels")
    step = np.diag(voxel_size(bbox_min, bbox_max, vol.shape))
    header: dict[str, Any] = {
        "space dimension": 3,
        "space origin": sample_origin(bbox_min, bbox_max, vol.shape),
        "encoding": encoding,
        "channels": ",".join(names),
        **({"space units": [units] * 3} if units else {}),
    }
    if num_channels == 1:
        data = vol[0].transpose(2, 1, 0)  # NRRD index order, fastest first: (x, y, z)
        header.update(kinds=["domain"] * 3, labels=["x", "y", "z"], **{"space directions": step})
    else:
        data = vol.transpose(0, 3, 2, 1)  # (channel, x, y, z)
        kind = "RGB-color" if num_channels == 3 else "vector"
        directions = np.vstack([np.full((1, 3), np.nan), step])
        header.update(kinds=[kind] + ["domain"] * 3, labels=["channel", "x", "y", "z"],
                      **{"space directions": directions})
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        nrrd.write(fh, data, header, index_order="F")
    return path


# ---------------------------------------------------------------------------------------------
# raw float32 + JSON header


def write_raw(
    path: str | os.PathLike,
    density,
    bbox_min,
    bbox_max,
    names: Sequence[str] | None = None,
    views: Sequence[str] = (),
    unit: float | None = None,
) -> tuple[Path, Path]:
    """Little-endian float32 bytes of the (C, nz, ny, nx) array (x fastest) at ``path`` and a
    JSON header at ``path + ".json"`` with shape, axis order, world placement (``length_unit``:
    ``m`` where ``unit``, the capture's metres per world unit, placed it in metres) and channel
    names. Returns (raw path, header path)."""
    vol = np.ascontiguousarray(_as_numpy(density), dtype="<f4")
    names = list(names) if names is not None else channel_names(vol.shape[0])
    if len(names) != vol.shape[0]:
        raise ValueError(f"{path}: {len(names)} channel names for {vol.shape[0]} channels")
    path = Path(path)
    header_path = path.with_name(path.name + ".json")
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    header = {
        "data_file": path.name,
        "dtype": "float32",
        "byte_order": "little",
        "shape": list(vol.shape),
        "axes": ["channel", "z", "y", "x"],
        "order": "C: x varies fastest, then y, then z, then channel",
        "channels": names,
        "bbox_min": lo.tolist(),
        "bbox_max": hi.tolist(),
        "voxel_size": voxel_size(lo, hi, vol.shape).tolist(),
        "origin": sample_origin(lo, hi, vol.shape).tolist(),
        "origin_is": "world xyz of the centre of voxel (0, 0, 0); voxel (k, j, i) is centred at "
        "origin + (i, j, k) * voxel_size",
        "views": list(views),
        "length_unit": "world units" if unit is None else "m",
        "metres_per_world_unit": unit,
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        vol.tofile(fh)
    write_json_atomic(header_path, header)
    return path, header_path


def read_raw(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read back :func:`write_raw`'s pair: (array (C, nz, ny, nx) float32, header dict)."""
    import json

    path = Path(path)
    header_path = path.with_name(path.name + ".json")
    header = json.loads(header_path.read_text())
    for key in ("shape", "dtype", "byte_order"):
        if key not in header:
            raise DensityFileError(f"{header_path}: missing field '{key}'")
    dtype = np.dtype(header["dtype"]).newbyteorder("<" if header["byte_order"] == "little" else ">")
    data = np.fromfile(path, dtype=dtype)
    if data.size != int(np.prod(header["shape"])):
        raise DensityFileError(
            f"{path}: holds {data.size} values, header field 'shape' {header['shape']} needs "
            f"{int(np.prod(header['shape']))}"
        )
    return data.reshape(header["shape"]).astype(np.float32, copy=False), header


# ---------------------------------------------------------------------------------------------
# a run's exports


def export_density(
    volume: Density, out_stem: str | os.PathLike, formats: Iterable[str] = FORMATS, iso: float = DEFAULT_ISO,
    names: Sequence[str] | None = None, unit: float | None = None,
) -> list[Path]:
    """Write ``volume`` as ``<out_stem>.vti``, ``.nrrd``, ``.raw`` (+ ``.raw.json``), ``.vdb``,
    ``.ply`` and/or ``.obj`` (the meshes: the iso-surface at ``iso`` times the peak of the channel mean,
    see :func:`~flamerecon.outputs.mesh.iso_surface`); ``names``: the channels' (default
    :func:`channel_names`). With ``unit`` (metres per world unit) every placement (origin,
    spacing, voxel size, vertices) is in metres, so that a 0.5 mm-unit capture arrives in Blender
    or ParaView at its real size; the values stay density.npz's (per world unit)."""
    formats = _check_formats(formats)
    stem = Path(out_stem)
    scale = 1.0 if unit is None else float(unit)
    args = (volume.density, np.asarray(volume.bbox_min, np.float64) * scale,
            np.asarray(volume.bbox_max, np.float64) * scale)
    written: list[Path] = []
    if "vti" in formats:
        written.append(write_vti(stem.with_name(stem.name + ".vti"), *args, names))
    if "nrrd" in formats:
        written.append(write_nrrd(stem.with_name(stem.name + ".nrrd"), *args, names,
                                  units=None if unit is None else "m"))
    if "raw" in formats:
        written.extend(write_raw(stem.with_name(stem.name + ".raw"), *args, names, views=volume.views, unit=unit))
    if "vdb" in formats:
        written.append(write_vdb(stem.with_name(stem.name + ".vdb"), volume.density,
                                 sample_origin(*args[1:], volume.density.shape),
                                 voxel_size(*args[1:], volume.density.shape),
                                 names or channel_names(len(volume.density))))
    meshes = [(f, w) for f, w in (("ply", write_ply), ("obj", write_obj)) if f in formats]
    if meshes:
        vertices, faces = iso_surface(*args, iso=iso)
        comment = (f"flamerecon iso-surface at {iso:g} x the peak of the density's channel mean; "
                   + ("world units" if unit is None else "metres")
                   + "; box {} to {}".format(*(list(map(float, b)) for b in args[1:])))
        written += [write(stem.with_name(f"{stem.name}.{fmt}"), vertices, faces, comment) for fmt, write in meshes]
    return written


def export_run(run_dir: str | os.PathLike, formats: Iterable[str] = FORMATS, iso: float = DEFAULT_ISO) -> list[Path]:
    """Export ``RUN_DIR/density.npz`` into the run folder as ``density.<format>``, and its
    confidence volume ``uncertainty.npz``, when the run has one, as ``uncertainty.<format>``
    for the volume formats (vti, nrrd, raw, vdb); placed in metres where the run's scene knew
    its unit (:func:`recorded_conventions`)."""
    run_dir = Path(run_dir)
    unit = recorded_conventions(run_dir)["unit"]
    written = export_density(load_density(run_dir / DENSITY_FILE), run_dir / "density", formats, iso, unit=unit)
    volumes = [f for f in _check_formats(formats) if f in VOLUME_FORMATS]
    if volumes and (run_dir / UNCERTAINTY_FILE).is_file():
        sigma = load_density(run_dir / UNCERTAINTY_FILE)
        written += export_density(sigma, run_dir / "uncertainty", volumes, iso, sigma_names(sigma.density.shape[0]),
                                  unit=unit)
    return written


def recorded_conventions(run_dir: str | os.PathLike) -> dict:
    """A run's scene conventions as its metrics.json recorded them (``scene``): ``up`` (an axis
    such as ``+z``), ``unit`` (metres per world unit or None) and ``frame_rate`` (or None); for
    a run that recorded none (written before they were, or no metrics.json), +y and unknown."""
    import json

    try:
        record = json.loads((Path(run_dir) / "metrics.json").read_text()).get("scene") or {}
    except (OSError, ValueError, AttributeError):
        record = {}
    return {"up": record.get("up") or "+y", "unit": record.get("unit"), "frame_rate": record.get("frame_rate")}


def check_exporters(formats: Iterable[str]) -> None:
    """ConfigError naming ``export.formats`` when a format's optional package is missing
    (checked before a run, not after its solve)."""
    try:
        for fmt in _check_formats(formats):
            if fmt == "vti":
                _vtk()
            elif fmt == "nrrd":
                try:
                    import nrrd  # noqa: F401
                except ImportError as err:
                    raise ImportError(f"writing .nrrd needs the 'pynrrd' package; {_INSTALL_HINT}") from err
            elif fmt in ("ply", "obj"):
                marching_cubes()
    except (ImportError, ValueError) as err:
        raise ConfigError(f"export.formats: {err}") from None


def _check_formats(formats: Iterable[str]) -> list[str]:
    formats = [formats] if isinstance(formats, str) else list(formats)
    expanded = [f for name in formats for f in ALIASES.get(name, [name])]
    unknown = sorted(set(expanded) - set(FORMATS))
    if unknown:
        raise ValueError(f"unknown export format(s) {unknown}; choose from {list(FORMATS)} or {list(ALIASES)}")
    return list(dict.fromkeys(expanded))
