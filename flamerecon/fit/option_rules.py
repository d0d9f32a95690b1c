"""Every option of ``conf/``, checked for type and range before any work, in one table.

:data:`RULES` maps a dotted key (``solver.max_iters``) to a :class:`Rule`; :func:`check_options`
walks a plain dict (the composed config, resolved) and raises one
:class:`~flamerecon.errors.ConfigError` naming the first key whose value breaks its rule:
``solver.max_iters: got 0; solver.max_iters must be an integer >= 1``. A number given as a
string (``solver.tol='1e-4'``: quoted on the command line) is refused as such. Keys without a
rule (``++scene.x=...`` extras) pass; ``tests/test_options_check.py`` makes sure every key of
every config group has one.

An option that sizes a resource (threads, iteration and round counts, memory, history and shift
sizes) has an upper bound (:class:`Cap`) tied to what the machine has or to what the method can
use, refused by name: ``threads: got 1000000; threads must be at most 2 (this machine's cores)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from flamerecon.arguments import describe
from flamerecon.errors import ArgumentError, ArgumentTypeError, ConfigError, FlameReconError
from flamerecon.geometry.axes import UP_AXES
from flamerecon.machine import cores, format_bytes, total_bytes
from flamerecon.rules import (
    Check,
    boolean,
    choice,
    either,
    integer,
    is_number,
    list_of,
    number,
    of_type,
    pattern,
    quoted_number,
    takes,
    text,
)


@dataclass(frozen=True)
class Cap:
    """An upper bound on an option that sizes a resource: ``most()`` the largest value this
    machine (or the method) can take, None where it cannot be told; ``why(most)`` says why, in
    the message."""

    most: Callable[[], float | None]
    why: Callable[[float], str]

    def problem(self, key: str, value) -> str | None:
        """What is wrong with ``value`` (a number, or a list of them) for ``key``, or None."""
        most = self.most()
        numbers = value if isinstance(value, (list, tuple)) else [value]
        over = [v for v in numbers if is_number(v) and most is not None and v > most]
        if not over:
            return None
        shown = f"{int(most):,}".replace(",", "_") if float(most).is_integer() else f"{most:g}"
        return f"got {value!r}; {key} must be at most {shown} ({self.why(most)})"


@dataclass(frozen=True)
class Rule:
    """``check(value)`` returns None or what the value must be; ``null``: None is allowed;
    ``cap``: the upper bound of an option that sizes a resource."""

    check: Check
    null: bool = False
    cap: Cap | None = None


#: the most iterations one solve (or camera fit, refit, inner loop) may be given: at a
#: millisecond each that is about 3 hours; more runs for days (solver.max_seconds bounds time)
MAX_ITERATIONS = 10**7
#: the most rounds (each a whole solve or camera fit) an option may ask for
MAX_ROUNDS = 1000
#: the most L-BFGS pairs kept (each holds two copies of the density; 3-20 are the useful range)
MAX_MEMORY_PAIRS = 1000
#: the most cells a whole-cell motion search may shift by (it pads every volume by as much on
#: each side and scores (2 max_shift + 1)^3 shifts)
MAX_SHIFT = 64
#: the most frames one motion window may hold (each frame's views are loaded and projected)
MAX_WINDOW = 101
#: the most control cells of a motion field along the grid's longest side
MAX_CONTROL = 256
#: the most frames one joint solve (scene.frames) may hold: each holds its own operator
MAX_JOINT_FRAMES = 1000
#: the most frames one advection or simulation may be carried (each a pass over the grid; 10_000
#: frames are over five minutes of a 30 fps video)
MAX_STEPS = 10_000


def _fixed(most: float, why: str) -> Cap:
    return Cap(lambda: most, lambda _: why)


_iterations = _fixed(MAX_ITERATIONS, "a longer solve runs for days; bound its time with solver.max_seconds")
_rounds = _fixed(MAX_ROUNDS, "each round is a whole solve")
_threads = Cap(cores, lambda _: "this machine's cores; more threads only fight over them")


def _gigabytes() -> float | None:
    total = total_bytes()
    return None if total is None else round(total / 2**30, 1)


def _gram_voxels() -> float | None:
    """The most unknowns whose dense Gram matrix (8 M^2 bytes) fits in this machine's memory."""
    total = total_bytes()
    return None if total is None else float(int((total / 8) ** 0.5))


_memory_gb = Cap(_gigabytes, lambda gb: f"the memory this machine has, {format_bytes(gb * 2**30)}")
_lars_voxels = Cap(_gram_voxels, lambda m: f"the LARS path holds a dense M x M Gram matrix, 8 M^2 bytes: "
                   f"{format_bytes(8 * m * m)} is this machine's memory")


_cells = integer(1)
_resolution = either(_cells, list_of(_cells, 3, "[nx, ny, nz] of integers >= 1"))
_box = list_of(list_of(number(), 3), 2, "[[xmin, ymin, zmin], [xmax, ymax, zmax]] of numbers")
_view = either(text, integer())
_views = either(_view, list_of(_view, what="a list of view names or indices"))


@takes(list, tuple)
def rung(value) -> str | None:
    """``ladder.rungs`` entry: [downscale (an integer >= 1), grid resolution (int or [nx, ny, nz])]."""
    want = "a rung [downscale, grid resolution], e.g. [4, 128]"
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        return want
    return None if integer(1)(value[0]) is None and _resolution(value[1]) is None else want


@takes(dict)
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
    "threads": Rule(integer(1), null=True, cap=_threads),
    "seed": Rule(integer(0)),
    "init": Rule(text, null=True),
    "debug": Rule(boolean),
    "resume": Rule(text, null=True),
    "overwrite": Rule(boolean),
    "leave_one_out": Rule(boolean),
    "grid.resolution": Rule(_resolution),
    "grid.bbox": Rule(_box, null=True),
    "grid.levels": Rule(list_of(_resolution, what="a list of grid sizes (ints or [nx, ny, nz])"),
                        null=True),
    "grid.level_iters": Rule(
        either(integer(1), list_of(integer(1), what="a list of integers >= 1")), null=True, cap=_iterations),
    "ladder.rungs": Rule(list_of(rung, what="a list of rungs [downscale, grid resolution], e.g. [[4, 128], [2, 192]]")),
    "ladder.iterations": Rule(either(integer(1), list_of(integer(1), what="a list of integers >= 1")), null=True,
                              cap=_iterations),
    "ladder.final_iterations": Rule(integer(1), null=True, cap=_iterations),
    "projector.backend": Rule(choice("auto", "assembled", "matrix_free")),
    "projector.step": Rule(number(0.01)),  # voxels; finer only multiplies samples (and memory)
    "projector.max_memory_gb": Rule(number(0, lo_open=True), null=True, cap=_memory_gb),
    "projector.rays": Rule(choice("silhouette", "hull")),
    "projector.reuse": Rule(either(choice("auto"), boolean)),
    "debias.method": Rule(choice("none", "gain", "refit")),
    "debias.iterations": Rule(integer(1), cap=_iterations),
    "calibration.refine": Rule(choice("none", "pose", "pose+intrinsics")),
    "calibration.rounds": Rule(integer(1), cap=_rounds),
    "calibration.iterations": Rule(integer(1), cap=_iterations),
    "calibration.band_px": Rule(integer(0)),
    "calibration.max_rays": Rule(integer(1)),
    "calibration.prior_rotation_deg": Rule(number(0, lo_open=True)),
    "calibration.prior_translation": Rule(number(0, lo_open=True)),
    "calibration.prior_focal": Rule(number(0, lo_open=True)),
    "calibration.prior_principal_px": Rule(number(0, lo_open=True)),
    "calibration.fit_against": Rule(choice("all", "others")),
    "calibration.resolution": Rule(integer(1), null=True),
    "calibration.frames": Rule(either(choice("auto"), list_of(integer(0), what="a list of frame indices >= 0 or auto"))),
    "calibration.gauge": Rule(choice("mean", "similarity")),
    "calibration.rig": Rule(boolean),
    "calibration.first_iterations": Rule(integer(1), null=True, cap=_iterations),
    "calibration.solve_iterations": Rule(integer(1), null=True, cap=_iterations),
    "calibration.seed": Rule(integer(0)),
    "calibration.folder": Rule(text, null=True),
    "calibration.file": Rule(text, null=True),
    "calibration.score_before": Rule(boolean),
    "calibration.min_gain": Rule(number(0, 1)),
    "calibration.offsets": Rule(boolean),
    "temporal.l2": Rule(number(0)),
    "temporal.tv": Rule(number(0)),
    "temporal.motion": Rule(choice("none", "shift")),
    "temporal.max_shift": Rule(integer(0), cap=_fixed(MAX_SHIFT, "the search pads every volume by it")),
    "temporal.tol": Rule(number(0)),
    "motion.window": Rule(integer(1), cap=_fixed(MAX_WINDOW, "every frame of the window is loaded and projected")),
    "motion.decay": Rule(number(0, 1)),
    "motion.control": Rule(integer(2), cap=_fixed(MAX_CONTROL, "control cells along the grid's longest side")),
    "motion.smooth": Rule(number(0)),
    "motion.iters": Rule(integer(1), cap=_iterations),
    "motion.max_shift": Rule(integer(0), cap=_fixed(MAX_SHIFT, "the search pads every volume by it")),
    "motion.fit_to": Rule(choice("density", "images")),
    "flow.control": Rule(integer(2), cap=_fixed(MAX_CONTROL, "control cells along the grid's longest side")),
    "flow.smooth": Rule(number(0)),
    "flow.divergence": Rule(number(0)),
    "flow.inflow": Rule(number(0, 1, hi_open=True)),
    "flow.outside": Rule(number(0)),
    "flow.iters": Rule(integer(1), cap=_iterations),
    "flow.warm_iters": Rule(integer(1), cap=_iterations),
    "flow.warm_start": Rule(boolean),
    "flow.margin": Rule(integer(1), cap=_fixed(MAX_SHIFT, "cells around the smoke the fit reads")),
    "advect.steps": Rule(integer(0), cap=_fixed(MAX_STEPS, "frames carried, each a pass over the grid")),
    "simulation.window": Rule(integer(1), cap=_fixed(MAX_WINDOW, "every frame of the window keeps its operator")),
    "simulation.control": Rule(integer(2), cap=_fixed(MAX_CONTROL, "control cells along the grid's longest side")),
    "simulation.smooth": Rule(number(0)),
    "simulation.buoyancy": Rule(number()),
    "simulation.fit_buoyancy": Rule(boolean),
    "simulation.iters": Rule(integer(1), cap=_iterations),
    "simulation.inflow": Rule(number(0, 1, hi_open=True)),
    "simulation.scheme": Rule(choice("semi_lagrangian", "maccormack")),
    "simulation.pad": Rule(integer(0), cap=_fixed(MAX_SHIFT, "still cells around the box, each side")),
    "simulation.margin": Rule(integer(0), cap=_fixed(MAX_SHIFT, "cells kept around the smoke, each side")),
    "simulation.outside": Rule(number(0)),
    "simulation.incompressible": Rule(boolean),
    "simulation.self_advection": Rule(boolean),
    "simulation.start": Rule(choice("flow", "assimilated")),
    "simulation.up": Rule(choice("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z"), null=True),
    "simulation.frame_rate": Rule(number(0, lo_open=True), null=True),
    "flow.up": Rule(choice("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z"), null=True),
    "flow.frame_rate": Rule(number(0, lo_open=True), null=True),
    "select.auto": Rule(boolean),
    "select.candidates": Rule(candidate_table),
    "select.folds": Rule(integer(2)),
    "select.iterations": Rule(integer(1), null=True, cap=_iterations),
    "uncertainty.enabled": Rule(boolean),
    "uncertainty.members": Rule(choice("cameras", "weights", "cameras+weights")),
    "uncertainty.shift_voxels": Rule(number(0, 2)),
    "uncertainty.scale": Rule(number(0, lo_open=True)),
    "uncertainty.iterations": Rule(integer(1), null=True, cap=_iterations),
    "uncertainty.weight_factor": Rule(number(1, lo_open=True)),
    **{f"silhouette.{k}": rule for k, rule in SILHOUETTE.items()},
    "hull.margin_voxels": Rule(integer(0)),
    "photometry.fit_gain": Rule(boolean),
    "photometry.fit_offset": Rule(boolean),
    "photometry.rounds": Rule(integer(1), cap=_rounds),
    "log.eval_every": Rule(integer(0)),
    "log.eval_share": Rule(number(0, 1, lo_open=True), null=True),
    "checkpoint.every": Rule(integer(0)),
    "checkpoint.divergence_factor": Rule(number(0)),
    # solver/*.yaml
    "solver.name": Rule(text),
    "solver.l1": Rule(number(0), null=True),
    "solver.l1_rel": Rule(number(0), null=True),
    "solver.max_iters": Rule(integer(1), null=True, cap=_iterations),
    "solver.max_seconds": Rule(number(0, lo_open=True), null=True),
    "solver.tol": Rule(number(0)),
    "solver.check_every": Rule(integer(1)),
    "solver.lr": Rule(number(0, lo_open=True)),
    "solver.lr_final": Rule(number(0, 1, lo_open=True)),
    "solver.patience": Rule(integer(1)),
    "solver.damp": Rule(number(0)),
    "solver.nonneg": Rule(boolean),
    "solver.smooth": Rule(number(0)),
    "solver.max_voxels": Rule(integer(1), cap=_lars_voxels),
    "solver.memory": Rule(integer(1), cap=_fixed(MAX_MEMORY_PAIRS, "each pair holds two copies of the density")),
    "solver.relax": Rule(number(0, 2, lo_open=True, hi_open=True)),  # mart: <= 1, its own check
    "solver.order": Rule(choice("fixed", "shuffled")),
    "solver.tv": Rule(number(0)),
    "solver.dual_step": Rule(number(0, lo_open=True), null=True),
    "solver.reweight_rounds": Rule(integer(0), cap=_rounds),
    "solver.reweight_eps": Rule(number(0, lo_open=True)),
    "solver.reweight": Rule(choice("tv", "l1", "both")),
    "solver.warm_iters": Rule(integer(0), cap=_iterations),
    "solver.cg_iters": Rule(integer(1), cap=_iterations),
    "solver.cg_tol": Rule(number(0, 1, lo_open=True, hi_open=True)),
    "solver.sigma": Rule(number(0, lo_open=True)),
    "solver.sigma_growth": Rule(number(1)),
    "solver.sigma_max": Rule(number(0, lo_open=True)),
    "solver.newton_iters": Rule(integer(1), cap=_iterations),
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
    "scene.up": Rule(choice("auto", *UP_AXES, "x", "y", "z")),
    "scene.unit": Rule(number(0, lo_open=True), null=True),
    "scene.frame_rate": Rule(number(0, lo_open=True), null=True),
    **{f"scene.silhouette.{k}": rule for k, rule in SILHOUETTE.items()},  # the box estimate's
    "scene.n_cameras": Rule(integer(2)),
    "scene.width": Rule(integer(1)),
    "scene.height": Rule(integer(1)),
    "scene.seed": Rule(integer(0)),
    "scene.phantom_resolution": Rule(integer(2)),
    "scene.phantom_step": Rule(number(0.01)),
    "scene.noise": Rule(number(0)),
    "scene.peak": Rule(number(0, lo_open=True)),
    "scene.field": Rule(choice("turbulent", "smooth")),
    "scene.azimuths": Rule(list_of(number(), what="a list of camera azimuths in degrees"), null=True),
    "scene.calibration_error": Rule(number(0)),
    "scene.rise": Rule(number(0)),
    "scene.swirl": Rule(number()),
    # export/*.yaml
    "export.formats": Rule(list_of(choice("vti", "nrrd", "raw", "vdb", "ply", "obj", "mesh", "all"),
                                   what="a list of vti, nrrd, raw, vdb, ply, obj, mesh, all")),
    "export.iso": Rule(number(0, 1, lo_open=True, hi_open=True)),
}


def problem(key: str, value) -> str | None:
    """What is wrong with ``value`` for ``key`` (None when fine or ``key`` has no rule)."""
    rule = RULES.get(key)
    if rule is None or (value is None and rule.null):
        return None
    want = rule.check(object() if value is None else value)
    if want is None:
        return None if rule.cap is None or value is None else rule.cap.problem(key, value)
    if rule.null:
        want += " or null"
    if quoted_number(value) and rule.check(float(value)) is None:
        return (f"got the string '{value}' (quoted on the command line?); {key} must be {want}: "
                f"write {key}={value} without quotes")
    if isinstance(value, str) and hasattr(rule.check, "choices"):
        return f"unknown {key.rsplit('.', 1)[-1]} '{value}'; {key} must be {want}"
    return f"got {value!r}; {key} must be {want}"


def refusal(key: str, value) -> FlameReconError | None:
    """The error for ``value`` given as ``key`` through the Python API (an option class's
    field, a function's argument) under the same rule: :class:`ArgumentTypeError` for a value
    of a type the rule does not take (None where it is not allowed, a string for a number),
    :class:`ArgumentError` for one of the right type out of range; None when it is fine."""
    rule = RULES[key]
    wrong = problem(key, value)
    if wrong is None:
        return None
    if not of_type(value, rule.check):
        want = rule.check(object()) + (" or None" if rule.null else "")
        return ArgumentTypeError(f"{key}: got {describe(value)}; {key} must be {want}")
    return ArgumentError(f"{key}: {wrong}")


def check_fields(section: str, values: Mapping) -> None:
    """Refuse the first of ``values`` ({field: value} of the options class of ``section``,
    e.g. ``grid``; ``""`` for the top level) that breaks its rule ``section.field`` (see
    :func:`refusal`); fields without a rule pass."""
    for field, value in values.items():
        key = f"{section}.{field}" if section else field
        error = refusal(key, value) if key in RULES else None
        if error is not None:
            raise error


def check_section(section: str, options) -> None:
    """What every options dataclass does when made: its list fields become tuples (options
    made by hand and from a config compare equal), then every field is checked by the rule
    of ``section.field`` (:func:`check_fields`)."""
    values = {}
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if isinstance(value, (list, tuple)):
            value = as_tuples(value)
            object.__setattr__(options, f.name, value)
        values[f.name] = value
    check_fields(section, values)


def as_tuples(value):
    """Lists (nested too) as tuples."""
    return tuple(as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value


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


@dataclass(frozen=True)
class Need:
    """An option that does something only together with another: ``used(value)`` says the
    option was set to do something, ``met(flat options)`` whether what it needs is there
    (``needs``, in words, for the message). ``preset``: a scene preset may set it for when the
    other is turned on (ScalarFlow's ``uncertainty.scale``), so it is refused only where the
    command line gives it (:func:`check_needs`' ``given``)."""

    used: Callable[[object], bool]
    met: Callable[[Mapping], bool]
    needs: str
    preset: bool = False


_REFINEMENT = "a refinement (calibration.refine=pose or pose+intrinsics, or a calibration.file)"


def _refined(flat: Mapping) -> bool:
    """Cameras refined now, or read from a calibration file (which the other keys describe)."""
    return flat.get("calibration.refine", "none") != "none" or flat.get("calibration.file") is not None


def _has_candidates(flat: Mapping) -> bool:
    candidates = flat.get("select.candidates") or {}
    return bool(candidates.get(flat.get("solver.name")))


def _frames(flat: Mapping) -> bool:
    return flat.get("scene.frames") is not None


def _changed(default) -> Callable[[object], bool]:
    return lambda value: value != default


def _given(_value) -> bool:
    return True


def _rung_runs(flat: Mapping) -> bool:
    """A rung of ``ladder.rungs`` runs: its downscale is above the scene's (``scene.downscale``,
    1 where the scene has none)."""
    own = flat.get("scene.downscale") or 1
    return any(int(rung[0]) > int(own) for rung in flat.get("ladder.rungs") or ())


_UNCERTAINTY = "the confidence (uncertainty.enabled=true)"
_RUNG = ("a rung of the ladder that runs (ladder.rungs with a downscale above scene.downscale, e.g. "
         "scene.downscale=1 under ScalarFlow's [[4, 128], [2, 192]])")


#: options accepted alone but doing nothing without another: refused by name
#: (:func:`check_needs`) rather than ignored in silence. ``temporal.*`` against its defaults
#: in conf/train.yaml.
NEEDS: dict[str, Need] = {
    "select.auto": Need(bool, _has_candidates, "candidates for the run's solver in select.candidates "
                        "(select.candidates.<solver.name>: a non-empty list)"),
    # calibration.frames alone is not refused: a scene preset sets it (scalarflow: [30, 50, 70]), and
    # calibration.refine=none must turn the refinement off without the user emptying it too; nor are
    # ladder.iterations / final_iterations (the scalarflow preset sets them; ladder.rungs=[] turns it off)
    "calibration.gauge": Need(_changed("mean"), _refined, _REFINEMENT),
    "calibration.rig": Need(bool, _refined, _REFINEMENT),
    "calibration.score_before": Need(bool, _refined, _REFINEMENT),
    "calibration.offsets": Need(bool, lambda flat: flat.get("calibration.refine", "none") != "none"
                                and bool(flat.get("calibration.frames")),
                                "a capture calibration (calibration.refine=pose or pose+intrinsics with "
                                "calibration.frames)"),
    "grid.level_iters": Need(lambda v: v is not None, lambda flat: bool(flat.get("grid.levels")),
                             "coarse levels (grid.levels, e.g. [16, 32])"),
    **{f"solver.{key}": Need(_changed(default), lambda flat: (flat.get("solver.reweight_rounds") or 0) > 0,
                             "reweighting rounds (solver.reweight_rounds >= 1)")
       for key, default in {"reweight_eps": 0.1, "reweight": "tv"}.items()},
    **{f"temporal.{key}": Need(_changed(default), _frames, "frames solved jointly (scene.frames=[first,last])")
       for key, default in {"l2": 0.01, "tv": 0.0, "motion": "none", "max_shift": 3, "tol": 1.0e-5}.items()},
    # options a preset may set for when their switch is on: refused only where the command line gives them
    **{f"uncertainty.{key}": Need(_given, lambda flat: flat.get("uncertainty.enabled") is True, _UNCERTAINTY, True)
       for key in ("members", "shift_voxels", "scale", "iterations", "weight_factor")},
    **{f"ladder.{key}": Need(_given, _rung_runs, _RUNG, True) for key in ("iterations", "final_iterations")},
    **{f"photometry.{key}": Need(_given, lambda flat: flat.get("photometry.fit_gain") is True,
                                 "the gain fit (photometry.fit_gain=true)", True) for key in ("fit_offset", "rounds")},
    "debias.iterations": Need(_given, lambda flat: flat.get("debias.method") == "refit",
                              "the refit debias (debias.method=refit)", True),
    **{f"select.{key}": Need(_given, lambda flat: flat.get("select.auto") is True,
                             "the weight selection (select.auto=true)", True) for key in ("folds", "iterations")},
    "export.iso": Need(_given, lambda flat: bool(set(flat.get("export.formats") or ()) & {"ply", "obj", "mesh", "all"}),
                       "a mesh export (export=mesh, or export.formats with ply, obj or all)", True),
    "log.eval_share": Need(lambda v: v is not None, lambda flat: (flat.get("log.eval_every") or 0) > 0,
                           "held-out pictures during the solve (log.eval_every >= 1)", True),
    **{f"calibration.{key}": Need(_given, lambda flat: flat.get("calibration.refine", "none") != "none",
                                  "a camera fit (calibration.refine=pose or pose+intrinsics)", True)
       for key in ("rounds", "iterations", "band_px", "max_rays", "prior_rotation_deg", "prior_translation",
                   "prior_focal", "prior_principal_px", "fit_against", "resolution", "frames", "first_iterations",
                   "solve_iterations", "seed", "min_gain")},
}


def check_needs(flat: Mapping, error: type[FlameReconError] = ConfigError, given: Collection[str] | None = None) -> None:
    """Raise ``error`` for the first option of ``flat`` ({dotted key: value}) set to do something
    that needs another option which is not there (:data:`NEEDS`); an option a preset may set
    (``Need.preset``) only where it is among ``given``, the keys the command line gives (None:
    the Python API, where every such option is kept for a later call, e.g. ``fr.confidence``)."""
    for key, need in NEEDS.items():
        if need.preset and (given is None or key not in given):
            continue
        if key in flat and need.used(flat[key]) and not need.met(flat):
            way_out = f"drop {key} from the command line" if need.preset else f"leave {key} at its default"
            raise error(f"{key}: got {describe(flat[key])}, which does nothing without {need.needs}; "
                        f"set that too or {way_out}")




#: solvers whose ``max_iters`` may be null (LARS: 10 path steps per voxel).
NULL_MAX_ITERS = ("lars",)


def check_options(config: dict, given: Collection[str] | None = None) -> None:
    """Raise :class:`~flamerecon.errors.ConfigError` for the first option of ``config`` (a
    plain nested dict, ``hydra`` node excluded) that breaks its rule in :data:`RULES`, or that
    does nothing in the combination (:func:`check_needs`; ``given``: the keys the command line
    gives, :func:`given_keys`)."""
    flat = leaves({k: v for k, v in config.items() if k != "hydra"})
    for key, value in flat.items():
        wrong = problem(key, value)
        if wrong is not None:
            raise ConfigError(f"{key}: {wrong}")
    frames = flat.get("scene.frames")
    if frames is not None and frames[1] - frames[0] + 1 > MAX_JOINT_FRAMES:
        raise ConfigError(f"scene.frames: got {frames}, {frames[1] - frames[0] + 1} frames; a joint solve may hold at "
                          f"most {MAX_JOINT_FRAMES} (each frame holds its own operator): split the range")
    name = flat.get("solver.name")
    unbounded = "solver.max_iters" in flat and flat["solver.max_iters"] is None
    if unbounded and name not in NULL_MAX_ITERS:
        raise ConfigError(f"solver.max_iters: got None; solver {name} needs an integer >= 1 "
                          "(only lars takes null)")
    check_needs(flat, given=given)


@dataclass(frozen=True)
class Yield:
    """A rule by which a preset's option ``key`` overrides options the command line may give
    (``overridden(flat)``: their keys), in words ``what`` it does; ``off``: the value of ``key``
    that turns the rule off. Given one of those options and not ``key``, the rule is turned off
    and said (the option given wins); given both, ``conflict`` says whether the option given
    would then go unused (refused) or only holds elsewhere (kept)."""

    key: str
    off: object
    overridden: Callable[[Mapping], tuple[str, ...]]
    what: str
    conflict: bool


#: the options of a camera fit (what a calibration.file replaces)
_FIT = tuple(f"calibration.{key}" for key in (
    "refine", "frames", "rounds", "iterations", "band_px", "max_rays", "prior_rotation_deg", "prior_translation",
    "prior_focal", "prior_principal_px", "fit_against", "resolution", "first_iterations", "solve_iterations", "seed",
    "min_gain", "offsets"))


def _selected(flat: Mapping) -> tuple[str, ...]:
    """The solver options the weight selection chooses: ``solver.l1``, ``solver.l1_rel`` and
    every key of the run's solver's ``select.candidates``."""
    candidates = (flat.get("select.candidates") or {}).get(flat.get("solver.name")) or []
    return tuple(dict.fromkeys(["solver.l1", "solver.l1_rel",
                                *(f"solver.{k}" for c in candidates if isinstance(c, Mapping) for k in c)]))


#: the rules by which an option overrides another (:class:`Yield`, :func:`given_wins`); each is
#: said in the run's log where it holds
YIELDS = (
    Yield("ladder.final_iterations", None, lambda flat: ("solver.max_iters",),
          "sets the iterations of the run's own level once a ladder rung ran", False),
    Yield("ladder.iterations", None, lambda flat: ("solver.max_iters",), "sets the iterations of each ladder rung",
          False),
    Yield("select.auto", False, _selected, "chooses the solver's weights from select.candidates", True),
    Yield("holdout", None, lambda flat: ("scene.holdout",), "holds out its own views in place of the scene's", True),
    Yield("calibration.file", None, lambda flat: _FIT, "reads the cameras from the file in place of a camera fit",
          True),
)


def given_keys(overrides: Collection[str]) -> set[str]:
    """The dotted keys a command line's ``overrides`` set (``+key=``, ``++key=``, ``~key`` too;
    a group choice ``solver=tv`` gives ``solver``)."""
    keys = set()
    for override in overrides:
        key = str(override).split("=", 1)[0].lstrip("+~").strip()
        if key:
            keys.add(key)
    return keys


def given_wins(flat: Mapping, given: Collection[str]) -> dict[str, tuple[object, str]]:
    """{overriding key: (the value that turns its rule off, the option given it would override)}
    for every rule of :data:`YIELDS` that holds in ``flat`` ({dotted key: value}) over an option
    among ``given`` while its own key is not given: the values to set so that the option given
    wins. Both given where the option would go unused (``Yield.conflict``): a ConfigError."""
    out = {}
    for rule in YIELDS:
        hit = [k for k in rule.overridden(flat) if k in given]
        if not hit or flat.get(rule.key) is None or flat.get(rule.key) == rule.off:
            continue
        if rule.key in given:
            if rule.conflict:
                shown = str(flat[rule.key]).lower() if isinstance(flat[rule.key], bool) else flat[rule.key]
                raise ConfigError(f"{hit[0]}: given with {rule.key}={shown}, which {rule.what}, "
                                  f"so {hit[0]} would not be used; give one of them")
            continue
        out[rule.key] = (rule.off, hit[0])
    return out
