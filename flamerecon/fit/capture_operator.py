"""One operator per capture, not per frame: the cameras of a capture stand still, so the rays
of its pixels and their voxel weights are the same for every frame; only the silhouettes (the
rows kept) and the hull (the columns kept) change.

A *region* holds a frame's hull grown: the visual hull of its training silhouettes dilated by
:data:`REGION_GROWTH` of the image's longer side (ScalarFlow's plume moves about 0.4% of it a
frame, so the region holds the next few frames), and as rows every pixel whose ray meets that
hull. Its operator is written to files beside the captures' calibration files
(``<calibration folder>/operators/<key>/``) block by block while it is assembled,
the frame's own rows and columns taken from each block on the way. A later frame whose hull
lies inside the region reads its rows and columns back
(:func:`~flamerecon.operators.stored.read_selection`; a row the region lacks misses its hull,
so it has no entry). Either way the frame's operator is the one
:func:`~flamerecon.operators.projector.assemble` makes, entry for entry (tested), and the
region is never held in memory: a frame takes the memory of its own operator.

``projector.reuse``: ``auto`` reads a region that holds the frame and builds none (a frame on
its own would pay for the region's larger assembly and its files); ``true`` (a sequence: a
multirun over frames, ``scripts/sequence_benchmark.py``) also builds one, or grows it (the
old region and this frame's grown) when the frame leaves it; ``false`` neither, as
``FLAMERECON_CACHE=0`` does. The key holds what the weights depend on (the training cameras'
values, image size, grid box and resolution, march step, rows, hull margin, the code of the
march), so a changed camera, grid, image size or box never reads a stale region. A folder that
cannot be written only costs the region's assembly. Entries beyond :data:`MAX_BYTES` in all
go, least recently used first.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import uuid
from pathlib import Path

import torch
import torch.nn.functional as F

from flamerecon.fit.options import ReconstructionOptions
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import hull_footprint, visual_hull
from flamerecon.operators import compiled, projector, stored
from flamerecon.operators.projector import assembled_blocks, camera_rays
from flamerecon.operators.sparse import CsrOperator, GrowingArray
from flamerecon.scenes.cache import cache_dir, cache_home, digest, entry_key

log = logging.getLogger(__name__)

#: the region's silhouettes are the frame's dilated by this share of the image's longer side
#: (ScalarFlow frames 55-63 at 1/4: 3-4 px covers the next frame, 5 px two, 8-9 px four)
REGION_GROWTH = 0.02
#: bytes of region operators kept in all; the least recently used beyond go
MAX_BYTES = 8 << 30
REGION_FILE = "region.pt"


def operators_folder(options: ReconstructionOptions) -> Path | None:
    """Where region operators go: ``operators/`` beside the captures' calibration files
    (``calibration.folder``, else the cache's ``calibration/``); None when reuse is off."""
    if not options.projector.reuse or cache_dir() is None:
        return None
    root = Path(options.calibration.folder) if options.calibration.folder else cache_home() / "calibration"
    return root / "operators"


def region_key(cams, image_size: tuple[int, int], grid: VoxelGrid, step: float, options: ReconstructionOptions) -> str:
    """The key of a region operator: what its weights and its region's rule depend on."""
    content = {
        "cameras": digest({"K": cams.intrinsics.cpu(), "E": cams.extrinsics.cpu()}),
        "image": list(image_size), "step": float(step), "rays": options.projector.rays,
        "margin": int(options.hull.margin_voxels), "growth": REGION_GROWTH,
        "grid": {"lo": list(grid.bbox_min), "hi": list(grid.bbox_max), "resolution": list(grid.resolution)},
    }
    return entry_key("operator", content, [projector, compiled, stored, sys.modules[__name__]])


def capture_operator(cams, grid: VoxelGrid, masks: torch.Tensor, rows: torch.Tensor,
                     hull: torch.Tensor, step: float, options: ReconstructionOptions) -> CsrOperator | None:
    """The frame's assembled operator (rows ``rows`` (T, H, W) bool x ``hull`` (nz, ny, nx)
    bool voxels) taken from its capture's region operator, when one holds its hull; with
    ``projector.reuse=true`` a region is assembled (or grown) and written first where none
    does (``masks`` (T, H, W): the frame's training silhouettes, which it grows). None where
    there is no region to take it from, the compiled kernels are missing (no numba) or
    reuse is off: the caller assembles the frame's own. The region is assembled and read on the
    CPU (the compiled march); the frame's operator is moved to ``masks``' device."""
    folder = operators_folder(options)
    if folder is None or not compiled.available("cpu"):
        return None
    device = masks.device  # the region is assembled and read on the CPU, the frame's operator moved here
    masks, rows, hull, cams = masks.cpu(), rows.cpu(), hull.cpu(), cameras_to(cams, "cpu")
    entry = folder / region_key(cams, tuple(masks.shape[-2:]), grid, step, options)[:32]
    region = read_region(entry)
    if region is not None and inside(hull, region["hull"]):
        try:
            found = stored.read_selection(entry, region["tag"], rows.reshape(-1)[region["rows"].reshape(-1)],
                                          column_map(region["hull"], hull))
            os.utime(entry / REGION_FILE)  # recently used: kept longest
            return frame_operator(rows, region["rows"], hull, *found).to(device)
        except (OSError, ValueError) as err:
            log.warning("operator cache: %s is unreadable (%s); assembling its region again", entry, err)
    if options.projector.reuse is not True:
        return None
    radius = max(1, round(REGION_GROWTH * max(masks.shape[-2:])))
    grown = masks[:, None].float()
    for kernel, pad in (((2 * radius + 1, 1), (radius, 0)), ((1, 2 * radius + 1), (0, radius))):
        grown = F.max_pool2d(grown, kernel, stride=1, padding=pad)  # a square, by rows then columns
    grown = grown[:, 0] > 0
    region_hull = visual_hull(grid, cams, grown, int(options.hull.margin_voxels)) | hull
    if region is not None:  # grown, never shrunk: it keeps serving the frames it held
        region_hull |= region["hull"]
    return assemble_region(entry, hull_footprint(grid, cams, region_hull), region_hull, cams, grid, step, rows,
                           hull).to(device)


def inside(part: torch.Tensor, whole: torch.Tensor) -> bool:
    """Whether every True of ``part`` is True in ``whole`` (same shapes)."""
    return part.shape == whole.shape and not bool((part & ~whole).any())


def column_map(region_hull: torch.Tensor, hull: torch.Tensor) -> torch.Tensor:
    """(M_region,) int32: each region hull voxel's column in the frame's operator (the rank of
    its flat index among the frame's hull voxels), or -1 where the frame's hull lacks it."""
    frame_column = torch.cumsum(hull.reshape(-1).to(torch.int32), 0, dtype=torch.int32) - 1
    frame_column[~hull.reshape(-1)] = -1
    return frame_column[region_hull.reshape(-1).nonzero().squeeze(1)]


def frame_operator(rows: torch.Tensor, region_rows: torch.Tensor, hull: torch.Tensor, counts: torch.Tensor,
                   col: torch.Tensor, val: torch.Tensor) -> CsrOperator:
    """The frame's operator from its rows' entries read from the region (``counts`` for each
    of its rows the region holds, in pixel order): a row the region lacks is a ray that
    misses the region's hull (its rows are every pixel whose ray meets it), so it misses the
    frame's hull too and has no entry."""
    held = region_rows.reshape(-1)[rows.reshape(-1)]  # (N,) of the frame's rows
    per_row = torch.zeros(int(held.numel()), dtype=torch.long)
    per_row[held] = counts
    crow = torch.zeros(per_row.numel() + 1, dtype=torch.long)
    torch.cumsum(per_row, 0, out=crow[1:])
    return CsrOperator.from_csr(crow, col, val, (int(per_row.numel()), int(hull.sum())))


def read_region(entry: Path) -> dict | None:
    """The region record of ``entry`` (its rows and hull, the version tag of its files), or
    None when there is none whole."""
    try:
        region = torch.load(entry / REGION_FILE, map_location="cpu", weights_only=True)
        if all(path.is_file() for path in stored.files(entry, region["tag"])):
            return region
    except FileNotFoundError:
        return None
    except Exception as err:  # noqa: BLE001 - an unreadable entry is assembled again
        log.warning("operator cache: %s is unreadable (%s); assembling its region again", entry, err)
    return None


def assemble_region(entry: Path, region_rows: torch.Tensor, region_hull: torch.Tensor, cams, grid: VoxelGrid,
                    step: float, rows: torch.Tensor, hull: torch.Tensor) -> CsrOperator:
    """Assemble the region operator (rows ``region_rows`` x voxels ``region_hull``), write it
    to ``entry`` (a new version, replacing the old one whole) and return the frame's operator
    (rows ``rows`` x voxels ``hull``), taken from each block as it is assembled."""
    rays, _ = camera_rays(cams, region_rows)
    keep_rows = rows.reshape(-1)[region_rows.reshape(-1)]
    columns = column_map(region_hull, hull)
    tag = uuid.uuid4().hex[:12]
    staging = entry.with_name(f"{entry.name}.{tag}.tmp")
    writer = None
    try:
        staging.mkdir(parents=True)
        writer = stored.StoredWriter(staging, tag)
    except OSError as err:
        log.warning("operator cache: cannot write %s (%s): each frame assembles its own operator; set "
                    "projector.reuse=false to stop trying", staging, err)
    counts = []
    cols, vals = GrowingArray(torch.int32, "cpu"), GrowingArray(torch.float32, "cpu")
    for sl, n, col, val in assembled_blocks(grid, rays, region_hull.reshape(-1).nonzero().squeeze(1), step):
        if writer is not None:
            try:
                writer.append(n, col, val)
            except OSError as err:
                log.warning("operator cache: writing %s failed (%s); this frame goes on without it", staging, err)
                writer.abandon()
                writer = None
        kept, c, v = stored.select(n, col, val, keep_rows[sl], columns)
        counts.append(kept)
        cols.append(c)
        vals.append(v)
    operator = frame_operator(rows, region_rows, hull, torch.cat(counts) if counts else torch.zeros(0, dtype=torch.long),
                              cols.tensor(), vals.tensor())
    if writer is not None:
        publish(entry, staging, writer, {"tag": tag, "rows": region_rows.cpu(), "hull": region_hull.cpu()})
    else:
        shutil.rmtree(staging, ignore_errors=True)
    return operator


def publish(entry: Path, staging: Path, writer: stored.StoredWriter, region: dict) -> None:
    """Finish the files in ``staging``, move them to ``entry`` (the old version removed) and
    keep the capture's entries within :data:`MAX_BYTES`."""
    try:
        writer.close()
        torch.save(region, staging / REGION_FILE)
        old = entry.with_name(f"{entry.name}.{region['tag']}.old")
        if entry.exists():
            entry.rename(old)
        staging.rename(entry)
        shutil.rmtree(old, ignore_errors=True)
        evict(entry.parent, keep=entry)
    except OSError as err:
        log.warning("operator cache: could not keep %s (%s); the next frame assembles its region again", entry, err)
        shutil.rmtree(staging, ignore_errors=True)


def evict(folder: Path, keep: Path) -> None:
    """Remove the least recently used region operators of ``folder`` beyond :data:`MAX_BYTES`
    (``keep``, the newest, stays)."""
    entries = []
    for path in folder.iterdir():
        if path.is_dir() and (path / REGION_FILE).is_file():
            size = sum(f.stat().st_size for f in path.iterdir() if f.is_file())
            entries.append(((path / REGION_FILE).stat().st_mtime, size, path))
    entries.sort(key=lambda e: (e[2] != keep, -e[0]))  # the kept one first, then newest first
    total = 0
    for _, size, path in entries:
        total += size
        if total > MAX_BYTES and path != keep:
            shutil.rmtree(path, ignore_errors=True)
