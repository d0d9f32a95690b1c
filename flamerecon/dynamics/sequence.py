"""Frames that form one sequence, checked before any velocity is fitted: one grid box, one
resolution, one number of channels, the same training cameras (a velocity fitted between frames
that saw the smoke through different cameras carries one camera set's artefacts onto the
other's: issue 38 measured 3x the speed), consecutive frame numbers. Each refusal is one line
naming the two frames and the field that differs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

from flamerecon.errors import ArgumentError, ConfigError


@dataclass(frozen=True)
class FrameFacts:
    """What a frame of a sequence must share with the others: how a message names it
    (``label``), its ``frame`` number (None: not known), its grid box (``bbox_min``,
    ``bbox_max``, world xyz) and ``shape`` (nz, ny, nx), ``channels`` and the names of the
    cameras it was fitted to (``train``)."""

    label: str
    frame: int | None
    bbox_min: tuple[float, ...]
    bbox_max: tuple[float, ...]
    shape: tuple[int, ...]
    channels: int
    train: tuple[str, ...]


def _close(a: Sequence[float], b: Sequence[float]) -> bool:
    return all(abs(float(x) - float(y)) <= 1e-6 * max(1.0, abs(float(x))) for x, y in zip(a, b))


def check_sequence(frames: Sequence[FrameFacts], where: str, api: bool = False) -> None:
    """Refuse ``frames`` that are not one sequence (module doc): :class:`ConfigError` (a command
    line's sweep) or, with ``api``, :class:`ArgumentError`, the message starting with
    ``where`` when no frame's label says it."""
    error = ArgumentError if api else ConfigError
    if len(frames) < 2:
        raise error(f"{where}: a flow needs at least two consecutive frames; got {len(frames)}")
    first = frames[0]
    fix = "reconstruct every frame of the sequence with the same grid and cameras"
    for other in frames[1:]:
        differs = [
            ("grid box (bbox_min)", first.bbox_min, other.bbox_min, not _close(first.bbox_min, other.bbox_min)),
            ("grid box (bbox_max)", first.bbox_max, other.bbox_max, not _close(first.bbox_max, other.bbox_max)),
            ("grid resolution (nz, ny, nx)", first.shape, other.shape, tuple(first.shape) != tuple(other.shape)),
            ("channels", first.channels, other.channels, first.channels != other.channels),
            ("training cameras (holdout)", list(first.train), list(other.train),
             sorted(first.train) != sorted(other.train)),
        ]
        for name, a, b, bad in differs:
            if bad:
                raise error(f"{other.label}: its {name} {_shown(b)} differs from {first.label}'s {_shown(a)}; {fix} "
                            "(grid.bbox, grid.resolution, holdout)")
    numbers = [f.frame for f in frames]
    if all(isinstance(n, int) for n in numbers):
        gaps = [f"{a}-{b}" for a, b in pairwise(numbers) if b != a + 1]
        if gaps:
            raise error(f"{where}: frames {numbers} are not consecutive (gaps {gaps}); a velocity carries one frame "
                        "onto the next: reconstruct every frame of the stretch, in order")


def _shown(value) -> str:
    if isinstance(value, (tuple, list)) and value and isinstance(value[0], float):
        return "(" + ", ".join(f"{v:g}" for v in value) + ")"
    return str(tuple(value)) if isinstance(value, tuple) else str(value)
