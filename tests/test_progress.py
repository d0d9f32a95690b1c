"""Every wait over a few seconds says how far it is: a line per step with the elapsed and the
expected remaining time (:mod:`flamerecon.progress`), silenced by ``FLAMERECON_PROGRESS=0``
(which tests/conftest.py sets for the suite)."""

from __future__ import annotations

import logging
import re

import pytest

from flamerecon.progress import ENV, Progress, duration


@pytest.fixture
def lines(monkeypatch, caplog):
    """The progress lines logged in the test, with progress turned on."""
    monkeypatch.setenv(ENV, "1")
    caplog.set_level(logging.INFO, logger="flamerecon.progress")
    return lambda: [r.getMessage() for r in caplog.records if r.name == "flamerecon.progress"]


def test_a_line_per_step_with_elapsed_and_remaining_time(lines, monkeypatch):
    clock = iter([0.0, 10.0, 20.0, 30.0])
    monkeypatch.setattr("flamerecon.progress.time.perf_counter", lambda: next(clock))
    p = Progress("leave-one-out", 3, unit="fold")
    p.step("cam00 held out")
    p.step("cam01 held out")
    p.step("cam02 held out")
    assert lines() == [
        "leave-one-out: 3 folds, started",
        "leave-one-out: fold 1/3 (cam00 held out); 10 s elapsed, about 20 s left",
        "leave-one-out: fold 2/3 (cam01 held out); 20 s elapsed, about 10 s left",
        "leave-one-out: fold 3/3 (cam02 held out); 30 s elapsed, done",
    ]


def test_updates_are_throttled_but_the_last_is_said(lines, monkeypatch):
    clock = iter([0.0, *[float(t) for t in range(1, 101)]])
    monkeypatch.setattr("flamerecon.progress.time.perf_counter", lambda: next(clock))
    p = Progress("reference solve", 100, unit="iteration", every=10.0)
    for it in range(1, 101):
        p.update(it)
    said = lines()[1:]
    assert len(said) == 10 and said[-1].startswith("reference solve: iteration 100/100;")


@pytest.mark.parametrize(("times", "expected"), [
    ([0.0, 1.0, 2.0, 3.0], []),  # quick: not a word, not even at the end
    ([0.0, 2.0, 6.0, 8.0, 17.0], ["assembling: ray 20/40; 6 s elapsed, about 6 s left",
                                  "assembling: ray 40/40; 17 s elapsed, done"]),
])
def test_a_wait_that_may_be_quick_speaks_only_once_it_is_long(lines, monkeypatch, times, expected):
    clock = iter(times)
    monkeypatch.setattr("flamerecon.progress.time.perf_counter", lambda: next(clock))
    p = Progress("assembling", 40, "ray", every=10.0, after=5.0)
    for done in (10, 20, 30, 40)[:len(times) - 1]:
        p.update(done)
    assert lines() == expected


def test_silenced_by_the_environment_variable(lines, monkeypatch):
    monkeypatch.setenv(ENV, "0")
    Progress("camera fit", 2).step()
    assert lines() == []


def test_durations_read_as_a_person_says_them():
    assert [duration(s) for s in (8.4, 200, 3900)] == ["8 s", "3 min 20 s", "1 h 05 min"]


def test_the_camera_fit_says_each_round(lines, small_scene):
    """The camera fit (calibration.refine) logs its first density and every round (run to its
    rounds: exact cameras, which it would otherwise find nothing to correct in and stop)."""
    import torch

    from flamerecon.fit.options import ReconstructionOptions
    from flamerecon.fit.reconstruct import calibrated_scene

    options = ReconstructionOptions.from_dict({
        "grid": {"resolution": 12}, "solver": {"name": "fista", "max_iters": 5},
        "calibration": {"refine": "pose", "rounds": 2, "iterations": 1, "max_rays": 200, "min_gain": 0.0},
    })
    calibrated_scene(small_scene, options, torch.device("cpu"))
    said = [s for s in lines() if s.startswith("camera fit")]
    assert said[0] == "camera fit: 3 steps, started"
    assert [re.sub(r";.*", "", s) for s in said[1:]] == [
        "camera fit: step 1/3 (the density of 1 frame(s) with the capture's cameras)",
        "camera fit: step 2/3 (round 1: cameras fitted)", "camera fit: step 3/3 (round 2: cameras fitted)"]
