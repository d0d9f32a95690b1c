"""Typed options of a reconstruction: what ``conf/train.yaml`` says, as dataclasses.

The core (:mod:`flamerecon.fit.build`, :mod:`flamerecon.fit.reconstruct`) takes these; only the run
layer reads Hydra configs, converting one to :class:`ReconstructionOptions` once
(:func:`ReconstructionOptions.from_dict` on the plain dict). The defaults are the CLI's
(``tests/test_options.py`` holds them equal to the composed ``conf/``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from flamerecon.arguments import instance, one_or_many, wrong_value
from flamerecon.errors import ArgumentError, ConfigError, FlameReconError
from flamerecon.fit.debias import DebiasOptions
from flamerecon.fit.levels import LadderOptions
from flamerecon.fit.option_rules import (
    NULL_MAX_ITERS,
    check_fields,
    check_needs,
    check_options,
    check_section,
    leaves,
)
from flamerecon.fit.refine_cameras import RefineOptions
from flamerecon.fit.uncertainty_options import UncertaintyOptions
from flamerecon.fit.weight_selection import SelectionOptions
from flamerecon.plain import plain
from flamerecon.solvers import SOLVERS
from flamerecon.solvers.base import option_names


@dataclass(frozen=True)
class GridOptions:
    """``resolution``: cells along the box's longest side, or (nx, ny, nz); ``bbox``: ((xmin,
    ymin, zmin), (xmax, ymax, zmax)) world units, None = the scene's box; ``levels``: coarser
    resolutions solved first, coarsest first; ``level_iters``: their iteration budgets (None:
    the solver's, an int, or one per level)."""

    resolution: int | tuple[int, int, int] = 64
    bbox: tuple | None = None
    levels: tuple = ()
    level_iters: int | tuple | None = None

    def __post_init__(self) -> None:
        check_section("grid", self)
        if self.bbox is not None and not all(lo < hi for lo, hi in zip(*self.bbox)):
            raise wrong_value("grid.bbox", self.bbox, "((xmin, ymin, zmin), (xmax, ymax, zmax)) with min < max on every axis")


@dataclass(frozen=True)
class ProjectorOptions:
    """``backend``: assembled | matrix_free | auto; ``step``: ray-march segment in voxels;
    ``rays``: silhouette | hull (also the background pixels whose ray meets the hull);
    ``max_memory_gb``: what the operator may take (None: 80% of the device's free memory);
    ``reuse``: the capture's region operator (:mod:`~flamerecon.fit.capture_operator`): ``auto``
    reads one that holds the frame, ``true`` also builds one (a sequence), ``false`` neither."""

    backend: str = "auto"
    step: float = 0.5
    rays: str = "silhouette"
    max_memory_gb: float | None = None
    reuse: bool | str = "auto"

    def __post_init__(self) -> None:
        check_section("projector", self)


@dataclass(frozen=True)
class SilhouetteOptions:
    """Keyword arguments of :func:`flamerecon.geometry.silhouettes.silhouettes` (pixels)."""

    method: str = "threshold"
    threshold: float | None = 0.03
    speck_px: int = 1
    dilate_px: int = 2
    blur_px: float = 0.0
    close_px: int = 0

    def __post_init__(self) -> None:
        check_section("silhouette", self)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class HullOptions:
    """``margin_voxels``: cells the visual hull is grown by."""

    margin_voxels: int = 1

    def __post_init__(self) -> None:
        check_section("hull", self)


@dataclass(frozen=True)
class PhotometryOptions:
    """After the solve, ``rounds`` times: fit each training camera's gain (and ``fit_offset``:
    offset) to the density's line integrals, then solve again (``fit_gain``: on)."""

    fit_gain: bool = False
    fit_offset: bool = True
    rounds: int = 2

    def __post_init__(self) -> None:
        check_section("photometry", self)


@dataclass(frozen=True)
class SolverOptions:
    """The solver ``name`` with ``l1`` (absolute weight, wins) or ``l1_rel`` (times max(A^T P))
    and ``params``, the solver's own keyword options (checked strictly by
    :func:`~flamerecon.solvers.make_solver`). The default is ``conf/solver/pqn_smooth.yaml``."""

    name: str = "pqn_smooth"
    l1: float | None = None
    l1_rel: float | None = 1.0e-3
    params: Mapping[str, Any] = field(default_factory=lambda: {
        "smooth": 0.01, "max_iters": 100, "max_seconds": None, "tol": 1.0e-4, "check_every": 10,
        "memory": 10})

    def __post_init__(self) -> None:
        check_fields("solver", {"name": self.name, "l1": self.l1, "l1_rel": self.l1_rel})
        if self.name not in SOLVERS:
            raise ArgumentError(f"solver.name: unknown solver '{self.name}'; choose one of {sorted(SOLVERS)}")
        instance("solver.params", self.params, Mapping, "a mapping of the solver's options")
        valid = option_names(SOLVERS[self.name])
        unknown = [key for key in self.params if key not in valid]
        if unknown:
            raise ArgumentError(f"solver.{unknown[0]}: unknown option of solver '{self.name}'; valid: "
                                f"{', '.join(valid)} (and name, l1, l1_rel)")
        check_fields("solver", self.params)
        if "max_iters" in self.params and self.params["max_iters"] is None and self.name not in NULL_MAX_ITERS:
            raise ArgumentError(f"solver.max_iters: got None; solver {self.name} needs an integer >= 1 "
                                f"(only {', '.join(NULL_MAX_ITERS)} takes None)")

    @classmethod
    def from_dict(cls, node: Mapping) -> SolverOptions:
        """From a ``solver:`` node: ``name``, ``l1``, ``l1_rel`` and the solver's own keys."""
        node = dict(node)
        if "name" not in node:
            raise ConfigError("solver.name: missing; name a solver (e.g. fista, tv)")
        return cls(node.pop("name"), node.pop("l1", None), node.pop("l1_rel", None), node)

    def as_dict(self) -> dict:
        """The ``solver:`` node back: name, l1, l1_rel and params in one mapping."""
        return {"name": self.name, "l1": self.l1, "l1_rel": self.l1_rel, **self.params}

    def with_values(self, **values) -> SolverOptions:
        """These options with some keys (``l1``, ``l1_rel`` or params) replaced."""
        return SolverOptions.from_dict({**self.as_dict(), **values})


def default_candidates() -> dict[str, tuple[dict, ...]]:
    """``select.candidates`` of ``conf/train.yaml``: per solver, weights strongest first."""
    return {
        "tv": ({"l1_rel": 0.01, "tv": 0.03}, {"l1_rel": 3.0e-3, "tv": 0.01}, {"l1_rel": 1.0e-3, "tv": 3.0e-3},
               {"l1_rel": 1.0e-3, "tv": 1.0e-3}, {"l1_rel": 3.0e-4, "tv": 3.0e-4}),
        "fista": ({"l1_rel": 0.01}, {"l1_rel": 1.0e-3}, {"l1_rel": 0.0}),
    }


@dataclass(frozen=True)
class SelectOptions:
    """``auto``: choose the solver's weights at run time by leave-one-view-out over
    ``candidates[solver.name]`` (``folds`` cameras left out in turn, ``iterations`` per fold
    solve, None: the solver's own)."""

    auto: bool = False
    candidates: Mapping[str, tuple[dict, ...]] = field(default_factory=default_candidates)
    folds: int = 4
    iterations: int | None = 100

    def __post_init__(self) -> None:
        check_section("select", self)
        # lists from a config become tuples: options compare equal
        object.__setattr__(self, "candidates", {k: tuple(dict(c) for c in v or ()) for k, v in self.candidates.items()})

    def for_solver(self, name: str) -> SelectionOptions | None:
        """The selection for solver ``name``; None when off or it has no candidates."""
        found = tuple(dict(c) for c in (self.candidates.get(name) or ())) if self.auto else ()
        if not found:
            return None
        try:
            return SelectionOptions(found, int(self.folds), None if self.iterations is None else int(self.iterations))
        except (TypeError, ValueError) as err:
            raise ConfigError(f"select: {err}") from err


SECTIONS = {"grid": GridOptions, "projector": ProjectorOptions, "silhouette": SilhouetteOptions,
            "hull": HullOptions, "photometry": PhotometryOptions, "debias": DebiasOptions,
            "calibration": RefineOptions, "select": SelectOptions, "ladder": LadderOptions,
            "uncertainty": UncertaintyOptions}


@dataclass(frozen=True)
class ReconstructionOptions:
    """Everything the core needs for one reconstruction (``conf/train.yaml`` less the run
    layer's keys: scene, log, checkpoint, export, resume, debug, temporal)."""

    grid: GridOptions = field(default_factory=GridOptions)
    projector: ProjectorOptions = field(default_factory=ProjectorOptions)
    silhouette: SilhouetteOptions = field(default_factory=SilhouetteOptions)
    hull: HullOptions = field(default_factory=HullOptions)
    solver: SolverOptions = field(default_factory=SolverOptions)
    photometry: PhotometryOptions = field(default_factory=PhotometryOptions)
    debias: DebiasOptions = field(default_factory=DebiasOptions)
    calibration: RefineOptions = field(default_factory=RefineOptions)
    select: SelectOptions = field(default_factory=SelectOptions)
    ladder: LadderOptions = field(default_factory=LadderOptions)
    uncertainty: UncertaintyOptions = field(default_factory=UncertaintyOptions)
    holdout: tuple | None = None  # view names or indices; None: the scene's default
    init: str | None = None  # a finished run's folder or density.npz to warm-start from
    seed: int = 0
    device: str = "auto"
    threads: int | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name in SECTIONS or f.name == "solver":
                kind = SECTIONS.get(f.name, SolverOptions)
                instance(f.name, getattr(self, f.name), kind,
                         f"a {kind.__name__} (a dict of options goes through ReconstructionOptions.from_dict)")
        holdout = one_or_many(self.holdout)  # one view, not its name's characters
        object.__setattr__(self, "holdout", tuple(holdout) if isinstance(holdout, list) else holdout)
        check_fields("", {k: getattr(self, k) for k in ("holdout", "init", "seed", "device", "threads")})
        check_needs(leaves(self.as_dict()), ArgumentError)

    @classmethod
    def from_dict(cls, config: Mapping, ignore: tuple[str, ...] = ()) -> ReconstructionOptions:
        """From a plain nested dict shaped like ``conf/train.yaml`` (absent keys keep their
        defaults). Keys in ``ignore`` are skipped; any other unknown key is a
        :class:`~flamerecon.errors.ConfigError` naming it and the valid ones."""
        valid = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(config) - valid - set(ignore))
        if unknown:
            raise ConfigError(f"options: unknown key {unknown[0]!r}; valid keys are {sorted(valid)}")
        values: dict[str, Any] = {}
        for key, node in config.items():
            if key in ignore:
                continue
            if key == "solver":
                values[key] = SolverOptions.from_dict(node)
            elif key in SECTIONS:
                values[key] = section(key, SECTIONS[key], node or {})
            else:
                values[key] = node
        return cls(**values)

    def as_dict(self) -> dict:
        """The options as a plain nested dict shaped like ``conf/train.yaml`` (tuples as lists)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out = {k: v.as_dict() if isinstance(v, SolverOptions) else
               dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v for k, v in out.items()}
        return plain(out)

    def check(self) -> ReconstructionOptions:
        """These options, after every value is checked against the CLI's rules
        (:func:`~flamerecon.fit.option_rules.check_options`: ranges, types, choices); a
        :class:`~flamerecon.errors.ConfigError` names the first that breaks its rule."""
        check_options(self.as_dict())
        return self

    def replace(self, **changes) -> ReconstructionOptions:
        """A copy with some fields replaced (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)


def section(name: str, cls: type, node: Mapping):
    """``cls(**node)`` with the config's error messages: an unknown key names the section."""
    valid = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in node if k not in valid]
    if unknown:
        raise ConfigError(f"{name}: unknown key '{unknown[0]}'; valid keys are {valid}")
    try:
        return cls(**node)
    except FlameReconError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err) if str(err).startswith(f"{name}.") else f"{name}: {err}") from err
