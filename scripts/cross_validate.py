"""Choose settings by leave-one-view-out cross-validation over the training views.

    python scripts/cross_validate.py scene=scalarflow --exclude train02 \\
        --sweep solver.smooth=0.1,0.3,1 --sweep solver.l1_rel=0.01,0.05 \\
        --average scene.frame=20,40,59 [--report scene.frame=10,66] [--test] [--out DIR]

Every combination of the ``--sweep`` values is scored by leave-one-view-out over the views not
in ``--exclude`` (those are never fitted), averaged over folds and over the ``--average``
values (e.g. frames), and ranked by mean held-out PSNR. With ``--test`` each setting is also
fitted on every view but the excluded ones, and the excluded views are scored: that column is
printed for reference and never used for the ranking. ``--report`` holds out frames as well
as views: the settings are ranked on the ``--average`` frames only, and the best setting and
the first one (the baseline to beat) are then scored the same way on the ``--report`` values,
which chose nothing. Writes DIR/cv.json.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import itertools
import math
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.progress import Progress
from flamerecon.resources import config_dir
from flamerecon.run.cli import output_folder, run_script, script_parser
from flamerecon.run.leave_one_out import leave_one_out
from flamerecon.scenes import load_scene


def key_values(text: str) -> tuple[str, list[str]]:
    """'key=a,b,c' -> ('key', ['a', 'b', 'c'])."""
    key, sep, values = text.partition("=")
    if not sep or not key or not values:
        raise argparse.ArgumentTypeError(f"expected key=v1,v2,..., got '{text}'")
    return key, values.split(",")


def mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def score_setting(overrides: list[str], averages: list[list[str]], exclude: list[str],
                  test: bool, out: Path) -> dict:
    """Cross-validated (and with ``test``, excluded-view) PSNR/SSIM of one setting, per
    ``--average`` combination and their mean."""
    parts = {}
    for extra in averages or [[]]:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name="train", overrides=[*overrides, *extra])
        label = " ".join(extra) or "all"
        folder = out / f"{len(parts):02d}"
        scene = load_scene(cfg.scene)  # once for the folds and the test fit
        cv = leave_one_out(cfg, folder / "cv", exclude=exclude, scene=scene)
        part = {"cv_psnr": cv["mean"]["psnr"], "cv_ssim": cv["mean"]["ssim"],
                "folds": {v: r["psnr"] for v, r in cv["views"].items()}}
        if test and exclude:
            held = leave_one_out(cfg, folder / "test", views=exclude, exclude=exclude, scene=scene)
            part.update(test_psnr=held["mean"]["psnr"], test_ssim=held["mean"]["ssim"])
        parts[label] = part
    keys = [k for k in ("cv_psnr", "cv_ssim", "test_psnr", "test_ssim") if k in next(iter(parts.values()))]
    return {"overrides": overrides, "parts": parts, **{k: mean([p[k] for p in parts.values()]) for k in keys}}


def table(rows: list[dict], sweep_keys: list[str]) -> str:
    ranked = sorted(rows, key=lambda r: -r["cv_psnr"])
    test = "test_psnr" in rows[0]
    head = f"  {'setting':<48} {'CV PSNR':>8} {'CV SSIM':>8}" + (f" {'test PSNR':>10} {'test SSIM':>10}" if test else "")
    lines = [head, "  " + "-" * (len(head) - 2)]
    for r in ranked:
        setting = " ".join(o for o in r["overrides"] if o.split("=")[0] in sweep_keys) or "(base)"
        line = f"  {setting:<48} {r['cv_psnr']:8.2f} {r['cv_ssim']:8.4f}"
        if test:
            line += f" {r['test_psnr']:10.2f} {r['test_ssim']:10.4f}"
        lines.append(line)
    if test:
        lines.append("  (ranked by CV PSNR; the test columns are for reference, never used to rank)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides shared by every setting")
    parser.add_argument("--sweep", type=key_values, action="append", default=[],
                        help="key=v1,v2,...: values to compare (repeat for a grid)")
    parser.add_argument("--average", type=key_values, action="append", default=[],
                        help="key=v1,v2,...: values every setting is averaged over (e.g. frames)")
    parser.add_argument("--report", type=key_values, action="append", default=[],
                        help="key=v1,v2,...: values (e.g. frames) scored after the choice, never used for it")
    parser.add_argument("--exclude", default="", help="comma-separated views never fitted")
    parser.add_argument("--test", action="store_true", help="also score the excluded views")
    parser.add_argument("--out", type=output_folder, help="output folder (default outputs/cv/<date>/<time>)",
                        default=str(Path("outputs/cv") / time.strftime("%Y-%m-%d") / time.strftime("%H-%M-%S")))
    args = parser.parse_args(argv)
    out = args.out
    exclude = [v for v in args.exclude.split(",") if v]
    sweep_keys = [k for k, _ in args.sweep]
    settings = [[f"{k}={v}" for k, v in zip(sweep_keys, combo)]
                for combo in itertools.product(*[vals for _, vals in args.sweep])]
    averages, reports = combos(args.average), combos(args.report)
    rows = []

    def run() -> None:
        steps = Progress("cross-validation", len(settings), unit="setting")
        for i, setting in enumerate(settings):
            row = score_setting([*args.overrides, *setting], averages, exclude, args.test, out / f"{i:03d}")
            rows.append(row)
            print(f"  {' '.join(setting) or '(base)'}: CV PSNR {row['cv_psnr']:.2f} dB"
                  + (f", test {row['test_psnr']:.2f} dB" if "test_psnr" in row else ""), flush=True)
            write_json_atomic(out / "cv.json", {"exclude": exclude, "settings": rows})
            steps.step(" ".join(setting) or "(base)")
        print(f"cross-validation ({len(rows)} settings): {out / 'cv.json'}\n{table(rows, sweep_keys)}")
        if reports:
            best = max(range(len(rows)), key=lambda i: rows[i]["cv_psnr"])
            held = [score_setting([*args.overrides, *settings[i]], reports, exclude, args.test,
                                  out / f"report{i:03d}") for i in sorted({0, best})]
            write_json_atomic(out / "cv.json", {"exclude": exclude, "settings": rows, "report": held})
            print(f"on {' '.join(' '.join(r) for r in reports)} (chose nothing):\n{table(held, sweep_keys)}")

    return run_script(run, args.debug)


def combos(pairs: list[tuple[str, list[str]]]) -> list[list[str]]:
    """Every combination of ``key=v1,v2`` values as override lists (empty without pairs)."""
    if not pairs:
        return []
    keys = [k for k, _ in pairs]
    return [[f"{k}={v}" for k, v in zip(keys, combo)] for combo in itertools.product(*[v for _, v in pairs])]


if __name__ == "__main__":
    sys.exit(main())
