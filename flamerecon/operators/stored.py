"""An assembled operator kept in files, written block of rows by block of rows as it is
assembled, and the operator of a subset of its rows and columns read back block by block:
neither holds the stored matrix in memory (about :data:`READ_BLOCK_ENTRIES` entries at a time).

Files of a stored operator (``tag`` names one version of it): ``crow-<tag>.npy`` (N + 1,) int64
row pointers, ``col-<tag>.bin`` int32 column indices (ascending within each row) and
``val-<tag>.bin`` float32 values, raw, in row order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from flamerecon import interrupt
from flamerecon.operators import compiled
from flamerecon.operators.sparse import GrowingArray

#: entries read at a time (8 bytes each, and about 20 more while a block is selected)
READ_BLOCK_ENTRIES = 4_000_000


def files(folder: Path, tag: str) -> tuple[Path, Path, Path]:
    """The row pointers', column indices' and values' files of version ``tag`` in ``folder``."""
    return folder / f"crow-{tag}.npy", folder / f"col-{tag}.bin", folder / f"val-{tag}.bin"


class StoredWriter:
    """Writes an operator's rows, block after block (:meth:`append`), into ``folder``'s files
    of version ``tag``; :meth:`close` writes the row pointers and returns the entries."""

    def __init__(self, folder: Path, tag: str):
        self.crow_path, col_path, val_path = files(folder, tag)
        self.col, self.val = open(col_path, "wb"), open(val_path, "wb")  # noqa: SIM115 - closed by close()
        self.counts: list[torch.Tensor] = []

    def append(self, counts: torch.Tensor, col: torch.Tensor, val: torch.Tensor) -> None:
        """Rows of a block: entries per row (R,), columns (E,) int32 and values (E,) float32."""
        self.counts.append(counts.long())
        col.to(torch.int32).numpy().tofile(self.col)
        val.to(torch.float32).numpy().tofile(self.val)

    def close(self) -> int:
        self.col.close()
        self.val.close()
        counts = torch.cat(self.counts) if self.counts else torch.zeros(0, dtype=torch.long)
        crow = np.zeros(counts.numel() + 1, np.int64)
        np.cumsum(counts.numpy(), out=crow[1:])
        np.save(self.crow_path, crow)
        return int(crow[-1])

    def abandon(self) -> None:
        """Close the files without finishing (their folder is removed by the caller)."""
        self.col.close()
        self.val.close()


def select(counts: torch.Tensor, col: torch.Tensor, val: torch.Tensor, keep_rows: torch.Tensor,
           col_map: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rows ``keep_rows`` (R,) bool of a block of rows (entries per row (R,), columns (E,),
    values (E,)) restricted to the columns ``col_map`` keeps (each old column's new index, or
    -1): (entries per kept row, new columns (E',) int32, values (E',)), in the same order, so
    ascending columns stay ascending when ``col_map`` is increasing where it keeps. On the CPU
    with numba one compiled pass (:func:`~flamerecon.operators.compiled.select`)."""
    if compiled.available(col.device):
        return compiled.select(counts, col, val, keep_rows, col_map)
    R = int(counts.numel())
    row = torch.repeat_interleave(torch.arange(R, device=col.device), counts.to(col.device))
    new = col_map.index_select(0, col.long())
    keep = (new >= 0) & keep_rows.to(col.device).index_select(0, row)
    kept = torch.bincount(row[keep], minlength=R)[keep_rows.to(col.device)]
    return kept, new[keep].to(torch.int32), val[keep]


def read_selection(folder: Path, tag: str, keep_rows: torch.Tensor, col_map: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The stored operator's rows ``keep_rows`` (N,) bool restricted to the columns ``col_map``
    (M_stored,) keeps (see :func:`select`), read block by block: entries per kept row, columns
    (E,) int32 and values (E,) float32."""
    crow_path, col_path, val_path = files(folder, tag)
    crow = torch.from_numpy(np.load(crow_path))
    N = int(crow.numel()) - 1
    if int(keep_rows.numel()) != N:
        raise ValueError(f"read_selection: {N} stored rows, {int(keep_rows.numel())} to select from")
    counts_out = []
    cols, vals = GrowingArray(torch.int32, "cpu"), GrowingArray(torch.float32, "cpu")
    col_map = col_map.to(torch.int32)
    with open(col_path, "rb") as col_file, open(val_path, "rb") as val_file:
        r0 = 0
        while r0 < N:
            e0 = int(crow[r0])
            r1 = int(torch.searchsorted(crow, e0 + READ_BLOCK_ENTRIES, right=True)) - 1
            r1 = min(N, max(r1, r0 + 1))
            n = int(crow[r1]) - e0
            col = torch.from_numpy(np.fromfile(col_file, np.int32, n))
            val = torch.from_numpy(np.fromfile(val_file, np.float32, n))
            if col.numel() != n or val.numel() != n:
                raise OSError(f"{col_path}: the stored operator ends early (entry {e0 + col.numel()} of {int(crow[-1])})")
            kept, c, v = select(crow[r0 + 1:r1 + 1] - crow[r0:r1], col, val, keep_rows[r0:r1], col_map)
            counts_out.append(kept)
            cols.append(c)
            vals.append(v)
            interrupt.check()
            r0 = r1
    counts = torch.cat(counts_out) if counts_out else torch.zeros(0, dtype=torch.long)
    return counts, cols.tensor(), vals.tensor()
