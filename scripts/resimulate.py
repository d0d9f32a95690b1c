"""A sequence re-simulated from its first frame, the source re-injected, every frame scored in
every camera beside its own reconstruction.

    python scripts/resimulate.py --frames FIRST LAST --out FILE.json [--figures DIR] [--every N] \
        [scene=scalarflow by default, any train.py overrides ...] [flow.KEY=VALUE ...] [simulation.KEY=VALUE ...]

Frames FIRST..LAST are reconstructed with the train.py config (in turn, through the Python API)
and a velocity fitted to each consecutive pair (``fr.estimate_flow``'s fit, warm-started; the
``flow.*`` keys set it). From frame FIRST's reconstruction alone the density is carried frame by
frame along these velocities (projected divergence-free with ``simulation.incompressible=true``;
``simulation.scheme=maccormack`` for MacCormack advection), the source re-injected each frame (in
the bottom ``simulation.inflow`` of the box along up, where that frame's smoke is, the density
becomes its reconstruction). Every frame is rendered in every camera and scored (PSNR, SSIM,
detail per view; means over the held-out and the training views). Prints a line per frame (with
how much smoke the re-simulation and the reconstruction hold, relative to frame FIRST's), the
means over the frames after FIRST, the time per frame and the peak memory; ``--out`` writes
``{"table": {"resimulation": {"heldout_psnr": .., ...}, "reconstruction": {...}}, "per_frame":
{"t": {"resimulation": {"views": {name: {"psnr": .., "ssim": .., "detail": ..}}, "heldout_psnr":
.., ..., "total": ..}, "reconstruction": {...}}}, "flows": [...], "timing": {...}}``. ``--figures DIR`` draws
every N-th frame's held-out views captured | re-simulated | reconstructed (with PSNR) and writes
their re-simulated densities as a ``.vti`` series with a ``.pvd`` index (ParaView).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import os
import sys

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

from flamerecon.dynamics.assimilation import SimulationOptions
from flamerecon.dynamics.resimulation import resimulate, resimulation_pictures, resimulation_series
from flamerecon.errors import ArgumentError
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.outputs.figures import write_png
from flamerecon.run.cli import (
    at_least,
    compose_train,
    output_file,
    output_folder,
    run_script,
    script_parser,
)
from flamerecon.run.flow import flow_options, parse_with_overrides, section_options
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene
from flamerecon.scenes.base import SceneError


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frames", type=at_least(0), nargs=2, required=True, metavar=("FIRST", "LAST"),
                        help="re-simulate from FIRST to LAST (FIRST < LAST)")
    parser.add_argument("--out", type=output_file, default=None, help="write the scores as JSON here")
    parser.add_argument("--figures", type=output_folder, default=None,
                        help="write here every N-th frame's held-out views and the .vti series")
    parser.add_argument("--every", type=at_least(1), default=10, help="frames between pictures (default 10)")
    parser.add_argument("overrides", nargs="*",
                        help="train.py overrides (default scene=scalarflow), flow.KEY=VALUE and simulation.KEY=VALUE")
    args = parse_with_overrides(parser, argv)
    first, last = args.frames
    if first >= last:
        parser.error(f"argument --frames: FIRST {first} is not before LAST {last}; give FIRST < LAST")

    def run() -> None:
        flow = flow_options([o for o in args.overrides if o.startswith("flow.")])
        simulation = section_options(SimulationOptions, "simulation",
                                     [o for o in args.overrides if o.startswith("simulation.")])
        cfg = compose_train([o for o in args.overrides if not o.startswith(("flow.", "simulation."))])
        options = options_from_config(cfg)
        try:  # the capture's end, before any reconstruction
            load_scene({**cfg.scene, "frame": last})
        except SceneError as err:
            raise ArgumentError(f"--frames: frame {last} is not in the capture ({err}); give a smaller LAST") from None
        load = os.getloadavg()[0]
        print(f"load average {load:.1f} on {os.cpu_count()} CPUs at the start; frames {first}-{last}, scene "
              f"{cfg.scene.name}, flow {flow.as_dict()}, simulation {simulation.as_dict()}", flush=True)
        report = resimulate(lambda t: load_scene({**cfg.scene, "frame": t}), options, flow, first, last, simulation,
                            keep=lambda t: args.figures is not None and ((t - first) % args.every == 0 or t == last))
        print(f"{'frame':>5} {'re-simulated held-out dB':>25} {'train dB':>9} {'reconstruction held-out dB':>27} "
              f"{'train dB':>9} {'smoke / frame ' + str(first):>16} {'reconstructed':>14}")
        totals = report.per_frame[first]["reconstruction"]["total"] or 1.0
        for t, row in report.per_frame.items():
            r, c = row["resimulation"], row["reconstruction"]
            print(f"{t:>5} {r['heldout_psnr']:25.2f} {r['train_psnr']:9.2f} {c['heldout_psnr']:27.2f} "
                  f"{c['train_psnr']:9.2f} {r['total'] / totals:16.3f} {c['total'] / totals:14.3f}")
        for method, scores in report.table.items():
            print(f"mean over frames {first + 1}-{last}, {method}: held-out {scores['heldout_psnr']:.2f} dB / SSIM "
                  f"{scores['heldout_ssim']:.4f} / detail {scores['heldout_detail']:.3f}; training "
                  f"{scores['train_psnr']:.2f} dB")
        timing = report.timing
        print(f"per frame: reconstruction {timing['reconstruction_s_per_frame']:.2f} s, flow "
              f"{timing['flow_s_per_frame']:.2f} s, transport {timing['transport_s_per_frame']:.2f} s, scoring "
              f"{timing['scoring_s_per_frame']:.2f} s; peak memory {timing['peak_rss_gb']:.2f} GB; load average "
              f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
        if args.figures is not None:
            for name, image in resimulation_pictures(report).items():
                print(f"written: {write_png(args.figures / f'{name}.png', image)}")
            for path in resimulation_series(report, args.figures):
                print(f"written: {path}")
        if args.out is not None:
            write_json_atomic(args.out, {**report.as_dict(), "frames": [first, last], "flow_options": flow.as_dict(),
                                         "simulation_options": simulation.as_dict(),
                                         "overrides": list(args.overrides), "load_average_start": load})
            print(f"written: {args.out}")

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
