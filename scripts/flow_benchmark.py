"""What a flow costs beside the reconstruction: each frame of a sequence reconstructed in turn
through the Python API, then the velocity from the previous frame fitted to its images
(warm-started along the sequence, as ``fr.estimate_flow`` does); prints per frame the seconds of
each and the residuals, then the totals, the peak memory and the load.

    python scripts/flow_benchmark.py --frames 0 74 [scene=scalarflow by default, train.py overrides ...] \
        [flow.KEY=VALUE ...]

The reconstruction's seconds count what a user waits for per frame (loading it, the camera
files, hull, operator, solve); the flow's count its fit alone (the next frame's operator is the
one its reconstruction built).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import os
import resource
import sys
import time

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np

import flamerecon as fr
from flamerecon.dynamics.flow import estimate_velocity
from flamerecon.run.cli import at_least, compose_train, run_script, script_parser
from flamerecon.run.flow import flow_options
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frames", type=at_least(0), nargs=2, required=True, metavar=("FIRST", "LAST"),
                        help="the first and last frame, FIRST < LAST")
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default scene=scalarflow) and flow.KEY=VALUE")
    args = parser.parse_args(argv)
    if args.frames[0] >= args.frames[1]:
        parser.error(f"argument --frames: FIRST {args.frames[0]} is not before LAST {args.frames[1]}; a flow "
                     "needs two frames or more")

    def run() -> None:
        flow = flow_options([o for o in args.overrides if o.startswith("flow.")])
        cfg = compose_train([o for o in args.overrides if not o.startswith("flow.")])
        options = options_from_config(cfg)
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs at the start", flush=True)
        print(f"{'frame':>5} {'recon s':>8} {'flow s':>7} {'residual u=0':>13} {'fitted':>8} {'rel. div':>9}", flush=True)
        rows, previous, control = [], None, None
        started = time.perf_counter()
        for t in range(args.frames[0], args.frames[1] + 1):
            clock = time.perf_counter()
            rec = fr.reconstruct(load_scene({**cfg.scene, "frame": t}), options)
            seconds = time.perf_counter() - clock
            if previous is None:
                print(f"{t:5d} {seconds:8.2f}", flush=True)
            else:
                pair = estimate_velocity(previous, rec.setup, flow, control, t - 1)
                control = pair.control if flow.warm_start else None
                rows.append((seconds, pair.seconds, pair.warm))
                print(f"{t:5d} {seconds:8.2f} {pair.seconds:7.2f} {pair.residual_none:13.4f} {pair.residual:8.4f} "
                      f"{pair.relative_divergence:9.3f}", flush=True)
            previous = rec.density.detach()
            del rec
        wall = time.perf_counter() - started
        data = np.array([r[:2] for r in rows])
        warm = [r[1] for r in rows if r[2]]
        print(f"{len(rows) + 1} frames, {len(rows)} frame pairs in {wall:.1f} s wall: reconstruction "
              f"{data[:, 0].mean():.2f} s per frame, flow {data[:, 1].mean():.2f} s per pair "
              f"({np.mean(warm) if warm else float('nan'):.2f} warm-started, {data[0, 1]:.2f} the first, cold); "
              f"the flow took {100 * data[:, 1].sum() / data[:, 0].sum():.0f} % of the reconstructions' time")
        print(f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20:.2f} GB; load average "
              f"{os.getloadavg()[0]:.1f} at the end")

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
