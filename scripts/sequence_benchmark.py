"""A real sequence end to end: each frame of a capture reconstructed in turn through the Python
API, cold or warm-started from the previous frame's density; prints per frame the time split,
iterations and held-out PSNR, SSIM and detail correlation, then frames per minute.

    python scripts/sequence_benchmark.py --frames 0 74 [--warm] [--every 1] \
        [--protocol run|hyfluid] [--out FILE.json] [scene=scalarflow by default, train.py overrides ...]

Frames per minute counts everything a user waits for: loading the frame, the reconstruction
(camera refinement included when the scene's default has it) and scoring it. Each frame also
prints its CPU seconds (user + system, every thread: what a busy machine disturbs least) and
the process's peak memory so far (and the GPU's peak of the frame on CUDA).

The frames share their capture's region operator (``projector.reuse=true`` unless the overrides
set it): the first frame assembles it, later ones take their rows and columns from it
(flamerecon/fit/capture_operator.py); ``projector.reuse=false`` assembles each frame's own, the
same operator entry for entry.

``--protocol hyfluid`` scores each frame as HyFluid scores ScalarFlow (flamerecon/evaluate/
protocols.py): train02 held out, rendered at half resolution (540 x 960) whatever the resolution
reconstructed (scene.downscale), cropped to rows 90-960 and columns 45-540, PSNR on [0, 1] and
SSIM as scikit-image computes it; its frames default to 60-74. ``--protocol run`` (the default)
prints the run's own held-out scores at its working resolution. ``--out`` writes the per-frame
figures (``psnr``, ``ssim``, ``detail``, ``seconds`` per frame) and their means as JSON.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import os
import time

import numpy as np
import torch

import flamerecon as fr
from flamerecon.evaluate.protocols import PROTOCOLS, protocol_scores
from flamerecon.fit.reconstruct import mean_of
from flamerecon.machine import peak_memory
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.progress import duration
from flamerecon.run.cli import at_least, compose_train, output_file, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frames", type=at_least(0), nargs=2, default=None, metavar=("FIRST", "LAST"),
                        help="the first and last frame, FIRST <= LAST (default: 0 74; 60 74 with --protocol hyfluid)")
    parser.add_argument("--every", type=at_least(1), default=1, help="take every N-th frame")
    parser.add_argument("--warm", action="store_true", help="warm-start each frame from the previous one")
    parser.add_argument("--protocol", choices=["run", *PROTOCOLS], default="run",
                        help="how the held-out view is scored (default: run, the run's own scores)")
    parser.add_argument("--out", type=output_file, default=None, metavar="FILE.json",
                        help="also write the per-frame figures as JSON")
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    args = parser.parse_args(argv)
    frames_given = args.frames or ([60, 74] if args.protocol == "hyfluid" else [0, 74])
    if frames_given[0] > frames_given[1]:
        parser.error(f"argument --frames: FIRST {frames_given[0]} is after LAST {frames_given[1]}; "
                     "give FIRST <= LAST")
    protocol = PROTOCOLS.get(args.protocol)

    def run() -> None:
        overrides = list(args.overrides)
        if not any(o.startswith("projector.reuse=") for o in overrides):
            overrides.append("projector.reuse=true")
        if protocol is not None and not any(o.startswith("holdout=") for o in overrides):
            overrides.append(f"holdout=[{protocol.view}]")
        base = compose_train(overrides)
        options = options_from_config(base)
        frames = list(range(frames_given[0], frames_given[1] + 1, args.every))
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs at the start", flush=True)
        print(f"{len(frames)} frames, {'warm' if args.warm else 'cold'} starts, "
              f"{options.solver.name} on a {options.grid.resolution}-cell grid at scene.downscale="
              f"{base.scene.get('downscale', 1)}, calibration.refine={options.calibration.refine}; held-out scores: "
              + (f"the {protocol.name} protocol ({protocol.view} at 1/{protocol.downscale} resolution"
                 + (f", rows {protocol.rows[0]}-{protocol.rows[1]}, columns {protocol.cols[0]}-{protocol.cols[1]})"
                    if protocol.rows else ", full frame)") if protocol else "the run's own, at its working resolution"),
              flush=True)
        print(f"{'frame':>5} {'load s':>7} {'recon s':>8} {'score s':>8} {'cpu s':>7} {'peak GiB':>9} {'iters':>6} "
              f"{'held-out dB':>12} {'SSIM':>7} {'detail':>7} {'train dB':>9}  done, left", flush=True)
        previous, rows, per_frame, started = None, [], {}, time.perf_counter()
        for t in frames:
            clock, cpu = time.perf_counter(), time.process_time()
            if torch.cuda.is_available():
                torch.cuda.reset_peak_memory_stats()
            scene = load_scene({**base.scene, "frame": t})
            loaded = time.perf_counter()
            rec = fr.reconstruct(scene, options, init=previous if args.warm else None)
            solved = time.perf_counter()
            metrics = fr.score(rec)
            train = mean_of(metrics["train"], "psnr")
            if protocol is None:
                held = {key: mean_of(metrics["heldout"], key) for key in ("psnr", "ssim", "detail")}
            else:
                held = protocol_scores(protocol, {**base.scene, "frame": t}, rec.scene, rec.setup.train,
                                       rec.density, rec.grid, rec.setup.step)
            scored = time.perf_counter()
            memory = peak_memory(rec.setup.pixels.device)
            peak = f"{memory['resident']:.2f}" + (f"/{memory['device']:.1f}" if "device" in memory else "")
            rows.append((loaded - clock, solved - loaded, scored - solved, rec.fit.result.iterations, held["psnr"],
                         held["ssim"], held["detail"], train))
            per_frame[str(t)] = {"psnr": held["psnr"], "ssim": held["ssim"], "detail": held["detail"],
                                 "train_psnr": train, "seconds": scored - clock, "reconstruction_seconds": solved - loaded,
                                 "iterations": rec.fit.result.iterations, "cpu_seconds": time.process_time() - cpu,
                                 "peak_memory_gib": memory}
            left = (time.perf_counter() - started) / len(rows) * (len(frames) - len(rows))  # the ETA
            print(f"{t:5d} {rows[-1][0]:7.2f} {rows[-1][1]:8.2f} {rows[-1][2]:8.2f} {time.process_time() - cpu:7.1f} "
                  f"{peak:>9} {rows[-1][3]:6d} "
                  f"{held['psnr']:12.2f} {held['ssim']:7.4f} {held['detail']:7.3f} {train:9.2f}  {len(rows)}/{len(frames)}, "
                  f"{duration(left)} left", flush=True)
            previous = rec.density.cpu()
            del rec, scene
        wall = time.perf_counter() - started
        data = np.array(rows)
        print(f"mean  {data[:, 0].mean():7.2f} {data[:, 1].mean():8.2f} {data[:, 2].mean():8.2f} {'':7} {'':9} "
              f"{data[:, 3].mean():6.0f} {data[:, 4].mean():12.2f} {data[:, 5].mean():7.4f} {data[:, 6].mean():7.3f} "
              f"{data[:, 7].mean():9.2f}")
        print(f"{len(frames)} frames in {wall:.1f} s wall: {60 * len(frames) / wall:.2f} frames per minute "
              f"(load average {os.getloadavg()[0]:.1f} at the end)")
        if args.out:
            mean = {key: float(np.mean([f[key] for f in per_frame.values()])) for key in next(iter(per_frame.values()))
                    if key != "peak_memory_gib"}
            write_json_atomic(args.out, {"protocol": args.protocol, "overrides": overrides, "frames": per_frame,
                                         "mean": mean, "wall_seconds": wall})
            print(f"wrote {args.out}")

    return run_script(run, args.debug)


if __name__ == "__main__":
    raise SystemExit(main())
