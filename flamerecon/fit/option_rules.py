"""Every option of ``conf/``, checked for type and range before any work, in one table.

:data:`RULES` maps a dotted key (``solver.max_iters``) to a :class:`Rule`; :func:`check_options`
walks a plain dict (the composed config, resolved) and raises one
:class:`~flamerecon.errors.ConfigError` naming the first key whose value breaks its rule:
``solver.max_iters: got 0; solver.max_iters must be an integer >= 1``. A number given as a
string (``solver.tol='1e-4'``: quoted on the command line) is refused as such. Keys without a
rule (``++scene.x=...`` extras) pass; ``tests/test_options_check.py`` makes sure every key of
every config group has one.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

from flamerecon.errors import ConfigError

Check = Callable[[object], str | None]  # value -> what is wrong with it, or None


@dataclass(frozen=True)
class Rule:
    """``check(value)`` returns None or what the value must be; ``null``: None is allowed."""

    check: Check
    null: bool = False


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _quoted_number(value) -> bool:
    if not isinstance(value, str):
        return False
    try:
        float(value)
    except ValueError:
        return False
    return True


def integer(lo: int | None = None, hi: int | None = None) -> Check:
    """An int (or an integral float, as ``1e3`` parses) in [lo, hi]."""
    want = ("an integer" + (f" >= {lo}" if lo is not None else "")
            + (f" <= {hi}" if hi is not None else ""))

    def check(value):
        if not _is_number(value) or not math.isfinite(value) or int(value) != value:
            return want
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            return want
        return None

    return check


def number(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           hi_open: bool = False) -> Check:
    """A finite int or float in the interval from lo to hi (open ends where asked)."""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    want = " and ".join(parts) if parts else "a finite number"

    def check(value):
        if not _is_number(value) or not math.isfinite(value):
            return want
        if lo is not None and (value <= lo if lo_open else value < lo):
            return want
        if hi is not None and (value >= hi if hi_open else value > hi):
            return want
        return None

    return check


def boolean(value) -> str | None:
    return None if isinstance(value, bool) else "true or false"


def text(value) -> str | None:
    return None if isinstance(value, str) and value != "" else "a non-empty string"


def choice(*values) -> Check:
    want = "one of " + ", ".join(str(v) for v in values)

    def check(value):
        return None if value in values and not isinstance(value, bool) else want

    check.choices = values
    return check


def either(*checks: Check) -> Check:
    """Any one of ``checks`` (the message lists them all)."""

    def check(value):
        wrong = [c(value) for c in checks]
        return None if None in wrong else " or ".join(dict.fromkeys(wrong))

    return check


def list_of(item: Check, length: int | None = None, what: str = "") -> Check:
    want = what or f"a list{f' of {length}' if length else ''}"

    def check(value):
        if not isinstance(value, (list, tuple)) or (length is not None and len(value) != length):
            return want
        return None if all(item(v) is None for v in value) else want

    return check


def pattern(regex: str, what: str) -> Check:
    return lambda value: None if isinstance(value, str) and re.fullmatch(regex, value) else what


_cells = integer(1)
_resolution = either(_cells, list_of(_cells, 3, "[nx, ny, nz] of integers >= 1"))
_box = list_of(list_of(number(), 3), 2, "[[xmin, ymin, zmin], [xmax, ymax, zmax]] of numbers")
_view = either(text, integer())
_views = either(_view, list_of(_view, what="a list of view names or indices"))

def candidate_table(value) -> str | None:
    """``select.candidates``: {solver name: [ {option: value}, ... ]}."""
    want = "a mapping of solver names to lists of option mappings, e.g. {tv: [{tv: 0.01}]}"
    if not isinstance(value, dict):
        return want
    for overrides in value.values():
        if overrides is None:
            continue
        if not isinstance(overrides, (list, tuple)) or not all(isinstance(o, dict) for o in overrides):
            return want
    return None


#: dotted key -> rule, for every option of conf/ (train.yaml and each group).
#: the silhouette options (``silhouette:``, and ``scene.silhouette:`` for a scene's box estimate).
SILHOUETTE: dict[str, Rule] = {
    "method": Rule(choice("otsu", "threshold")),
    "threshold": Rule(number(0), null=True),
    "speck_px": Rule(integer(0)),
    "dilate_px": Rule(integer(0)),
    "blur_px": Rule(number(0)),
    "close_px": Rule(integer(0)),
}

RULES: dict[str, Rule] = {
    # train.yaml
    "holdout": Rule(_views, null=True),
    "device": Rule(pattern(r"auto|cpu|cuda(:\d+)?", "auto, cpu, cuda or cuda:N")),
    "threads": Rule(integer(1), null=True),
    "seed": Rule(integer(0)),
    "init": Rule(text, null=True),
    "debug": Rule(boolean),
    "resume": Rule(text, null=True),
    "grid.resolution": Rule(_resolution),
    "grid.bbox": Rule(_box, null=True),
    "grid.levels": Rule(list_of(_resolution, what="a list of grid sizes (ints or [nx, ny, nz])"),
                        null=True),
    "grid.level_iters": Rule(
        either(integer(1), list_of(integer(1), what="a list of integers >= 1")), null=True),
    "projector.backend": Rule(choice("auto", "assembled", "matrix_free")),
    "projector.step": Rule(number(0.01)),  # voxels; finer only multiplies samples (and memory)
    "projector.max_memory_gb": Rule(number(0, lo_open=True), null=True),
    "projector.rays": Rule(choice("silhouette", "hull")),
    "debias.method": Rule(choice("none", "gain", "refit")),
    "debias.iterations": Rule(integer(1)),
    "calibration.refine": Rule(choice("none", "pose", "pose+intrinsics")),
    "calibration.rounds": Rule(integer(1)),
    "calibration.iterations": Rule(integer(1)),
    "calibration.band_px": Rule(integer(0)),
    "calibration.max_rays": Rule(integer(1)),
    "calibration.prior_rotation_deg": Rule(number(0, lo_open=True)),
    "calibration.prior_translation": Rule(number(0, lo_open=True)),
    "calibration.prior_focal": Rule(number(0, lo_open=True)),
    "calibration.prior_principal_px": Rule(number(0, lo_open=True)),
    "calibration.fit_against": Rule(choice("all", "others")),
    "calibration.resolution": Rule(integer(1), null=True),
    "calibration.frames": Rule(list_of(integer(0), what="a list of frame indices >= 0")),
    "calibration.gauge": Rule(choice("mean", "similarity")),
    "calibration.rig": Rule(boolean),
    "calibration.seed": Rule(integer(0)),
    "temporal.l2": Rule(number(0)),
    "temporal.tv": Rule(number(0)),
    "temporal.motion": Rule(choice("none", "shift")),
    "temporal.max_shift": Rule(integer(0)),
    "temporal.tol": Rule(number(0)),
    "select.auto": Rule(boolean),
    "select.candidates": Rule(candidate_table),
    "select.folds": Rule(integer(2)),
    "select.iterations": Rule(integer(1), null=True),
    **{f"silhouette.{k}": rule for k, rule in SILHOUETTE.items()},
    "hull.margin_voxels": Rule(integer(0)),
    "photometry.fit_gain": Rule(boolean),
    "photometry.fit_offset": Rule(boolean),
    "photometry.rounds": Rule(integer(1)),
    "log.eval_every": Rule(integer(0)),
    "log.eval_share": Rule(number(0, 1, lo_open=True), null=True),
    "checkpoint.every": Rule(integer(0)),
    "checkpoint.divergence_factor": Rule(number(0)),
    # solver/*.yaml
    "solver.name": Rule(text),
    "solver.l1": Rule(number(0), null=True),
    "solver.l1_rel": Rule(number(0), null=True),
    "solver.max_iters": Rule(integer(1), null=True),
    "solver.max_seconds": Rule(number(0, lo_open=True), null=True),
    "solver.tol": Rule(number(0)),
    "solver.check_every": Rule(integer(1)),
    "solver.lr": Rule(number(0, lo_open=True)),
    "solver.lr_final": Rule(number(0, 1, lo_open=True)),
    "solver.patience": Rule(integer(1)),
    "solver.damp": Rule(number(0)),
    "solver.nonneg": Rule(boolean),
    "solver.smooth": Rule(number(0)),
    "solver.max_voxels": Rule(integer(1)),
    "solver.memory": Rule(integer(1)),
    "solver.relax": Rule(number(0, 2, lo_open=True, hi_open=True)),
    "solver.tv": Rule(number(0)),
    "solver.dual_step": Rule(number(0, lo_open=True), null=True),
    "solver.warm_iters": Rule(integer(0)),
    "solver.cg_iters": Rule(integer(1)),
    "solver.cg_tol": Rule(number(0, 1, lo_open=True, hi_open=True)),
    # scene/*.yaml
    "scene.name": Rule(text),
    "scene.root": Rule(text),
    "scene.file": Rule(text),
    "scene.calibration": Rule(text, null=True),
    "scene.frame": Rule(integer(0)),
    "scene.frames": Rule(list_of(integer(0), 2, "[first, last] frame indices"), null=True),
    "scene.downscale": Rule(integer(1)),
    "scene.channels": Rule(choice(1, 3, "auto")),
    "scene.gamma": Rule(either(number(0, lo_open=True), choice("srgb"))),
    "scene.black_level": Rule(number(0, 1, hi_open=True)),
    "scene.bbox": Rule(_box, null=True),
    "scene.holdout": Rule(_views, null=True),
    **{f"scene.silhouette.{k}": rule for k, rule in SILHOUETTE.items()},  # the box estimate's
    "scene.n_cameras": Rule(integer(2)),
    "scene.width": Rule(integer(1)),
    "scene.height": Rule(integer(1)),
    "scene.seed": Rule(integer(0)),
    "scene.phantom_resolution": Rule(integer(2)),
    "scene.phantom_step": Rule(number(0.01)),
    "scene.noise": Rule(number(0)),
    "scene.peak": Rule(number(0, lo_open=True)),
    # export/*.yaml
    "export.formats": Rule(list_of(choice("vti", "nrrd", "raw", "all"),
                                   what="a list of vti, nrrd, raw, all")),
}


def problem(key: str, value) -> str | None:
    """What is wrong with ``value`` for ``key`` (None when fine or ``key`` has no rule)."""
    rule = RULES.get(key)
    if rule is None or (value is None and rule.null):
        return None
    want = rule.check(object() if value is None else value)
    if want is None:
        return None
    if rule.null:
        want += " or null"
    if _quoted_number(value) and rule.check(float(value)) is None:
        return (f"got the string '{value}' (quoted on the command line?); {key} must be {want}: "
                f"write {key}={value} without quotes")
    if isinstance(value, str) and hasattr(rule.check, "choices"):
        return f"unknown {key.rsplit('.', 1)[-1]} '{value}'; {key} must be {want}"
    return f"got {value!r}; {key} must be {want}"


def leaves(tree: dict, prefix: str = "") -> dict[str, object]:
    """{dotted key: value} of every leaf of a nested dict (lists are leaves)."""
    out = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and key not in RULES:
            out.update(leaves(v, key + "."))
        else:
            out[key] = v
    return out


#: solvers whose ``max_iters`` may be null (LARS: 10 path steps per voxel).
NULL_MAX_ITERS = ("lars",)


def check_options(config: dict) -> None:
    """Raise :class:`~flamerecon.errors.ConfigError` for the first option of ``config`` (a
    plain nested dict, ``hydra`` node excluded) that breaks its rule in :data:`RULES`."""
    flat = leaves({k: v for k, v in config.items() if k != "hydra"})
    for key, value in flat.items():
        wrong = problem(key, value)
        if wrong is not None:
            raise ConfigError(f"{key}: {wrong}")
    name = flat.get("solver.name")
    unbounded = "solver.max_iters" in flat and flat["solver.max_iters"] is None
    if unbounded and name not in NULL_MAX_ITERS:
        raise ConfigError(f"solver.max_iters: got None; solver {name} needs an integer >= 1 "
                          "(only lars takes null)")
