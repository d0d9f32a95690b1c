"""scripts/cross_validate.py: settings ranked by leave-one-view-out over the training views,
the excluded (test) view never fitted while ranking."""

from __future__ import annotations

import json
import sys

import pytest

from tests.helpers import REPO, TINY

sys.path.insert(0, str(REPO / "scripts"))
import cross_validate


@pytest.mark.slow
def test_cross_validation_never_fits_the_excluded_view_and_averages_its_folds(tmp_path, capsys):
    out = tmp_path / "cv"
    code = cross_validate.main([*TINY, "--exclude", "cam04", "--sweep", "solver.l1_rel=0,0.3",
                                "--average", "scene.frame=0,1", "--test", "--out", str(out)])
    assert code == 0
    record = json.loads((out / "cv.json").read_text())
    assert record["exclude"] == ["cam04"] and len(record["settings"]) == 2
    for i, setting in enumerate(record["settings"]):
        folds = []
        for part in ("00", "01"):
            loo = json.loads((out / f"{i:03d}" / part / "cv" / "loo.json").read_text())
            assert sorted(loo["views"]) == ["cam00", "cam01", "cam02", "cam03"]
            assert all("cam04" not in row["train"] and len(row["train"]) == 3
                       for row in loo["views"].values())
            folds.append(loo["mean"]["psnr"])
            test = json.loads((out / f"{i:03d}" / part / "test" / "loo.json").read_text())
            assert test["views"]["cam04"]["train"] == ["cam00", "cam01", "cam02", "cam03"]
        assert setting["cv_psnr"] == pytest.approx(sum(folds) / 2)
    # a heavy L1 weight predicts the held-out views worse than none, and ranks last
    psnr = {s["overrides"][-1]: s["cv_psnr"] for s in record["settings"]}
    assert psnr["solver.l1_rel=0"] > psnr["solver.l1_rel=0.3"]
    table = capsys.readouterr().out.split("CV PSNR  CV SSIM")[1]
    assert table.index("solver.l1_rel=0 ") < table.index("solver.l1_rel=0.3")


def test_a_malformed_sweep_is_refused_by_argparse():
    with pytest.raises(SystemExit):
        cross_validate.main(["--sweep", "solver.l1_rel"])


def test_report_frames_score_the_choice_and_never_enter_the_ranking(tmp_path, capsys):
    out = tmp_path / "cv"
    code = cross_validate.main([*TINY, "--exclude", "cam04", "--sweep", "solver.l1_rel=0.3,0",
                                "--average", "scene.frame=0", "--report", "scene.frame=2",
                                "--out", str(out)])
    assert code == 0
    record = json.loads((out / "cv.json").read_text())
    assert all(list(s["parts"]) == ["scene.frame=0"] for s in record["settings"])
    best = max(record["settings"], key=lambda s: s["cv_psnr"])["overrides"]
    reported = [r["overrides"] for r in record["report"]]
    assert best in reported and record["settings"][0]["overrides"] in reported
    assert all(list(r["parts"]) == ["scene.frame=2"] for r in record["report"])
    assert "(chose nothing)" in capsys.readouterr().out
