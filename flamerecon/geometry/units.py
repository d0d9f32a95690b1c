"""A capture's length unit: metres per world unit (None where the calibration does not say), and
how figures and messages name lengths in it."""

from __future__ import annotations


def length_name(unit: float | None) -> str:
    """How to label a length in world units of ``unit`` metres (None: unknown)."""
    if unit is None:
        return "world units"
    for metres, name in ((1.0, "m"), (1e-2, "cm"), (1e-3, "mm")):
        if abs(unit / metres - 1.0) < 1e-9:
            return name
    return f"world units of {unit:g} m"


def display_length(unit: float | None, extent: float) -> tuple[float, str]:
    """(factor, name): world lengths times ``factor`` in the unit named ``name`` that suits a
    figure spanning ``extent`` world units: metres from 1 m, centimetres from 10 cm, else
    millimetres where ``unit`` is known; the world units themselves where it is not."""
    if unit is None:
        return 1.0, "world units"
    metres = extent * unit
    if metres >= 1.0:
        return unit, "m"
    if metres >= 0.1:
        return unit * 100.0, "cm"
    return unit * 1000.0, "mm"
