"""Leave-one-view-out: reconstruct once per camera, holding that camera out, and score it.

    python scripts/leave_one_out.py [--views a,b] [--exclude v] [--rig] [--out DIR] [train.py overrides ...]

The overrides are train.py's (e.g. scene=scalarflow scene.frame=40 solver.smooth=0.1). Prints
a table (view, PSNR, SSIM, black-image PSNR, and both inside the silhouette union) with the
mean, and writes DIR/loo.json and DIR/renders/. ``--exclude`` keeps views out of every fit
(e.g. ``--exclude train02`` to choose settings by cross-validation without the test view).
The protocol is strict (a held-out camera as the calibration file gives it); ``--rig`` scores
the rig-calibrated one instead (``calibration.rig=true``: every camera refined on
``calibration.frames``, which must not include the frame scored).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from flamerecon.resources import config_dir
from flamerecon.run.cli import output_folder, run_script, script_parser
from flamerecon.run.leave_one_out import leave_one_out, loo_table


def names(value: str | None) -> list[str]:
    return [v for v in (value or "").split(",") if v]


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides, key=value")
    parser.add_argument("--views", help="comma-separated views to hold out in turn (default: all)")
    parser.add_argument("--exclude", help="comma-separated views left out of every fit")
    parser.add_argument("--rig", action="store_true",
                        help="the rig-calibrated protocol (calibration.rig=true) instead of the strict one")
    parser.add_argument("--out", type=output_folder, help="output folder (default outputs/loo/<date>/<time>)",
                        default=str(Path("outputs/loo") / time.strftime("%Y-%m-%d") / time.strftime("%H-%M-%S")))
    args = parser.parse_args(argv)
    out = args.out

    def run() -> None:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name="train", overrides=[*args.overrides, *(["calibration.rig=true"] if args.rig else [])])
        record = leave_one_out(
            cfg, out, names(args.views), names(args.exclude),
            progress=lambda name, r: print(f"  {name}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}, "
                                           f"detail {r['detail']:.3f}, "
                                           f"{r['iterations']} iterations, {r['seconds']:.1f} s", flush=True),
        )
        print(f"leave-one-view-out, {cfg.scene.name}: {out / 'loo.json'}\n{loo_table(record)}")

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
