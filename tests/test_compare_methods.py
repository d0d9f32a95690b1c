"""scripts/compare_methods.py: methods side by side per frame, each a train.py run with its own
overrides on the same loaded frame, with the leave-one-view-out mean on request."""

from __future__ import annotations

import json
import sys

import pytest

from tests.helpers import REPO, TINY

sys.path.insert(0, str(REPO / "scripts"))
import compare_methods


@pytest.mark.slow
def test_each_method_is_scored_on_each_frame_and_a_heavy_penalty_predicts_worse(tmp_path, capsys):
    out = tmp_path / "compare.json"
    code = compare_methods.main(["scene=synthetic", *TINY, "--frames", "0,1", "--loo", "--out", str(out),
                                 "--method", "plain=", "--method", "heavy=solver.l1_rel=0.5"])
    assert code == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["frame"], r["method"]) for r in rows] == [(0, "plain"), (0, "heavy"), (1, "plain"), (1, "heavy")]
    for r in rows:
        assert r["heldout"] > r["black"] and set(r["loo_views"]) == {f"cam{i:02d}" for i in range(5)}
        assert r["loo"] == pytest.approx(sum(r["loo_views"].values()) / 5)
    for frame in (0, 1):
        plain, heavy = (r for r in rows if r["frame"] == frame)
        assert plain["heldout"] > heavy["heldout"] and plain["loo"] > heavy["loo"]
    printed = capsys.readouterr().out
    assert " mean plain " in printed and " mean heavy " in printed


def test_a_method_without_a_name_is_refused_by_argparse():
    with pytest.raises(SystemExit):
        compare_methods.main(["--frames", "0", "--method", "=solver.l1_rel=0"])


def test_the_figure_shows_the_capture_and_each_method_with_its_detail_band(tmp_path):
    """--figure: one PNG per frame and held-out view, the capture and every method in a row
    (the methods' titles carry their scores), their detail bands in a row below; a blurred
    render's band is flatter than the capture's."""
    import cv2
    import numpy as np

    from flamerecon.outputs.figures import TITLE_PX

    code = compare_methods.main(["scene=synthetic", *TINY, "--frames", "0", "--figure", str(tmp_path / "fig"),
                                 "--method", "plain=", "--method", "blurred=solver.l1_rel=0.5"])
    assert code == 0
    files = sorted(p.name for p in (tmp_path / "fig").iterdir())
    assert files == ["heldout-0-cam04.png"]  # the tiny scene holds out cam04
    figure = cv2.imread(str(tmp_path / "fig" / files[0]))
    H = figure.shape[0] // 2 - TITLE_PX
    W = figure.shape[1] // 3
    assert figure.shape[1] == 3 * W and figure.shape[0] == 2 * (TITLE_PX + H)
    bands = [figure[2 * TITLE_PX + H:, k * W:(k + 1) * W].astype(float) for k in range(3)]
    spread = [float(np.abs(b - 127.5).mean()) for b in bands]
    assert spread[2] < spread[0]  # the heavily penalised render keeps less of the capture's detail


def test_a_method_that_changes_the_scene_gets_its_own_scene(tmp_path):
    """scene.* in one method's overrides loads that scene (it was the first method's scene for
    all: scene.downscale=2 in a method compared the 1/4-resolution images)."""
    out = tmp_path / "compare.json"
    code = compare_methods.main(["scene=synthetic", *TINY, "solver.max_iters=5", "--frames", "0", "--out", str(out),
                                 "--method", "plain=", "--method", "half=scene.downscale=2"])
    assert code == 0
    plain, half = json.loads(out.read_text())["rows"]
    assert plain["black"] != pytest.approx(half["black"], abs=1e-6)  # other captured images
