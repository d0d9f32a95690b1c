"""The voxel grid: an axis-aligned box cut into (nx, ny, nz) cells.

Voxel ``(k, j, i)`` (z, y, x order, x fastest, as in ``density.npz``) is the cell whose corner
nearest ``bbox_min`` is ``bbox_min + (i, j, k) * voxel_size``; its value sits at the cell
centre, exactly how ``torch.nn.functional.grid_sample(align_corners=False)`` reads a volume.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from flamerecon.arguments import value, wrong_value
from flamerecon.rules import either, integer, list_of, number

POINT = list_of(number(), 3, "(x, y, z) of finite numbers")
CELLS = list_of(integer(1), 3, "(nx, ny, nz) of integers >= 1")
SIZE = either(integer(1), list_of(integer(1), 1, "[n]"), CELLS)


def resolution_for_box(resolution, extent) -> tuple[int, int, int]:
    """(nx, ny, nz) from an int (cells along the longest side, others follow the aspect
    ratio) or from an explicit triple."""
    value("grid.resolution", resolution, SIZE)
    if not isinstance(resolution, (list, tuple)) or len(resolution) == 1:
        n = int(resolution if not isinstance(resolution, (list, tuple)) else resolution[0])
        ext = [float(e) for e in extent]
        longest = max(ext)
        return tuple(max(1, round(n * e / longest)) for e in ext)  # type: ignore[return-value]
    return tuple(int(r) for r in resolution)  # type: ignore[return-value]


@dataclass(frozen=True)
class VoxelGrid:
    """Box ``[bbox_min, bbox_max]`` (world units) split into ``resolution = (nx, ny, nz)`` cells."""

    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    resolution: tuple[int, int, int]

    def __post_init__(self) -> None:
        lo, hi = checked_box(self.bbox_min, self.bbox_max)
        cells = tuple(int(n) for n in value("VoxelGrid.resolution", as_sequence(self.resolution), CELLS))
        object.__setattr__(self, "bbox_min", lo)
        object.__setattr__(self, "bbox_max", hi)
        object.__setattr__(self, "resolution", cells)

    @classmethod
    def from_box(cls, bbox_min, bbox_max, resolution) -> VoxelGrid:
        """The box ``bbox_min``..``bbox_max`` cut into ``resolution`` cells: an int (along the
        longest side, the others following the aspect ratio) or (nx, ny, nz)."""
        lo, hi = checked_box(bbox_min, bbox_max)
        ext = [h - l for l, h in zip(lo, hi)]
        return cls(lo, hi, resolution_for_box(resolution, ext))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (nz, ny, nx)."""
        nx, ny, nz = self.resolution
        return (nz, ny, nx)

    @property
    def num_voxels(self) -> int:
        nx, ny, nz = self.resolution
        return nx * ny * nz

    def lo(self, device=None) -> torch.Tensor:
        return torch.tensor(self.bbox_min, dtype=torch.float32, device=device)

    def hi(self, device=None) -> torch.Tensor:
        return torch.tensor(self.bbox_max, dtype=torch.float32, device=device)

    def voxel_size(self, device=None) -> torch.Tensor:
        """Cell size (3,) in world units, xyz order."""
        return (self.hi(device) - self.lo(device)) / torch.tensor(
            self.resolution, dtype=torch.float32, device=device
        )

    def centers(self, device=None) -> torch.Tensor:
        """World xyz of every cell centre, (nz, ny, nx, 3)."""
        lo, size = self.lo(device), self.voxel_size(device)
        axes = [lo[a] + (torch.arange(self.resolution[a], device=device) + 0.5) * size[a] for a in range(3)]
        z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return torch.stack([x, y, z], dim=-1)

    def index_frame(self, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(scale (3,), offset (3,)) of :meth:`world_to_index`: ``xyz * scale + offset``."""
        size = self.voxel_size(device)
        return 1.0 / size, -self.lo(device) / size - 0.5

    def normalized_frame(self, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(scale (3,), offset (3,)) of :meth:`world_to_normalized`: ``xyz * scale + offset``."""
        extent = self.hi(device) - self.lo(device)
        return 2.0 / extent, -2.0 * self.lo(device) / extent - 1.0

    def world_to_index(self, xyz: torch.Tensor) -> torch.Tensor:
        """Continuous voxel coordinates (…, 3) as (i, j, k): cell centre ``i`` sits at ``i``."""
        scale, offset = self.index_frame(xyz.device)
        return torch.addcmul(offset.to(xyz.dtype), xyz, scale.to(xyz.dtype))

    def index_to_world(self, ijk: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`world_to_index`."""
        return self.lo(ijk.device) + (ijk + 0.5) * self.voxel_size(ijk.device)

    def world_to_normalized(self, xyz: torch.Tensor) -> torch.Tensor:
        """World xyz (…, 3) to grid_sample's [-1, 1] coordinates (align_corners=False)."""
        scale, offset = self.normalized_frame(xyz.device)
        return torch.addcmul(offset.to(xyz.dtype), xyz, scale.to(xyz.dtype))

    def corners(self) -> torch.Tensor:
        """The 8 corners of the box (8, 3)."""
        lo, hi = self.lo(), self.hi()
        c = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=torch.float32)
        return lo + c * (hi - lo)

    def dense(self, values: torch.Tensor, voxel_index: torch.Tensor) -> torch.Tensor:
        """Scatter values (M, C) of the voxels ``voxel_index`` (M,) (flat indices) into a dense
        volume (C, nz, ny, nx), zero elsewhere; differentiable in ``values``."""
        C = values.shape[1]
        vol = values.new_zeros(C, self.num_voxels).index_copy(1, voxel_index, values.T)
        return vol.reshape(C, *self.shape)

    def scaled(self, factor: float) -> VoxelGrid:
        """Same box, resolution multiplied by ``factor`` (coarse-to-fine, finer phantoms)."""
        res = tuple(max(1, round(r * factor)) for r in self.resolution)
        return VoxelGrid(self.bbox_min, self.bbox_max, res)  # type: ignore[arg-type]


def checked_box(bbox_min, bbox_max, owner: str = "VoxelGrid") -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The corners of a box as float triples, each three finite numbers, min < max; errors
    name ``owner.bbox_min`` / ``owner.bbox_max``."""
    lo = tuple(float(v) for v in value(f"{owner}.bbox_min", as_sequence(bbox_min), POINT))
    hi = tuple(float(v) for v in value(f"{owner}.bbox_max", as_sequence(bbox_max), POINT))
    if any(h <= l for l, h in zip(lo, hi)):
        raise wrong_value(f"{owner}.bbox_max", hi, f"above bbox_min {lo} on every axis (the box is empty)")
    return lo, hi


def as_sequence(given):
    """A tensor or array (of a point, of a size) as a list of Python numbers; others as given."""
    return given.tolist() if hasattr(given, "tolist") and not isinstance(given, (list, tuple)) else given
