"""Gather a Hydra multirun: its jobs side by side, and a multirun over frames into one sequence.

    PYTHONPATH=. python scripts/assemble.py SWEEP_DIR [--no-vti] [--skip-incomplete]

Prints a table of the jobs (the overrides that set them apart, held-out PSNR, black-image floor,
SSIM, detail, training PSNR, iterations, seconds, status) and writes it as sweep_summary.csv. A
multirun over frames (scene.frame) also becomes, in SWEEP_DIR: sequence.npz (T, C, nz, ny, nx)
with frame numbers, sequence.pvd + sequence_vti/frame_NNNN.vti, sequence_metrics.csv and
sequence_metrics.png (needs matplotlib); a sweep over other settings is only compared.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys

from flamerecon.outputs.sequence import assemble_sweep
from flamerecon.outputs.sweep import sweep_rows, sweep_table, write_sweep_csv
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
        print(sweep_table(args.sweep_dir))
        print(f"table: {write_sweep_csv(args.sweep_dir)}")
        varying, _ = sweep_rows(args.sweep_dir)
        if varying and "scene.frame" not in varying:
            print(f"not a sequence of frames (its jobs differ in {', '.join(varying)}): compared above only")
            return
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
