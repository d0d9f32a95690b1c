"""Export a run's density.npz for ParaView (VTK .vti), NRRD readers and simulation codes (raw).

    PYTHONPATH=. python scripts/export.py RUN_DIR --format vti|nrrd|raw|all [--format ...]

Writes RUN_DIR/density.vti, density.nrrd, density.raw + density.raw.json.
"""

from __future__ import annotations

import sys

from flamerecon.outputs.export import FORMATS, export_run
from flamerecon.run.cli import ArgumentParser, run_script
from flamerecon.run.lock import run_lock


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="run folder holding density.npz")
    parser.add_argument(
        "--format", dest="formats", action="append", choices=[*FORMATS, "all"],
        help="export format; repeat for several (default: all)",
    )
    args = parser.parse_args(argv)

    def export() -> None:
        with run_lock(args.run_dir):
            written = export_run(args.run_dir, args.formats or ["all"])
        for path in written:
            print(path)

    return run_script(export, args.debug)


if __name__ == "__main__":
    sys.exit(main())
