"""The velocity of a reconstructed sequence, written beside its frames: a multirun over
consecutive frames gets ``velocity.npz`` in each run folder (world units per second; the last
frame has none), ``sequence.npz`` and the ``.pvd`` series again with the velocities (ParaView:
Glyph or Stream Tracer on the ``velocity`` vectors), ``flow.json``, TensorBoard scalars in
``flow/`` and speed / vorticity slices and streamlines in ``flow_figures/``.

    python train.py -m scene=scalarflow 'scene.frame=range(50,60)'
    python scripts/flow.py multirun/DATE/TIME [--figures 54 55] [--no-vti] [flow.KEY=VALUE ...]

Each velocity is fitted to the next frame's training images (``fr.estimate_flow``'s fit,
warm-started from the previous pair); ``flow.*`` keys set fr.FlowOptions (``flow.control=24``,
``flow.frame_rate=30`` for a capture that does not say its own).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import sys

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

from flamerecon.run.cli import at_least, run_script, script_parser
from flamerecon.run.flow import FIGURES, FLOW_JSON, flow_options, flow_sweep, parse_with_overrides


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("sweep_dir", help="multirun folder whose subfolders are per-frame runs")
    parser.add_argument("--figures", type=at_least(0), nargs="*", default=None,
                        help="frames to draw (default: the middle one; none with an empty list)")
    parser.add_argument("--no-vti", action="store_true", help="skip the .vti series and .pvd")
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    parser.add_argument("overrides", nargs="*", help="flow.KEY=VALUE options")
    args = parse_with_overrides(parser, argv)

    def run() -> None:
        report = flow_sweep(args.sweep_dir, flow_options(args.overrides), args.figures, not args.no_vti, args.device)
        for r in report["pairs"]:
            print(f"frame {r['frame']:>4} -> {r['next_frame']}: residual {r['residual_none']:.4f} -> {r['residual']:.4f}, "
                  f"mean speed {r['mean_speed_world']:.4f} {report['units'].split('; ')[-1]}, relative divergence "
                  f"{r['relative_divergence']:.3f}, {r['seconds']:.1f} s")
        print(f"written: velocity.npz in {len(report['pairs'])} run folders, {FLOW_JSON}, sequence.npz, "
              f"{FIGURES}/ and flow/ (TensorBoard) in {args.sweep_dir}")

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
