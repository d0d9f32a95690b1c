"""Every option that sizes a resource has an upper bound tied to what the machine has (or to
what the method can use), refused by name before any work (issue 33): ``threads=10**6`` once
started threads until other processes could not fork. One table over the bounded options,
each just above its bound (refused) and at it (taken), through the command line's rules and
the Python API's options alike; then the bounds checked where the images or the phantom are
known (silhouette kernels, the synthetic scene's memory)."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import flamerecon as fr
from flamerecon.device import set_threads
from flamerecon.errors import ArgumentError, ConfigError, MemoryBudgetError
from flamerecon.fit import option_rules
from flamerecon.fit.option_rules import (
    MAX_ITERATIONS,
    MAX_JOINT_FRAMES,
    RULES,
    check_options,
    problem,
)
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.machine import cores, total_bytes
from flamerecon.run.runner import run_task
from tests.helpers import tiny_cfg

CAPPED = sorted(key for key, rule in RULES.items() if rule.cap is not None)

# (key, the most it may be, words of the reason in the message)
BOUNDS = {
    "threads": (cores(), "this machine's cores"),
    "solver.max_iters": (MAX_ITERATIONS, "solver.max_seconds"),
    "grid.level_iters": (MAX_ITERATIONS, "runs for days"),
    "ladder.iterations": (MAX_ITERATIONS, "runs for days"),
    "ladder.final_iterations": (MAX_ITERATIONS, "runs for days"),
    "select.iterations": (MAX_ITERATIONS, "runs for days"),
    "calibration.iterations": (MAX_ITERATIONS, "runs for days"),
    "calibration.first_iterations": (MAX_ITERATIONS, "runs for days"),
    "calibration.solve_iterations": (MAX_ITERATIONS, "runs for days"),
    "debias.iterations": (MAX_ITERATIONS, "runs for days"),
    "uncertainty.iterations": (MAX_ITERATIONS, "runs for days"),
    "motion.iters": (MAX_ITERATIONS, "runs for days"),
    "solver.cg_iters": (MAX_ITERATIONS, "runs for days"),
    "solver.newton_iters": (MAX_ITERATIONS, "runs for days"),
    "solver.warm_iters": (MAX_ITERATIONS, "runs for days"),
    "calibration.rounds": (option_rules.MAX_ROUNDS, "each round is a whole solve"),
    "photometry.rounds": (option_rules.MAX_ROUNDS, "each round is a whole solve"),
    "solver.reweight_rounds": (option_rules.MAX_ROUNDS, "each round is a whole solve"),
    "solver.memory": (option_rules.MAX_MEMORY_PAIRS, "two copies of the density"),
    "temporal.max_shift": (option_rules.MAX_SHIFT, "pads every volume"),
    "motion.max_shift": (option_rules.MAX_SHIFT, "pads every volume"),
    "motion.window": (option_rules.MAX_WINDOW, "loaded and projected"),
    "motion.control": (option_rules.MAX_CONTROL, "control cells"),
    "flow.control": (option_rules.MAX_CONTROL, "control cells"),
    "simulation.control": (option_rules.MAX_CONTROL, "control cells"),
    "flow.iters": (MAX_ITERATIONS, "runs for days"),
    "flow.warm_iters": (MAX_ITERATIONS, "runs for days"),
    "simulation.iters": (MAX_ITERATIONS, "runs for days"),
    "simulation.window": (option_rules.MAX_WINDOW, "keeps its operator"),
    "flow.margin": (option_rules.MAX_SHIFT, "cells around the smoke"),
    "simulation.margin": (option_rules.MAX_SHIFT, "cells kept around the smoke"),
    "simulation.pad": (option_rules.MAX_SHIFT, "still cells"),
    "advect.steps": (option_rules.MAX_STEPS, "each a pass over the grid"),
    "projector.max_memory_gb": (round(total_bytes() / 2**30, 1), "the memory this machine has"),
    "solver.max_voxels": (int((total_bytes() / 8) ** 0.5), "Gram matrix"),
}


def test_every_bounded_option_is_in_the_table():
    assert sorted(BOUNDS) == CAPPED


@pytest.mark.parametrize("key", sorted(BOUNDS))
def test_a_bound_refuses_above_and_takes_at_it(key):
    most, why = BOUNDS[key]
    above = most + 0.5 if isinstance(most, float) else most + 1
    message = problem(key, above)
    assert message is not None and f"{key} must be at most" in message and why in message, message
    assert problem(key, most) is None
    if key == "grid.level_iters":  # a list: every level's budget is bounded
        assert "must be at most" in problem(key, [10, above]) and problem(key, [10, most]) is None


@settings(max_examples=60, deadline=None)
@given(key=st.sampled_from(sorted(BOUNDS)), excess=st.integers(1, 10**12))
def test_any_value_past_a_bound_is_refused_naming_the_option(key, excess):
    most, _ = BOUNDS[key]
    with pytest.raises(ConfigError, match=rf"^{key}: got .*; {key} must be at most"):
        check_options(_nested(key, most + excess))


def _nested(key: str, value) -> dict:
    *parents, leaf = key.split(".")
    node: dict = {leaf: value}
    for parent in reversed(parents):
        node = {parent: node}
    return node


# the Python API: the options' own checks, and the functions that set a resource
API_CASES = {
    "ReconstructionOptions(threads=10**6)": (lambda: fr.ReconstructionOptions(threads=10**6), ArgumentError,
                                             r"threads: got 1000000; threads must be at most \d+ \(this machine's"),
    "SolverOptions(max_iters=10**9)": (lambda: fr.SolverOptions("fista", params={"max_iters": 10**9}), ArgumentError,
                                       r"solver.max_iters: got 1000000000; .*at most 10_000_000"),
    "ProjectorOptions(max_memory_gb=1e9)": (lambda: fr.ProjectorOptions(max_memory_gb=1e9), ArgumentError,
                                            r"projector.max_memory_gb: .*the memory this machine has"),
    "PhotometryOptions(rounds=10**6)": (lambda: fr.PhotometryOptions(rounds=10**6), ArgumentError,
                                        r"photometry.rounds: .*at most 1_000"),
    "make_solver('pqn', memory=10**9)": (lambda: fr.make_solver("pqn", memory=10**9), ArgumentError,
                                         r"solver.memory: .*two copies of the density"),
    "set_threads(cores + 1)": (lambda: set_threads(cores() + 1), ArgumentError, r"threads: got \d+; .*at most"),
    "scripts' --threads": (lambda: set_threads(10**6, "--threads"), ArgumentError, r"^--threads: got 1000000"),
    "joint frames past the bound": (
        lambda: check_options({"scene": {"frames": [0, MAX_JOINT_FRAMES]}}), ConfigError,
        rf"scene.frames: got \[0, {MAX_JOINT_FRAMES}\], {MAX_JOINT_FRAMES + 1} frames; .*split the range"),
    "silhouette kernel wider than the image": (
        lambda: silhouettes(torch.rand(2, 3, 18, 24), dilate_px=10**6), ConfigError,
        r"silhouette.dilate_px: got 1000000; for 24x18 images it must be at most 24 px"),
    "silhouette blur wider than the image": (
        lambda: silhouettes(torch.rand(1, 3, 18, 24), blur_px=25.0), ConfigError, r"silhouette.blur_px: got 25.0"),
    "speck size of the box estimate": (
        lambda: silhouettes(torch.rand(1, 3, 18, 24), speck_px=25, field="scene.silhouette"), ConfigError,
        r"^scene.silhouette.speck_px: got 25"),
}


@pytest.mark.parametrize("case", list(API_CASES))
def test_the_python_api_refuses_by_name(case):
    make, kind, pattern = API_CASES[case]
    with pytest.raises(kind, match=pattern):
        make()


def test_at_the_bound_the_api_takes_it():
    assert fr.ReconstructionOptions(threads=cores()).threads == cores()
    assert silhouettes(torch.rand(1, 3, 18, 24), dilate_px=24, blur_px=24.0).shape == (1, 18, 24)
    check_options({"scene": {"frames": [0, MAX_JOINT_FRAMES - 1]}})


SCENE = {"name": "synthetic", "n_cameras": 5, "width": 48, "height": 36, "phantom_resolution": 32}


@pytest.mark.parametrize("overrides, field", [
    (["phantom_resolution=100000"], r"scene.phantom_resolution: a 66667x100000x66667 phantom needs about"),
    (["width=100000000"], r"scene.n_cameras x scene.width x scene.height: 5 images of 100000000x36 px"),
    (["n_cameras=100000000"], r"scene.n_cameras x scene.width x scene.height: 100000000 images"),
])
def test_a_synthetic_scene_too_big_for_memory_is_refused_before_it_is_made(overrides, field):
    with pytest.raises(MemoryBudgetError, match=field + r".* is free; use "):
        fr.load_scene({**SCENE, **{k: int(v) for k, v in (o.split("=") for o in overrides)}})


def test_the_command_line_refuses_threads_past_the_cores(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        run_task(tiny_cfg("threads=1000000"), tmp_path / "run")
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("flamerecon: error: threads: got 1000000; threads must be at most") and "Traceback" not in err


def test_the_camera_fits_own_grid_is_refused_naming_its_option(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        run_task(tiny_cfg("calibration.refine=pose", "calibration.resolution=100000"), tmp_path / "run")
    assert stop.value.code == 2
    assert capsys.readouterr().err.startswith("flamerecon: error: calibration.resolution: a 66667x100000x66667 grid")
