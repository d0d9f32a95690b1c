"""Export a run's density.npz for ParaView (VTK .vti), NRRD readers and simulation codes (raw).

    PYTHONPATH=. python scripts/export.py RUN_DIR --format vti|nrrd|raw|all [--format ...]

Writes RUN_DIR/density.vti, density.nrrd, density.raw + density.raw.json.
"""

from __future__ import annotations

import argparse
import sys

from flamerecon.export import FORMATS, DensityFileError, export_run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="run folder holding density.npz")
    parser.add_argument(
        "--format", dest="formats", action="append", choices=[*FORMATS, "all"],
        help="export format; repeat for several (default: all)",
    )
    args = parser.parse_args(argv)
    try:
        written = export_run(args.run_dir, args.formats or ["all"])
    except (FileNotFoundError, DensityFileError, ImportError, ValueError) as err:
        print(f"export: {err}", file=sys.stderr)
        return 1
    for path in written:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
