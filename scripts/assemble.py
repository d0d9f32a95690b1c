"""Gather a Hydra multirun over frames into one sequence: npz, ParaView series, metrics table.

    PYTHONPATH=. python scripts/assemble.py SWEEP_DIR [--no-vti] [--skip-incomplete]

Writes into SWEEP_DIR: sequence.npz (T, C, nz, ny, nx) with frame numbers, sequence.pvd +
sequence_vti/frame_NNNN.vti, sequence_metrics.csv and sequence_metrics.png (needs matplotlib).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys

from flamerecon.outputs.sequence import assemble_sweep
from flamerecon.run.cli import run_script, script_parser


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("sweep_dir", help="multirun folder whose subfolders are per-frame runs")
    parser.add_argument("--no-vti", action="store_true", help="skip the .vti series and .pvd")
    parser.add_argument(
        "--skip-incomplete", action="store_true", help="leave out runs without density.npz"
    )
    args = parser.parse_args(argv)

    def assemble() -> None:
        written = assemble_sweep(args.sweep_dir, vti=not args.no_vti,
                                 skip_incomplete=args.skip_incomplete)
        for kind, path in written.items():
            if path is None:
                print(f"{kind}: skipped (matplotlib not installed or no numeric metrics)")
            else:
                print(f"{kind}: {path}")

    return run_script(assemble, args.debug)


if __name__ == "__main__":
    sys.exit(main())
