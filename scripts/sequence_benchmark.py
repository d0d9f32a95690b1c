"""A real sequence end to end: each frame of a capture reconstructed in turn through the Python
API, cold or warm-started from the previous frame's density; prints per frame the time split,
iterations and held-out PSNR, SSIM and detail correlation, then frames per minute.

    python scripts/sequence_benchmark.py --frames 0 74 [--warm] [--every 1] \
        [scene=scalarflow by default, any train.py overrides ...]

Frames per minute counts everything a user waits for: loading the frame, the reconstruction
(camera refinement included when the scene's default has it) and scoring it.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import os
import time

import numpy as np

import flamerecon as fr
from flamerecon.fit.reconstruct import mean_of
from flamerecon.run.cli import at_least, compose_train, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frames", type=at_least(0), nargs=2, default=[0, 74], metavar=("FIRST", "LAST"),
                        help="the first and last frame, FIRST <= LAST (default: 0 74)")
    parser.add_argument("--every", type=at_least(1), default=1, help="take every N-th frame")
    parser.add_argument("--warm", action="store_true", help="warm-start each frame from the previous one")
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    args = parser.parse_args(argv)
    if args.frames[0] > args.frames[1]:
        parser.error(f"argument --frames: FIRST {args.frames[0]} is after LAST {args.frames[1]}; "
                     "give FIRST <= LAST")

    def run() -> None:
        base = compose_train(args.overrides)
        options = options_from_config(base)
        frames = list(range(args.frames[0], args.frames[1] + 1, args.every))
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs at the start", flush=True)
        print(f"{len(frames)} frames, {'warm' if args.warm else 'cold'} starts, "
              f"{options.solver.name} on a {options.grid.resolution}-cell grid, calibration.refine="
              f"{options.calibration.refine}", flush=True)
        print(f"{'frame':>5} {'load s':>7} {'recon s':>8} {'score s':>8} {'iters':>6} {'held-out dB':>12} "
              f"{'SSIM':>7} {'detail':>7} {'train dB':>9}", flush=True)
        previous, rows, started = None, [], time.perf_counter()
        for t in frames:
            clock = time.perf_counter()
            scene = load_scene({**base.scene, "frame": t})
            loaded = time.perf_counter()
            rec = fr.reconstruct(scene, options, init=previous if args.warm else None)
            solved = time.perf_counter()
            metrics = fr.score(rec)
            scored = time.perf_counter()
            held, train = mean_of(metrics["heldout"], "psnr"), mean_of(metrics["train"], "psnr")
            ssim, detail = mean_of(metrics["heldout"], "ssim"), mean_of(metrics["heldout"], "detail")
            rows.append((loaded - clock, solved - loaded, scored - solved, rec.fit.result.iterations, held,
                         ssim, detail, train))
            print(f"{t:5d} {rows[-1][0]:7.2f} {rows[-1][1]:8.2f} {rows[-1][2]:8.2f} {rows[-1][3]:6d} "
                  f"{held:12.2f} {ssim:7.4f} {detail:7.3f} {train:9.2f}", flush=True)
            previous = rec.density.cpu()
        wall = time.perf_counter() - started
        data = np.array(rows)
        print(f"mean  {data[:, 0].mean():7.2f} {data[:, 1].mean():8.2f} {data[:, 2].mean():8.2f} "
              f"{data[:, 3].mean():6.0f} {data[:, 4].mean():12.2f} {data[:, 5].mean():7.4f} {data[:, 6].mean():7.3f} "
              f"{data[:, 7].mean():9.2f}")
        print(f"{len(frames)} frames in {wall:.1f} s wall: {60 * len(frames) / wall:.2f} frames per minute "
              f"(load average {os.getloadavg()[0]:.1f} at the end)")

    return run_script(run, args.debug)


if __name__ == "__main__":
    raise SystemExit(main())
