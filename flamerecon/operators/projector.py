"""The emission-only projector: a pixel is the line integral, in world units, of the
trilinearly interpolated density along its ray.

Rays are marched through the grid's box grown by half a voxel (the support of the trilinear
interpolant) in segments of ``step`` voxels; each segment contributes its length times the
density at its midpoint. Two backends share these samples and agree to float precision:

- matrix-free (:class:`MatrixFreeOperator`): ``grid_sample`` on the dense volume, autograd
  for the adjoint; differentiable, memory light, the renderer for full images;
- assembled (:class:`~flamerecon.operators.CsrOperator`): the same weights stored once as CSR,
  restricted to silhouette rays x hull voxels; fastest for repeated solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera

from flamerecon import interrupt
from flamerecon.geometry.cameras import cameras_to, pixel_centers, pixel_rays, project_points
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import compiled
from flamerecon.operators.sparse import TRANSPOSE_BLOCK, CsrOperator, GrowingArray, stable_argsort
from flamerecon.progress import Progress

#: samples per chunk when marching (bounds memory: about 100 bytes per sample and channel).
CHUNK_SAMPLES = 4_000_000
#: a march or an assembly that lasts longer than this many seconds says how far it is, every
#: :data:`PROGRESS_EVERY` seconds (a full-resolution frame's assembly takes about 25 s)
PROGRESS_AFTER = 5.0
PROGRESS_EVERY = 10.0
#: ray samples per chunk when assembling (:data:`BYTES_PER_CHUNK_SAMPLE` each at the peak)
ASSEMBLY_CHUNK_SAMPLES = 2_000_000


@dataclass
class Rays:
    """Flat ray batch: origins (R, 3), unit directions (R, 3), world units."""

    origins: torch.Tensor
    directions: torch.Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def __getitem__(self, idx) -> Rays:
        return Rays(self.origins[idx], self.directions[idx])

    def to(self, device) -> Rays:
        return Rays(self.origins.to(device), self.directions.to(device))


def camera_rays(cams: PinholeCamera, masks: torch.Tensor | None = None) -> tuple[Rays, torch.Tensor]:
    """Rays through pixel centres of every camera, row-major per image, cameras in order.

    With ``masks`` (B, H, W) bool only the masked pixels are kept. Returns the rays and the
    flat pixel index ``b * H * W + v * W + u`` (R,) of each ray.
    """
    B = cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    device = cams.intrinsics.device
    uv = pixel_centers(H, W, device=device)[None].expand(B, -1, -1).contiguous()
    origins, dirs = pixel_rays(cams, uv)
    flat = torch.arange(B * H * W, device=device)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    if masks is not None:
        keep = masks.reshape(-1).to(device)
        origins, dirs, flat = origins[keep], dirs[keep], flat[keep]
    return Rays(origins, dirs), flat


def march_box(grid: VoxelGrid, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The box rays are marched through: the grid's box grown by half a voxel, (3,), (3,)."""
    half = 0.5 * grid.voxel_size(device)
    return grid.lo(device) - half, grid.hi(device) + half


def ray_box(rays: Rays, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: entry and exit distances (R,), entry clamped at 0; exit <= entry means a miss."""
    d = rays.directions
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0 = (lo - rays.origins) / safe
    t1 = (hi - rays.origins) / safe
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


def support_box(grid: VoxelGrid, voxel_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The box (3,), (3,) outside which the trilinear interpolant of values on the voxels
    ``voxel_index`` (flat indices) vanishes: their centres' bounding box grown by a voxel."""
    nx, ny, _ = grid.resolution
    device = voxel_index.device
    if voxel_index.numel() == 0:
        return grid.lo(device), grid.lo(device)
    ijk = torch.stack([voxel_index % nx, (voxel_index // nx) % ny, voxel_index // (nx * ny)], -1)
    size = grid.voxel_size(device)
    lo = grid.lo(device) + (ijk.amin(0) - 0.5) * size
    hi = grid.lo(device) + (ijk.amax(0) + 1.5) * size
    return lo, hi


def _segments(
    rays: Rays, grid: VoxelGrid, step: float, box: tuple[torch.Tensor, torch.Tensor] | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Where each ray's segments lie: march box entry and exit distances (R,), the first and
    one-past-last segment index (R,) as floats (narrowed to ``box`` when given), and the
    segment length ``ds`` in world units."""
    lo, hi = march_box(grid, rays.origins.device)
    t_near, t_far = ray_box(rays, lo, hi)
    ds = float(step) * float(grid.voxel_size().min())
    first = torch.zeros_like(t_near)
    end = torch.ceil((t_far - t_near).clamp_min(0.0) / ds)
    if box is not None:
        b_near, b_far = ray_box(rays, *box)
        first = torch.floor((b_near - t_near).clamp_min(0.0) / ds)
        end = torch.minimum(end, torch.ceil((b_far - t_near).clamp_min(0.0) / ds))
        end = torch.where(b_far > b_near, end, first)
    return t_near, t_far, first, end, ds


def ray_samples(
    rays: Rays, grid: VoxelGrid, step: float, box: tuple[torch.Tensor, torch.Tensor] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Segment midpoints (R, S, 3) and segment lengths (R, S) along each ray through the
    march box; ``step`` is the segment length in units of the smallest voxel side.

    Segments always start at the march box's entry, so that narrowing to ``box`` (where the
    density can be nonzero, see :func:`support_box`) only skips segments outside it and
    leaves every other sample where the full march puts it.
    """
    t_near, t_far, first, end, ds = _segments(rays, grid, step, box)
    count = (end - first).clamp_min(0.0)
    S = max(1, int(count.max().item())) if len(rays) else 1
    k = first[:, None] + torch.arange(S, device=t_near.device, dtype=t_near.dtype)
    start = t_near[:, None] + k * ds
    length = (t_far[:, None] - start).clamp(0.0, ds) * (k < end[:, None])
    mid = start + 0.5 * length
    points = rays.origins[:, None, :] + mid[..., None] * rays.directions[:, None, :]
    return points, length


@dataclass
class Samples:
    """The segments of a block of rays, only those the march keeps, ray after ray: the ray
    of each (P,) long, its midpoint (P, 3) and length (P,) in world units."""

    ray: torch.Tensor
    points: torch.Tensor
    length: torch.Tensor


def packed_samples(
    rays: Rays, grid: VoxelGrid, step: float, box: tuple[torch.Tensor, torch.Tensor] | None = None,
    chunk: int | None = None, frame: tuple[torch.Tensor, torch.Tensor] | None = None,
):
    """Yield (slice of rays, :class:`Samples`) blocks of about ``chunk`` samples (default
    :data:`CHUNK_SAMPLES`; a longer ray is a block alone); ``Samples.ray`` counts from the
    block's first ray. The same points and lengths as :func:`ray_samples`, bit for bit, without
    its padding of short rays (and of rays that miss) up to the longest ray of the chunk.
    ``frame`` (scale (3,), offset (3,)), e.g. :meth:`VoxelGrid.normalized_frame`, gives the
    points as ``xyz * scale + offset`` (the rays are moved into that frame once, not each sample)."""
    chunk = CHUNK_SAMPLES if chunk is None else int(chunk)
    t_near, t_far, first, end, ds = _segments(rays, grid, step, box)
    origins, directions = rays.origins, rays.directions
    if frame is not None:
        scale, offset = (t.to(origins) for t in frame)
        origins, directions = torch.addcmul(offset, origins, scale), directions * scale
    count = (end - first).clamp_min(0.0).long()
    total = torch.cumsum(count, 0)
    R, s = len(rays), 0
    while s < R:
        base = int(total[s - 1]) if s else 0
        e = int(torch.searchsorted(total, base + chunk, right=True))
        e = min(R, max(e, s + 1))
        n = count[s:e]
        ray = torch.repeat_interleave(torch.arange(e - s, device=n.device), n)
        near, far, first_k, origin, direction = (
            t[s:e].index_select(0, ray) for t in (t_near, t_far, first, origins, directions)
        )
        offset = torch.cumsum(n, 0) - n  # each ray's first sample in the block
        k = first_k.add_(torch.arange(ray.numel(), device=n.device) - offset.index_select(0, ray))
        start = near.add_(k.mul_(ds))  # the same float operations as ray_samples
        length = far.sub_(start).clamp_(0.0, ds)
        mid = start.add_(length, alpha=0.5)
        points = direction.mul_(mid[:, None]).add_(origin)
        yield slice(s, e), Samples(ray, points, length)
        s = e


def _chunks(rays: Rays, grid: VoxelGrid, step: float):
    """Yield (slice, rays) chunks small enough to march at once."""
    diag = float(torch.linalg.norm(grid.hi() - grid.lo() + grid.voxel_size()))
    per_ray = max(1, int(diag / (float(step) * float(grid.voxel_size().min()))) + 1)
    size = max(1, CHUNK_SAMPLES // per_ray)
    for s in range(0, len(rays), size):
        sl = slice(s, min(s + size, len(rays)))
        yield sl, rays[sl]


def integrate_dense(
    volume: torch.Tensor, grid: VoxelGrid, rays: Rays, step: float = 0.5,
    box: tuple[torch.Tensor, torch.Tensor] | None = None, what: str = "marching rays",
) -> torch.Tensor:
    """Line integrals (R, C) of a dense volume (C, nz, ny, nx) along ``rays``; differentiable.
    ``box`` may narrow the march to where the volume can be nonzero (see :func:`support_box`);
    ``what`` names the march in its progress lines (a long one only)."""
    C = volume.shape[0]
    out = []
    progress = Progress(what, len(rays), "ray", every=PROGRESS_EVERY, after=PROGRESS_AFTER)
    if compiled.available(volume.device) and not (torch.is_grad_enabled() and (
            volume.requires_grad or rays.origins.requires_grad or rays.directions.requires_grad)):
        values = volume.detach().float().contiguous()
        live = cells_touching(grid, (values != 0).any(0).view(-1).nonzero().squeeze(1))
        for sl, seg in compiled_blocks(rays, grid, step, box):
            out.append(compiled.integrate(values, live, seg).to(volume.dtype))
            progress.update(sl.stop)
            interrupt.check()
        return torch.cat(out, 0) if out else volume.new_zeros(0, C)
    frame = grid.normalized_frame(rays.origins.device)
    for sl, smp in packed_samples(rays, grid, step, box, frame=frame):
        weighted = _sample(volume, smp.points) * smp.length  # (C, P); points as x, y, z in [-1, 1]
        sums = weighted.new_zeros(C, sl.stop - sl.start).index_add_(1, smp.ray, weighted)
        out.append(sums.T)
        progress.update(sl.stop)
        interrupt.check()  # a stop signal inside a solve ends a long march within a block
    if not out:
        return volume.new_zeros(0, C)
    return torch.cat(out, 0)


def _sample(volume: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """``grid_sample`` of ``volume`` (C, nz, ny, nx) at normalized ``coords`` (P, 3): (C, P).

    On the CPU without autograd the points are split into one batch entry per thread: the CPU
    kernel of 3-D ``grid_sample`` parallelises over the batch only (same values, bit for bit),
    also where autograd follows ``coords`` (the camera fit's Jacobians: the backward pass too,
    1.5x faster on 2 cores), not where it follows ``volume`` (each entry would hold its gradient).
    """
    P, C = coords.shape[0], volume.shape[0]
    if P == 0:
        return volume.reshape(C, -1)[:, :0]  # still part of autograd's graph
    n = 1
    if not volume.is_cuda and not (torch.is_grad_enabled() and volume.requires_grad):
        n = max(1, min(torch.get_num_threads(), P))
    parts = []
    even = P - P % n
    for lo, hi, m in ((0, even, n), (even, P, 1)):
        if hi > lo:
            vals = F.grid_sample(
                volume[None].expand(m, *volume.shape), coords[lo:hi].reshape(m, 1, 1, -1, 3),
                mode="bilinear", padding_mode="zeros", align_corners=False,
            )  # (m, C, 1, 1, p)
            parts.append(vals.transpose(0, 1).reshape(C, hi - lo))
    return parts[0] if len(parts) == 1 else torch.cat(parts, 1)


def trilinear_weights(
    points: torch.Tensor, length: torch.Tensor, grid: VoxelGrid
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat voxel indices (P, 8) and weights (P, 8) of the 8 trilinear corners of each of the
    P samples ``points`` (P, 3), weights scaled by segment ``length`` (P,); corners outside
    the grid get weight 0 and index 0 (``grid_sample``'s zero padding). Slot ``4 dz + 2 dy +
    dx`` is the corner at offset (dx, dy, dz) from the sample's lower corner."""
    u = grid.world_to_index(points).T.contiguous()
    i0 = torch.floor(u)
    idx, w = _corners(u, i0, i0.long(), length, grid)
    return idx.long(), w


#: corner offsets (8, 3) as (dx, dy, dz) in the slot order of :func:`trilinear_weights`
CORNER_OFFSETS = torch.tensor([[c, b, a] for a in (0, 1) for b in (0, 1) for c in (0, 1)])


def _parent_table() -> torch.Tensor:
    """(126, 8) long: for a sample whose lower corner moved by (dx, dy, dz) in -2..2 from the
    previous sample's (code ``(dx+2) + 5 (dy+2) + 25 (dz+2)``; code 125: no previous sample on
    the ray), the offset from each corner entry to the previous sample's entry of the same
    voxel, 0 where that sample does not hold it."""
    d = torch.arange(-2, 3)
    dz, dy, dx = torch.meshgrid(d, d, d, indexing="ij")
    delta = torch.stack([dx, dy, dz], -1).reshape(125, 1, 3)
    there = CORNER_OFFSETS[None] + delta  # (125, 8, 3) the voxel's corner slot in the previous sample
    ok = ((there >= 0) & (there <= 1)).all(-1)
    slot = there[..., 0] + 2 * there[..., 1] + 4 * there[..., 2]
    rel = torch.where(ok, slot - torch.arange(8) - 8, torch.zeros_like(slot))
    return torch.cat([rel, torch.zeros(1, 8, dtype=rel.dtype)])


PARENT_TABLE = _parent_table()


def _corners(
    u: torch.Tensor, i0f: torch.Tensor, i0: torch.Tensor, length: torch.Tensor, grid: VoxelGrid
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`trilinear_weights` from continuous voxel coordinates ``u`` (3, P), axis-major,
    their floor ``i0f`` (3, P) and its ``i0`` as integers: indices (P, 8), int32 when the grid
    has fewer than 2^31 voxels (int64 products measured 3x slower), and weights (P, 8)."""
    if grid.num_voxels < 2**31:
        i0 = i0.to(torch.int32)
    f = u - i0f
    frac, index = [], []
    for axis, n in enumerate(grid.resolution):  # per axis: corner 0 and corner 1
        c0, c1 = i0[axis], i0[axis] + 1
        frac.append(((1 - f[axis]) * ((c0 >= 0) & (c0 < n)), f[axis] * ((c1 >= 0) & (c1 < n))))
        index.append((c0.clamp(0, n - 1), c1.clamp(0, n - 1)))
    (fx, fy, fz), (ix, iy, iz) = frac, index
    nx, ny, _ = grid.resolution
    w = torch.stack([fz[a] * fy[b] * fx[c] * length for a in (0, 1) for b in (0, 1) for c in (0, 1)], 1)
    zy = [(iz[a] * ny + iy[b]) * nx for a in (0, 1) for b in (0, 1)]
    idx = torch.stack([zy[2 * a + b] + ix[c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], 1)
    return idx, w


def _first_of_run(ray: torch.Tensor, cell: torch.Tensor) -> torch.Tensor:
    """For the 8 corner entries of each of P samples (``ray`` (P,), lower corner ``cell`` (P, 3),
    samples in march order): the flat entry index (P * 8,) where each entry's (ray, voxel)
    pair first appears. The samples that have a voxel among their corners are consecutive along
    a ray (a line meets the voxel's 2x2x2 cells once), so an entry continues the entry of the
    previous sample that holds the same voxel, and runs are followed to their start."""
    P = ray.numel()
    device = ray.device
    code = torch.full((P,), 125, dtype=torch.long, device=device)
    if P > 1:
        d = (cell[1:] - cell[:-1]).clamp_(-2, 2) + 2  # (P-1, 3)
        step = d[:, 0] + 5 * d[:, 1] + 25 * d[:, 2]
        code[1:] = torch.where(ray[1:] == ray[:-1], step, 125)
    index = torch.int32 if P * 8 < 2**31 else torch.long
    root = PARENT_TABLE.to(device=device, dtype=index).index_select(0, code).view(-1)
    root += torch.arange(P * 8, device=device, dtype=index)
    while True:  # pointer doubling: a run spans a few samples, so a few rounds
        up = root.index_select(0, root)
        if torch.equal(up, root):
            return root
        root = up


def cells_touching(grid: VoxelGrid, voxel_index: torch.Tensor) -> torch.Tensor:
    """(nz+1, ny+1, nx+1) bool: entry [k+1, j+1, i+1] says whether the trilinear cell with lower
    corner (i, j, k), i in -1..nx-1, has one of ``voxel_index``'s voxels among its 8 corners."""
    nx, ny, nz = grid.resolution
    occupied = torch.zeros(grid.num_voxels, device=voxel_index.device)
    occupied[voxel_index] = 1.0
    padded = F.pad(occupied.view(1, 1, nz, ny, nx), (1, 1, 1, 1, 1, 1))
    return F.max_pool3d(padded, 2, stride=1)[0, 0] > 0


def assemble(
    grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
) -> CsrOperator:
    """The operator rays x voxels (N, M) as CSR; column m is grid voxel ``voxel_index[m]``.

    Only columns in ``voxel_index`` (the hull) are kept; rows are the rays in order. An entry
    is the sum, in march order, of the weights of every sample that has the voxel among its 8
    trilinear corners.
    """
    device = rays.origins.device
    column = torch.full((grid.num_voxels,), -1, dtype=torch.long, device=device)
    column[voxel_index.to(device)] = torch.arange(voxel_index.numel(), device=device)
    M = int(voxel_index.numel())
    box = support_box(grid, voxel_index.to(device))
    live = cells_touching(grid, voxel_index.to(device))
    if compiled.available(device):
        return _assemble_compiled(grid, rays, voxel_index, step)
    top = torch.tensor(live.shape[::-1], device=device) - 1  # (nx, ny, nz)
    N = len(rays)
    counts = torch.zeros(N, dtype=torch.long, device=device)  # entries of each row
    cols_out, vals_out = GrowingArray(torch.int32, device), GrowingArray(torch.float32, device)  # row by row
    shape = torch.tensor(live.shape, device=device)
    frame = grid.index_frame(device)
    progress = Progress("assembling the operator", N, "ray", every=PROGRESS_EVERY, after=PROGRESS_AFTER)
    for sl, smp in packed_samples(rays, grid, step, box, ASSEMBLY_CHUNK_SAMPLES, frame):
        u = smp.points.T.contiguous()  # (3, P) continuous voxel coordinates
        i0f = torch.floor(u)
        i0 = i0f.to(torch.int32 if grid.num_voxels < 2**31 else torch.long)
        # keep only samples whose trilinear cell touches the hull (most of the support box
        # does not): the 8-corner work below is then done for samples that contribute
        cx, cy, cz = ((i0[a] + 1).clamp_(0, int(top[a])) for a in range(3))
        valid = live.view(-1)[(cz * int(shape[1]) + cy) * int(shape[2]) + cx] & (smp.length > 0)
        sel = valid.nonzero().squeeze(1)
        ray, i0 = smp.ray[sel], i0[:, sel]
        idx, w = _corners(u[:, sel], i0f[:, sel], i0, smp.length[sel], grid)
        i0 = i0.T
        # merge duplicates (neighbouring samples share corners), summed in march order
        root = _first_of_run(ray, i0)
        val = torch.zeros(root.numel(), dtype=w.dtype, device=device).index_add_(0, root, w.view(-1))
        entry = ((root == torch.arange(root.numel(), device=device, dtype=root.dtype)) & (val > 0)).nonzero()
        entry = entry.squeeze(1)  # the first entry of each (ray, voxel) pair that has weight
        col = column[idx.view(-1)[entry]]
        entry, col = entry[col >= 0], col[col >= 0]
        key = ray[entry // 8] * M + col
        order = stable_argsort(key)
        key, val = key[order], val[entry[order]]
        if key.numel() > 1 and bool((key[1:] == key[:-1]).any()):  # a run broken by rounding
            key, repeats = torch.unique_consecutive(key, return_counts=True)
            seg = torch.repeat_interleave(torch.arange(key.numel(), device=device), repeats)
            val = torch.zeros(key.numel(), dtype=val.dtype, device=device).index_add_(0, seg, val)
        counts[sl] = torch.bincount(key // M, minlength=sl.stop - sl.start)
        cols_out.append((key % M).to(torch.int32))  # columns ascending within each row
        vals_out.append(val)
        del smp, u, i0f, i0, idx, w, root, entry, key, order, val  # before the next chunk's
        progress.update(sl.stop)
        interrupt.check()
    crow = torch.zeros(N + 1, dtype=torch.long, device=device)
    torch.cumsum(counts, 0, out=crow[1:])
    return CsrOperator.from_csr(crow, cols_out.tensor(), vals_out.tensor(), (N, M))


def compiled_blocks(rays: Rays, grid: VoxelGrid, step: float, box: tuple[torch.Tensor, torch.Tensor] | None):
    """Yield (slice of rays, segments) blocks of about
    :data:`~flamerecon.operators.compiled.BLOCK_SEGMENTS` segments for the compiled kernels:
    the rays' origins and directions (R, 3) in continuous voxel coordinates, march box entry
    and exit (R,), first and one-past-last segment (R,) (narrowed to ``box``) and the
    segment length, as :func:`packed_samples` marches them."""
    t_near, t_far, first, end, ds = _segments(rays, grid, step, box)
    scale, offset = grid.index_frame(rays.origins.device)
    origins = torch.addcmul(offset.to(rays.origins), rays.origins, scale.to(rays.origins))
    directions = rays.directions * scale.to(rays.directions)
    total = torch.cumsum((end - first).clamp_min(0).long(), 0)
    N, s = len(rays), 0
    while s < N:
        base = int(total[s - 1]) if s else 0
        e = min(N, max(int(torch.searchsorted(total, base + compiled.BLOCK_SEGMENTS, right=True)), s + 1))
        yield slice(s, e), (origins[s:e], directions[s:e], t_near[s:e], t_far[s:e], first[s:e], end[s:e], ds)
        s = e


def assembled_blocks(grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5):
    """Yield the rows of :func:`assemble` block by block, by the compiled kernel
    (:mod:`~flamerecon.operators.compiled`; CPU, numba): (slice of rays, entries per row (R,)
    long, columns (E,) int32 ascending within each row, values (E,) float32)."""
    M = int(voxel_index.numel())
    column = torch.full((grid.num_voxels,), -1, dtype=torch.int32)
    column[voxel_index] = torch.arange(M, dtype=torch.int32)
    box, live = support_box(grid, voxel_index), cells_touching(grid, voxel_index)
    progress = Progress("assembling the operator", len(rays), "ray", every=PROGRESS_EVERY, after=PROGRESS_AFTER)
    for sl, seg in compiled_blocks(rays, grid, step, box):
        yield (sl, *compiled.assemble_block(seg, column, M, live, grid.resolution))
        progress.update(sl.stop)
        interrupt.check()


def _assemble_compiled(grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float) -> CsrOperator:
    """:func:`assemble` by the compiled kernel, block by block (:func:`assembled_blocks`)."""
    N = len(rays)
    counts = torch.zeros(N, dtype=torch.long)
    cols_out, vals_out = GrowingArray(torch.int32, "cpu"), GrowingArray(torch.float32, "cpu")
    for sl, n, col, val in assembled_blocks(grid, rays, voxel_index, step):
        counts[sl] = n
        cols_out.append(col)
        vals_out.append(val)
    crow = torch.zeros(N + 1, dtype=torch.long)
    torch.cumsum(counts, 0, out=crow[1:])
    return CsrOperator.from_csr(crow, cols_out.tensor(), vals_out.tensor(), (N, int(voxel_index.numel())))


#: rays assembled to estimate the operator's size (:func:`assembled_memory`): evenly spread over
#: the views, they put the nonzeros within about 2% of the full count (ScalarFlow, 1/4 to full
#: resolution, 128- to 256-cell grids) at under 1% of the assembly's time
ESTIMATE_RAYS = 4096
#: bytes of temporaries per ray sample of one chunk while assembling (points, 8 corner indices
#: and weights, run roots, sort keys): measured 110-130 (ScalarFlow, 2e6-sample chunks)
BYTES_PER_CHUNK_SAMPLE = 160
#: bytes of temporaries per entry of a block of the transpose (:func:`transpose_csr`)
BYTES_PER_TRANSPOSE_ENTRY = 48


@dataclass
class OperatorMemory:
    """Estimated size of the assembled operator: nonzeros, bytes kept (A, and A^T where the
    adjoint needs it: ``copies``), peak bytes."""

    nnz: int
    operator_bytes: int
    peak_bytes: int
    copies: int = 2

    @property
    def stored(self) -> str:
        return "A and A^T" if self.copies == 2 else "A"


#: new trilinear corners a line meets per voxel of length at most: 4 per cell face it crosses,
#: |dx| + |dy| + |dz| <= sqrt(3) faces per voxel; and a ray's at most beyond that: the 8 of
#: its first cell and 4 for each axis's rounding up of its crossings
CORNERS_PER_VOXEL = 4 * 3**0.5
CORNERS_PER_RAY = 8 + 3 * 4


def assembled_bound(grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5) -> int:
    """Peak bytes :func:`assemble` can take at most, from geometry alone (no sample assembled):
    every ray's chord through the hull's support box times :data:`CORNERS_PER_VOXEL`, plus
    :data:`CORNERS_PER_RAY` entries a ray, stored as :func:`assembled_memory` counts them, plus a block's temporaries."""
    N, M = len(rays), int(voxel_index.numel())
    if N == 0 or M == 0:
        return 4 * (N + M + 2)
    near, far = ray_box(rays, *support_box(grid, voxel_index.to(rays.origins.device)))
    voxels = float((far - near).clamp_min(0).sum()) / float(grid.voxel_size().min())
    nnz = CORNERS_PER_VOXEL * voxels + CORNERS_PER_RAY * N
    copies = 1 if compiled.available(rays.origins.device) else 2
    transient = 2 * 8 * 8 * compiled.BLOCK_SEGMENTS if copies == 1 else (
        BYTES_PER_CHUNK_SAMPLE * ASSEMBLY_CHUNK_SAMPLES + BYTES_PER_TRANSPOSE_ENTRY * TRANSPOSE_BLOCK)
    return int(copies * 8 * nnz + 4 * (N + M + 2) + transient)


def assembled_memory(
    grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
) -> OperatorMemory:
    """Estimate what :func:`assemble` would store and its peak memory beyond what is held
    before it, from the exact assembly of :data:`ESTIMATE_RAYS` rays spread evenly over
    ``rays``: the nonzeros scaled to every ray, A (and A^T, off the compiled kernels) at
    (4 + 4) bytes each, and at the peak the assembly's temporaries: the compiled march's block
    scratch, or the torch path's chunk and a transpose block."""
    N, M = len(rays), int(voxel_index.numel())
    device = rays.origins.device
    copies = 1 if compiled.available(device) else 2
    if N == 0 or M == 0:
        return OperatorMemory(0, 4 * (N + M + 2), 4 * (N + M + 2), copies)
    stride = max(1, N // ESTIMATE_RAYS)
    subset = rays[torch.arange(0, N, stride, device=device)]
    nnz = int(assemble(grid, subset, voxel_index, step).nnz * N / len(subset))
    entry = 4 + (4 if nnz < 2**31 else 8)  # value + column index, per copy
    operator_bytes = copies * entry * nnz + 4 * (N + M + 2)
    if copies == 1:  # a block's scratch (8 entries a segment) and its rows' copies
        transient = 2 * 8 * 8 * compiled.BLOCK_SEGMENTS
    else:
        chunk = min(nnz, ASSEMBLY_CHUNK_SAMPLES)  # about a sample per nonzero
        transient = max(BYTES_PER_CHUNK_SAMPLE * chunk, BYTES_PER_TRANSPOSE_ENTRY * min(nnz, TRANSPOSE_BLOCK))
    return OperatorMemory(nnz, operator_bytes, operator_bytes + transient, copies)


#: CPU seconds per ray segment of a matrix-free product (measured 15-40 ns by the compiled
#: march, hull cells and empty ones together, 33-60 ns by grid_sample, ScalarFlow 1/2 x 192)
SECONDS_PER_SEGMENT = 50e-9
#: products of A or A^T per solver iteration (the tv solver: 2 and its checks)
PRODUCTS_PER_ITERATION = 2.6


def matrix_free_seconds(rays: Rays, grid: VoxelGrid, step: float, voxel_index: torch.Tensor, iterations: int,
                        threads: int) -> float:
    """Wall seconds a matrix-free solve of ``iterations`` takes on ``threads`` cores: every
    product marches the rays' segments inside the hull's support box again."""
    _, _, first, end, _ = _segments(rays, grid, step, support_box(grid, voxel_index.to(rays.origins.device)))
    segments = float((end - first).clamp_min(0).sum())
    return segments * SECONDS_PER_SEGMENT * PRODUCTS_PER_ITERATION * max(int(iterations), 1) / max(int(threads), 1)


class MatrixFreeOperator:
    """Rays x hull voxels without storing weights: scatter into the grid, ``grid_sample``.

    ``forward`` (M, C) -> (N, C) is differentiable; ``adjoint`` is its vector-Jacobian product,
    taken block by block of ray samples (about :data:`CHUNK_SAMPLES` each), so both products
    hold one block's samples at a time whatever the number of rays. Every product marches
    every ray again: 150-300x the time of the assembled operator's (docs/results.md), which
    :func:`~flamerecon.operators.norm_sq` and the solvers read from :attr:`costly_products`.
    """

    costly_products = True

    def __init__(self, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5):
        self.grid, self.rays, self.step = grid, rays, float(step)
        self.voxel_index = voxel_index.to(rays.origins.device)
        self.box = support_box(grid, self.voxel_index)
        self.shape = (len(rays), int(voxel_index.numel()))
        self.compiled = compiled.available(rays.origins.device)
        if self.compiled:  # the rows are gathered on the fly by the compiled march
            self.column = torch.full((grid.num_voxels,), -1, dtype=torch.int32)
            self.column[self.voxel_index] = torch.arange(self.shape[1], dtype=torch.int32)
            self.live = cells_touching(grid, self.voxel_index)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.compiled:
            return _RowsProduct.apply(x, self)
        return integrate_dense(self.grid.dense(x, self.voxel_index), self.grid, self.rays, self.step, self.box)

    def rows(self, x: torch.Tensor, adjoint: bool) -> torch.Tensor:
        """A x (or A^T y for ``adjoint``) by the compiled march, block by block."""
        parts = []
        what = "the adjoint's march" if adjoint else "marching rays"
        progress = Progress(what, self.shape[0], "ray", every=PROGRESS_EVERY, after=PROGRESS_AFTER)
        x = x.detach().float().contiguous()
        out = x.new_zeros(self.shape[1], x.shape[1]) if adjoint else None
        for sl, seg in compiled_blocks(self.rays, self.grid, self.step, self.box):
            args = (seg, self.column, self.shape[1], self.live, self.grid.resolution)
            if adjoint:
                out += compiled.rows_adjoint(*args, x[sl])
            else:
                parts.append(compiled.rows_forward(*args, x))
            progress.update(sl.stop)
            interrupt.check()
        if adjoint:
            return out
        return torch.cat(parts) if parts else x.new_zeros(0, x.shape[1])

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        if self.compiled:
            return self.rows(y, adjoint=True).to(y.dtype)
        C = y.shape[1]
        volume = torch.zeros(C, *self.grid.shape, dtype=y.dtype, device=y.device, requires_grad=True)
        total = torch.zeros(C, *self.grid.shape, dtype=y.dtype, device=y.device)
        frame = self.grid.normalized_frame(y.device)
        progress = Progress("the adjoint's march", self.shape[0], "ray", every=PROGRESS_EVERY, after=PROGRESS_AFTER)
        with torch.enable_grad():
            for sl, smp in packed_samples(self.rays, self.grid, self.step, self.box, frame=frame):
                weighted = _sample(volume, smp.points) * smp.length  # (C, P)
                (grad,) = torch.autograd.grad(weighted, volume, grad_outputs=y[sl].index_select(0, smp.ray).T)
                total += grad
                progress.update(sl.stop)
                interrupt.check()
        return total.reshape(C, -1)[:, self.voxel_index].T.contiguous()


class _RowsProduct(torch.autograd.Function):
    """y = A x of a compiled :class:`MatrixFreeOperator`, with dL/dx = A^T dL/dy."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, op: MatrixFreeOperator) -> torch.Tensor:
        ctx.op = op
        return op.rows(x, adjoint=False).to(x.dtype)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        return ctx.op.rows(grad_out, adjoint=True).to(grad_out.dtype), None


#: voxels per side of the blocks whose projections bound where a render can be nonzero
FOOTPRINT_BLOCK = 2


def footprint(nonzero: torch.Tensor, grid: VoxelGrid, cams: PinholeCamera, block: int = FOOTPRINT_BLOCK
              ) -> torch.Tensor:
    """(B, H, W) bool: the pixels whose rays can meet a nonzero of the trilinear interpolant of
    a volume whose nonzero voxels are ``nonzero`` (nz, ny, nx) bool; every other pixel renders
    exactly 0. The nonzeros are grown by a voxel (the interpolant's reach), grouped in blocks of
    ``block`` voxels, and each occupied block's cells (grown by half a voxel) are bounded in every
    image by the rectangle of its 8 projected corners, widened by a pixel. A camera with a corner
    of an occupied block at or behind its centre plane keeps every pixel."""
    B, H, W = cams.batch_size, int(cams.height[0]), int(cams.width[0])
    device = nonzero.device
    grown = F.max_pool3d(nonzero[None, None].float(), 3, stride=1, padding=1)[0, 0]
    pad = [(-n) % block for n in grown.shape]  # (nz, ny, nx) up to whole blocks
    grown = F.pad(grown, (0, pad[2], 0, pad[1], 0, pad[0]))
    occupied = F.max_pool3d(grown[None, None], block, stride=block)[0, 0].nonzero()  # (K, 3) as k, j, i
    mask = torch.zeros(B, H + 1, W + 1, dtype=torch.int32, device=device)
    if occupied.numel() == 0:
        return mask[:, :H, :W] > 0
    size = grid.voxel_size(device)
    ijk = occupied.flip(1).to(size.dtype)  # (K, 3) as i, j, k
    lo = grid.lo(device) + (ijk * block - 0.5) * size
    hi = grid.lo(device) + ((ijk + 1) * block + 0.5) * size
    offsets = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=size.dtype, device=device)
    corners = (lo[:, None] + offsets * (hi - lo)[:, None]).reshape(-1, 3)  # (K * 8, 3)
    uv, depth = project_points(cams, corners)
    uv, depth = uv.reshape(B, -1, 8, 2), depth.reshape(B, -1, 8)
    # pixel centres are at (j + 0.5, i + 0.5): the columns j with j + 0.5 in [u_min, u_max], +- 1
    first = (uv.amin(2) - 0.5).floor().long() - 1  # (B, K, 2) as (u, v)
    last = (uv.amax(2) - 0.5).ceil().long() + 1
    limit = torch.tensor([W - 1, H - 1], device=device)
    first, last = first.clamp(min=0), torch.minimum(last, limit)
    inside = (first <= last).all(-1)  # (B, K): the rectangle meets the image
    for b in range(B):
        if bool((depth[b] <= 1e-6).any()):
            mask[b] = 1
            continue
        f, e = first[b][inside[b]], last[b][inside[b]] + 1
        # the union of rectangles by a 2-D difference array and its cumulative sums
        for (u, v), sign in (((f[:, 0], f[:, 1]), 1), ((e[:, 0], f[:, 1]), -1), ((f[:, 0], e[:, 1]), -1),
                             ((e[:, 0], e[:, 1]), 1)):
            mask[b].index_put_((v, u), torch.full_like(u, sign, dtype=torch.int32), accumulate=True)
    return mask.cumsum(1).cumsum(2)[:, :H, :W] > 0


def render_image(
    volume: torch.Tensor, grid: VoxelGrid, cams: PinholeCamera, step: float = 0.5,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Render every pixel of every camera: volume (C, nz, ny, nx) -> images (B, C, H, W).
    Only the pixels of the :func:`footprint` of the volume's nonzeros are marched, and only in
    the box of those nonzeros (everything else adds exactly 0). ``known``: pixels already
    rendered, their flat index ``b * H * W + v * W + u`` (K,) and values (K, C) (an assembled
    operator's A x: the same weights), taken as they are, not marched."""
    B, C = cams.batch_size, volume.shape[0]
    H, W = int(cams.height[0]), int(cams.width[0])
    with torch.no_grad():
        nonzero = volume.abs().sum(0) > 0
        box = support_box(grid, nonzero.reshape(-1).nonzero().squeeze(1))
        seen = footprint(nonzero, grid, cameras_to(cams, volume.device)).reshape(-1)
        pix = volume.new_zeros(B * H * W, C)
        if known is not None:
            index = known[0].to(volume.device)
            pix[index] = known[1].to(pix)
            seen[index] = False
        rays, _ = camera_rays(cams, seen.reshape(B, H, W).to(cams.intrinsics.device))
        pix[seen] = integrate_dense(volume, grid, rays.to(volume.device), step, box,
                                    f"rendering {B} view{'s' if B != 1 else ''} of {W}x{H} px")
    return pix.T.reshape(C, B, H, W).transpose(0, 1).contiguous()


def make_operator(
    backend: str, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
):
    """Build the ``assembled`` (CSR) or ``matrix_free`` operator for rays x hull voxels."""
    if backend == "assembled":
        return assemble(grid, rays, voxel_index, step)
    if backend == "matrix_free":
        return MatrixFreeOperator(grid, rays, voxel_index, step)
    raise ValueError(f"projector.backend: unknown backend '{backend}'; use 'assembled' or 'matrix_free'")
