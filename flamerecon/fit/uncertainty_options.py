"""The options of a reconstruction's confidence (``uncertainty:`` of ``conf/train.yaml``): which
ensemble :mod:`flamerecon.fit.ensemble` solves and how
:mod:`flamerecon.evaluate.uncertainty` turns it into predicted spreads."""

from __future__ import annotations

from dataclasses import dataclass

from flamerecon.fit.option_rules import check_section

#: ``uncertainty.members``: which members are solved
MEMBER_KINDS = ("cameras", "weights", "cameras+weights")


@dataclass(frozen=True)
class UncertaintyOptions:
    """The confidence of a reconstruction (``uncertainty:`` of ``conf/train.yaml``).

    ``enabled``: the run computes it after the solve (the Python API computes it on request,
    :func:`flamerecon.uncertainty`); ``members``: a kind of :data:`MEMBER_KINDS`;
    ``shift_voxels``: the density shifted by this many voxels along each axis, both ways, is
    six more members (where a structure is, to about this much; 0: none); ``scale``: the
    predicted one-sigma spread per unit of the ensemble's (chosen on frames that are not
    reported, docs/results.md); ``iterations``: solver steps of a member (None: the solver's
    ``max_iters``); ``weight_factor``: the ``weights`` members' factor."""

    enabled: bool = False
    members: str = "cameras"
    shift_voxels: float = 0.75
    scale: float = 0.95
    iterations: int | None = None
    weight_factor: float = 2.0

    def __post_init__(self) -> None:
        check_section("uncertainty", self)
