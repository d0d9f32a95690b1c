"""Future frames predicted by the fitted flow and by the smoke simulator fitted to the frames
before, scored in every camera, against persistence, a uniform upward shift and the per-frame
reconstruction.

    python scripts/predict.py --frames FIRST LAST --horizons 1 5 10 20 30 --out FILE.json [--figures DIR] \
        [scene=scalarflow by default, any train.py overrides ...] [flow.KEY=VALUE ...] [simulation.KEY=VALUE ...]

Frames FIRST-1 .. LAST + the longest horizon are reconstructed with the train.py config (in
turn, through the Python API), a velocity fitted to each consecutive pair
(``fr.estimate_flow``'s fit, warm-started along the sequence; ``flow.control=24`` and the other
``flow.*`` keys set fr.FlowOptions), and from each frame t in FIRST..LAST frame t+k is predicted
by: ``flow`` (frame t carried k frames by the velocity fitted from t to t+1), ``flow_causal``
(by the one fitted from t-1 to t: nothing after frame t is used), ``persistence`` (frame t
unchanged), ``shift`` (frame t moved up k times one speed fitted to all the frames reconstructed),
``simulation`` (frame t carried k frames by the buoyant, incompressible smoke simulator fitted to
the images of the ``simulation.window`` frames up to t, its source held: nothing after frame t
is used; ``simulation.*`` keys set its options, ``--no-simulation`` leaves it out) and
``reconstruction`` (frame t+k's own reconstruction: what the cameras allow). Each is
rendered in every camera of frame t+k and scored: PSNR, SSIM and detail, means over the
held-out views and over the training views, then over the frames. Prints the table, the time
per frame and per flow and the peak memory; ``--out`` writes it as JSON:
``{"horizons": {"1": {"flow": {"heldout_psnr": .., "heldout_detail": .., "train_psnr": .., ...},
"simulation": {...}, "persistence": {...}, "shift": {...}, "reconstruction": {...}}, ...},
"shift_cells_per_frame": .., "per_frame": {...}, "flows": [...], "simulations": [...], "timing":
{...}}``. The capture must hold frame LAST + the longest horizon: that is checked before any
reconstruction. On ``scene=plume`` (a known
velocity) it also prints and writes each velocity's error: relative L2 and mean angle over the
smoke (``velocity_error``). ``--variant NAME:KEY=VALUE,...`` (repeatable) scores another flow
beside the default as ``flow:NAME`` (e.g. ``nodiv:divergence=0``): settings compared on the same
frames; ``--simulation-variant NAME:KEY=VALUE,...`` scores another simulation as
``simulation:NAME`` (e.g. ``physical:incompressible=true,self_advection=true,fit_buoyancy=true,start=assimilated``).
``--figures DIR`` draws frame FIRST's velocity (speed and vorticity
slices, streamlines) and, for each horizon, each held-out view captured beside every
prediction, with its PSNR, and writes the simulation's and the reconstructions' densities at
each horizon as ``.vti`` files with a ``.pvd`` index each (ParaView).
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
from flamerecon.dynamics.conventions import frame_rate_of, speed_unit
from flamerecon.dynamics.prediction import (
    METHODS,
    predict_sequence,
    prediction_pictures,
    prediction_series,
)
from flamerecon.errors import ArgumentError
from flamerecon.fit.option_rules import MAX_STEPS
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
                        help="predict from each frame FIRST..LAST (FIRST <= LAST)")
    parser.add_argument("--horizons", type=at_least(1), nargs="+", default=[1, 2, 5, 10],
                        help="frames ahead to predict (default: 1 2 5 10; up to 30 and more)")
    parser.add_argument("--no-simulation", action="store_true", help="leave the simulator's prediction out")
    parser.add_argument("--simulation-variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                        help="another simulation beside the default, e.g. physical:incompressible=true (repeatable)")
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON here")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                        help="another flow to score beside the default, e.g. nodiv:divergence=0 (repeatable)")
    parser.add_argument("--figures", type=output_folder, default=None,
                        help="write here FIRST's velocity (slices, streamlines) and its held-out predictions")
    parser.add_argument("overrides", nargs="*",
                        help="train.py overrides (default scene=scalarflow), flow.KEY=VALUE and simulation.KEY=VALUE")
    args = parse_with_overrides(parser, argv)
    if args.frames[0] > args.frames[1]:
        parser.error(f"argument --frames: FIRST {args.frames[0]} is after LAST {args.frames[1]}; give FIRST <= LAST")
    horizons = sorted(set(args.horizons))
    if horizons[-1] > MAX_STEPS:
        parser.error(f"argument --horizons: {horizons[-1]} frames ahead; at most {MAX_STEPS} (each a pass over the grid)")

    def run() -> None:
        flow = flow_options([o for o in args.overrides if o.startswith("flow.")])
        given = [o for o in args.overrides if o.startswith("simulation.")]
        simulation = None if args.no_simulation else section_options(SimulationOptions, "simulation", given)
        simulation_variants = {}
        for text in args.simulation_variant:
            name, _, settings = text.partition(":")
            if not name or not settings:
                raise ArgumentError(f"--simulation-variant: got '{text}'; give NAME:KEY=VALUE[,KEY=VALUE...], e.g. "
                                    "physical:incompressible=true")
            simulation_variants[name] = section_options(SimulationOptions, "simulation",
                                                        [*given, *(f"simulation.{kv}" for kv in settings.split(","))])
        variants = {}
        for text in args.variant:
            name, _, settings = text.partition(":")
            if not name or not settings:
                raise ArgumentError(f"--variant: got '{text}'; give NAME:KEY=VALUE[,KEY=VALUE...], e.g. nodiv:divergence=0")
            base = [o for o in args.overrides if o.startswith("flow.")]
            variants[name] = flow_options([*base, *(f"flow.{kv}" for kv in settings.split(","))])
        cfg = compose_train([o for o in args.overrides if not o.startswith(("flow.", "simulation."))])
        options = options_from_config(cfg)
        truth = None
        if cfg.scene.name == "plume":
            from flamerecon.scenes.plume import true_velocity

            def truth(grid):
                return true_velocity(grid, float(cfg.scene.rise), float(cfg.scene.swirl))

        end = args.frames[1] + horizons[-1]
        try:  # the capture's end, before any reconstruction
            load_scene({**cfg.scene, "frame": end})
        except SceneError as err:
            raise ArgumentError(f"--frames/--horizons: predicting {horizons[-1]} frames ahead of frame {args.frames[1]} "
                                f"needs frame {end}, which the capture does not have ({err}); give a smaller "
                                "LAST or horizon") from None
        load = os.getloadavg()[0]
        print(f"load average {load:.1f} on {os.cpu_count()} CPUs at the start; frames {args.frames[0]}-"
              f"{args.frames[1]}, horizons {horizons}, scene {cfg.scene.name}, flow {flow.as_dict()}, simulation "
              f"{simulation.as_dict() if simulation else 'off'}", flush=True)
        report = predict_sequence(lambda t: load_scene({**cfg.scene, "frame": t}), options, flow, args.frames[0],
                                  args.frames[1], horizons, true_velocity=truth, variants=variants,
                                  simulation=simulation, simulation_variants=simulation_variants)
        print_table(report.table)
        print(f"uniform shift fitted to the sequence: {report.shift:.2f} cells per frame")
        timing = report.timing
        scene = report.first["frame"].scene
        rate = frame_rate_of(scene, flow.frame_rate)
        print(f"reconstruction {timing['reconstruction_s_per_frame']:.2f} s per frame; flow "
              f"{timing['flow_s_per_pair_warm']:.2f} s per frame pair warm-started "
              f"({timing['flow_s_per_pair_cold']:.2f} s cold); simulation fitted in "
              f"{timing['simulation_fit_s_per_start_frame']:.1f} s per start frame, "
              f"{timing['simulation_s_per_frame_ahead']:.2f} s per frame ahead; peak memory "
              f"{timing['peak_rss_gb']:.2f} GB; load average {load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
        print(f"frame rate {rate if rate is not None else 'not known (velocities in cells per frame)'}"
              + (" frames per second" if rate is not None else ""))
        for record in report.simulations:
            print(f"{record['method']} from frame {record['frame']}: buoyancy {record['buoyancy_cells_per_frame2']:.4f} cells "
                  f"per frame^2, window residual {sum(record['residual_unmoved']):.4f} unmoved -> "
                  f"{sum(record['residual']):.4f}, {record['seconds']:.1f} s")
        out = report.as_dict()
        if "velocity_error" in out:
            err = out["velocity_error"]
            print(f"velocity against the truth over the smoke: relative L2 {err['rel_l2']:.3f}, mean angle "
                  f"{err['angular_deg']:.1f} degrees (mean of {len(err['per_pair'])} frame pairs)")
        if "simulation_velocity_error" in out:
            err = out["simulation_velocity_error"]
            print(f"simulation's velocity at the start frame against the truth: relative L2 {err['rel_l2']:.3f}, "
                  f"mean angle {err['angular_deg']:.1f} degrees (mean of {len(err['per_pair'])} start frames)")
        if args.figures is not None:
            unit = speed_unit(scene)
            for name, image in prediction_pictures(report, rate, unit, unit.removesuffix("/s")).items():
                print(f"written: {write_png(args.figures / f'{name}.png', image)}")
            for path in prediction_series(report, args.figures):
                print(f"written: {path}")
        if args.out is not None:
            write_json_atomic(args.out, {**out, "frames": list(args.frames), "flow_options": flow.as_dict(),
                                         "simulation_options": simulation.as_dict() if simulation else None,
                                         "frame_rate": rate,
                                         "overrides": list(args.overrides), "load_average_start": load})
            print(f"written: {args.out}")

    return run_script(run, args.debug)


def print_table(table: dict) -> None:
    """One row per horizon and method: held-out and training PSNR, SSIM, detail."""
    print(f"{'k':>3} {'method':<20} {'held-out dB':>11} {'SSIM':>7} {'detail':>7} {'train dB':>9} {'SSIM':>7} "
          f"{'detail':>7}")
    for k, methods in table.items():
        for m in [*METHODS, *sorted(set(methods) - set(METHODS))]:
            if m in methods:
                s = methods[m]
                print(f"{k:>3} {m:<20} {s['heldout_psnr']:11.2f} {s['heldout_ssim']:7.4f} {s['heldout_detail']:7.3f} "
                      f"{s['train_psnr']:9.2f} {s['train_ssim']:7.4f} {s['train_detail']:7.3f}")


if __name__ == "__main__":
    sys.exit(main())
