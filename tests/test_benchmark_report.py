"""scripts/benchmark.py's report: a peer's budget is swept by cold runs, so its time to a gap is
only known to lie between its last run above the gap and its first at or below; our lead over
the fastest peer is printed at both ends of that bracket."""

from __future__ import annotations

import sys

import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "scripts"))
import benchmark

F_REF = 10.0


def trace(*gaps_at: tuple[float, float]) -> list[tuple[float, float]]:
    """(seconds, objective) pairs from (seconds, relative gap) pairs."""
    return [(seconds, F_REF * (1 + gap)) for seconds, gap in gaps_at]


def test_a_sweep_brackets_the_time_to_a_gap_between_the_runs_either_side_of_it():
    sweep = trace((1.0, 1e-2), (2.0, 3e-4), (4.0, 5e-5), (8.0, 1e-7))
    assert benchmark.swept_bracket(sweep, F_REF, 1e-4) == [2.0, 4.0]
    assert benchmark.seconds_to(sweep, F_REF, 1e-4) == 4.0  # the bracket's upper end
    assert benchmark.swept_bracket(trace((3.0, 1e-5)), F_REF, 1e-4) == [3.0, 3.0]  # the first run gets there
    assert benchmark.swept_bracket(trace((1.0, 1e-2), (2.0, 2e-4)), F_REF, 1e-4) is None


def test_our_lead_is_given_at_both_ends_of_the_fastest_peers_bracket():
    def method(seconds, bracket=None):
        return {"seconds_to_1e-4": seconds, "bracket_1e-4": bracket}

    methods = {"fista": method(5.0), "pqn": method(2.0), "newton_cg": method(None),
               "sklearn_lasso": method(40.0, [20.0, 40.0]), "skglm_lasso": method(90.0, [50.0, 90.0]),
               "celer_lasso": method(None)}
    won = benchmark.lead(methods)
    assert (won["ours"], won["seconds"], won["peer"], won["peer_bracket"]) == ("pqn", 2.0, "sklearn_lasso", [20.0, 40.0])
    assert won["ratio"] == pytest.approx([10.0, 20.0])
    assert benchmark.lead({"pqn": method(None), "sklearn_lasso": method(40.0, [20.0, 40.0])}) is None
    ours_swept = {"pqn": method(2.0, [1.0, 2.0]), "pqn" + benchmark.ONE: method(3.0, [2.5, 3.0]),
                  "sklearn_lasso": method(40.0, [20.0, 40.0])}
    assert benchmark.lead(ours_swept)["peer"] == "sklearn_lasso"  # ours, on any cores, are never the peer


def test_the_lead_on_the_peers_cores_is_ours_on_one_thread_and_both_are_printed(capsys):
    def method(seconds, bracket=None):
        return {"seconds_to_1e-4": seconds, "seconds_to_1e-6": None, "bracket_1e-4": bracket, "best_rel_gap": 1e-7,
                "iterations": 1}

    methods = {"pqn": method(2.0), "pqn" + benchmark.ONE: method(4.0),
               "sklearn_lasso": method(40.0, [20.0, 40.0])}
    same = benchmark.lead(methods, ("pqn" + benchmark.ONE,))
    assert same["ours"] == "pqn (1 thread)" and same["ratio"] == pytest.approx([5.0, 10.0])
    report = {"grid": [8, 8, 8], "l1_rel": 1e-3, "reference_objective": F_REF, "reference_certified_rel_gap": 1e-9,
              "load_average": (1.5, 1.0, 0.5), "methods": methods, "skipped": {"celer_lasso": "celer not installed"},
              "threads": 2, "lead_1e-4": same, "lead_1e-4_threads": benchmark.lead(methods)}
    benchmark.print_table(report)
    out = capsys.readouterr().out
    assert "to 1e-4 on the peers' cores: pqn (1 thread) 4.00 s, the fastest peer sklearn_lasso between 20.00 and " \
           "40.00 s: 5.0x to 10.0x sooner (load average 1.50)" in out
    assert "to 1e-4 ours on 2 threads: pqn 2.00 s" in out and "10.0x to 20.0x sooner" in out
    assert "celer_lasso           skipped: celer not installed" in out
