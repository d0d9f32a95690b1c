"""Export a run's density.npz for ParaView (VTK .vti), NRRD readers, simulation codes (raw),
Blender and Houdini (OpenVDB .vdb) and as an iso-surface mesh for Blender and ParaView (PLY, OBJ).

    PYTHONPATH=. python scripts/export.py RUN_DIR --format vti --format ply [--iso 0.1]

Formats: vti, nrrd, raw, vdb, ply, obj, mesh (ply and obj), all (every one; the default). Writes
RUN_DIR/density.vti, density.nrrd, density.raw + density.raw.json, density.vdb, density.ply,
density.obj.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys

from flamerecon.outputs.export import ALIASES, FORMATS, export_run
from flamerecon.outputs.mesh import DEFAULT_ISO
from flamerecon.run.cli import run_script, script_parser
from flamerecon.run.lock import run_lock


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("run_dir", help="run folder holding density.npz")
    parser.add_argument(
        "--format", dest="formats", action="append", choices=[*FORMATS, *ALIASES],
        help="export format; repeat for several (default: all)",
    )
    parser.add_argument("--iso", type=float, default=DEFAULT_ISO,
                        help=f"mesh level, a fraction of the peak density in (0, 1) (default: {DEFAULT_ISO})")
    args = parser.parse_args(argv)

    def export() -> None:
        with run_lock(args.run_dir):
            written = export_run(args.run_dir, args.formats or ["all"], args.iso)
        for path in written:
            print(path)

    return run_script(export, args.debug)


if __name__ == "__main__":
    sys.exit(main())
