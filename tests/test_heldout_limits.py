"""scripts/heldout_limits.py: a held-out view's score beside its oracles (own exposure, a
blurred render, its pose refitted to its own image)."""

from __future__ import annotations

import re
import sys

import pytest

from tests.helpers import REPO, TINY

sys.path.insert(0, str(REPO / "scripts"))
import heldout_limits


@pytest.mark.slow
def test_the_oracles_are_printed_per_held_out_view_and_the_own_gain_never_loses(capsys):
    assert heldout_limits.main(["scene=synthetic", *TINY, "--frames", "0"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.strip().startswith("0 cam04"))
    run, gained, blurred, posed = (float(v) for v in re.findall(r"-?\d+\.\d+", row)[:4])
    assert gained >= run - 1e-6  # the least-squares gain minimises the squared error
    assert min(run, gained, blurred, posed) > 10


def test_frames_must_be_numbers():
    with pytest.raises(SystemExit):
        heldout_limits.main(["--frames", "a,b"])
