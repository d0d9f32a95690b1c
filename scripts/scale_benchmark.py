"""The resolution ladder of a capture, measured: one `python train.py` run per rung (its own
process, as a user runs it), each timed (wall) with its peak resident memory (the run's own
metrics.json `memory`, the kernel's ru_maxrss: what `/usr/bin/time -v` prints), then its density
scored the same way for every rung: the held-out view
rendered at one resolution (--score-downscale, default 2: half resolution), full frame, and on
ScalarFlow also HyFluid's crop (flamerecon/evaluate/protocols.py).

    python scripts/scale_benchmark.py [--frame 59] [--rungs 4:128 2:192 1:256] [--out FILE.json] \
        [--keep DIR] [--scene scalarflow] [--score-downscale 2] [train.py overrides ...]

Each run is `python train.py scene=SCENE scene.frame=F scene.downscale=D grid.resolution=G`
plus the overrides: the preset's own ladder, iterations and calibration (the capture's
calibration file is read when an earlier run wrote it; the first run of a new capture fits it,
and its time is then in that rung's wall time). The runs go into --keep DIR (default: a
temporary folder, removed at the end).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import os
import sys
import tempfile
from pathlib import Path

from flamerecon.evaluate.protocols import PROTOCOLS, Protocol, protocol_scores
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.run.cli import at_least, output_file, run_script, script_parser, timed_child
from flamerecon.run.folder import load_run

REPO = Path(__file__).resolve().parents[1]


def rung(text: str) -> tuple[int, int]:
    """argparse type: 'D:G' -> (downscale D >= 1, grid resolution G >= 8)."""
    import argparse

    try:
        d, g = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"got '{text}'; give DOWNSCALE:GRID, e.g. 2:192") from None
    if d < 1 or g < 8:
        raise argparse.ArgumentTypeError(f"got '{text}'; the downscale must be >= 1 and the grid >= 8 cells")
    return d, g


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frame", type=at_least(0), default=59, help="the frame (default 59)")
    parser.add_argument("--rungs", type=rung, nargs="+", default=[(4, 128), (2, 192), (1, 256)],
                        metavar="D:G", help="downscale:grid of each run (default: 4:128 2:192 1:256)")
    parser.add_argument("--out", type=output_file, default=None, metavar="FILE.json", help="also write the table as JSON")
    parser.add_argument("--keep", default=None, metavar="DIR", help="keep the run folders in DIR")
    parser.add_argument("--scene", default="scalarflow", help="the scene preset (default: scalarflow)")
    parser.add_argument("--score-downscale", type=at_least(1), default=2,
                        help="the resolution every run is scored at (default 2: half)")
    parser.add_argument("overrides", nargs="*", help="more train.py overrides")
    args = parser.parse_args(argv)

    def run() -> int:
        folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="flamerecon-scale-"))
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs at the start; frame {args.frame}",
              flush=True)
        print(f"held-out view scored at 1/{args.score_downscale} resolution; crop: HyFluid's (ScalarFlow only)")
        print(f"{'downscale':>9} {'grid':>5} {'wall s':>7} {'peak GiB':>9} {'held dB':>8} {'detail':>7} "
              f"{'crop dB':>8} {'crop SSIM':>9} {'load':>5}", flush=True)
        table = []
        for downscale, grid in args.rungs:
            run_dir = folder / f"ds{downscale}_grid{grid}"
            command = [sys.executable, str(REPO / "train.py"), f"scene={args.scene}", f"scene.frame={args.frame}",
                       f"scene.downscale={downscale}", f"grid.resolution={grid}", *args.overrides,
                       f"hydra.run.dir={run_dir}"]
            wall = timed_child(command, f"train.py at scene.downscale={downscale}, grid.resolution={grid}")
            done = load_run(run_dir)
            peak = done.metrics["memory"]["resident"]
            train = tuple(done.scene.views[v] for v in done.train)
            common = Protocol("scored", done.scene.views[done.holdout[0]], args.score_downscale, None, None, train)
            half = protocol_scores(common, done.scene_options, done.scene, done.train, done.density, done.grid)
            hyfluid = PROTOCOLS["hyfluid"]
            nan = {"psnr": float("nan"), "ssim": float("nan"), "detail": float("nan")}
            crop = (protocol_scores(hyfluid, done.scene_options, done.scene, done.train, done.density, done.grid)
                    if sorted(train) == sorted(hyfluid.train) else nan)
            row = {"downscale": downscale, "grid": grid, "wall_seconds": wall, "peak_gib": peak,
                   "half_psnr": half["psnr"], "half_detail": half["detail"], "crop_psnr": crop["psnr"],
                   "crop_ssim": crop["ssim"], "crop_detail": crop["detail"],
                   "timing": done.metrics.get("timing"),
                   "load": os.getloadavg()[0]}
            table.append(row)
            print(f"{downscale:9d} {grid:5d} {wall:7.1f} {peak:9.2f} {half['psnr']:8.2f} {half['detail']:7.3f} "
                  f"{crop['psnr']:8.2f} {crop['ssim']:9.4f} {row['load']:5.1f}", flush=True)
        if args.out:
            write_json_atomic(args.out, {"frame": args.frame, "overrides": args.overrides, "rungs": table})
            print(f"wrote {args.out}")
        if not args.keep:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
        return 0

    return run_script(run, args.debug)


if __name__ == "__main__":
    raise SystemExit(main())
