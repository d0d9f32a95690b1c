"""Convert another tool's calibration into an OpenCV calibration file for scene=opencv.

    python scripts/convert_capture.py pinf DATA/info.json OUT/calibration.yaml
    python scripts/convert_capture.py colmap sparse/0 OUT/calibration.yaml --images images/
    python scripts/convert_capture.py matlab rig.json OUT/calibration.yaml --images frames/ \\
        --pattern '{camera}_t{frame:04d}.png' --unit 0.0005 --up +z
    python train.py scene=opencv scene.root=OUT              # then reconstruct from it

pinf: a PINF/HyFluid info.json (or its folder): cameras, their videos or frame folders, the box
(voxel_matrix, voxel_scale) and the held-out cameras (test_videos). colmap: COLMAP's text model
(cameras.txt, images.txt; `colmap model_converter --output_type TXT` writes it from a binary one),
one camera per image, named by its file stem, the images in --images (default: the model folder's
../../images, COLMAP's layout). matlab: a jsonencode'd or saved (MAT-file, needs scipy) MATLAB
cameraParameters, stereoParameters, or a map or array of cameras, in either of MATLAB's
conventions (pre-R2022b: IntrinsicMatrix, postmultiply poses; R2022b+: K, rigidtform3d), which it
detects and names; the images in --images (default: the file's folder), each camera's named after
it (NAME.png, NAME.mp4, NAME/) unless --pattern says otherwise.
--pattern (colmap, matlab): the file names of a flat image folder, with {camera} and optionally
{frame} ({frame:04d}: four digits); each camera's frames are linked into OUT/NAME/NNNNNN.png.
--unit: metres per world unit (0.0005 for half millimetres), --up: the world axis pointing up
(+x -x +y -y +z -z); both written at the file's top level as `unit` and `up`.
--holdout names held-out cameras, --bbox gives the box (--bbox=xmin,ymin,zmin,xmax,ymax,zmax in
world units); else the loader estimates it from the silhouettes. An existing output is replaced
only with --force, and never when it is one of the converter's own inputs.
Check the result with scripts/check_capture.py scene=opencv scene.root=OUT (docs/own_capture.md).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import argparse
import math
import sys
from pathlib import Path

from flamerecon.run.cli import run_script, script_parser
from flamerecon.scenes.base import SceneError
from flamerecon.scenes.convert import (
    check_output,
    colmap_to_opencv,
    matlab_to_opencv,
    pinf_to_opencv,
    write_conversion,
)
from flamerecon.scenes.image_pattern import ImagePattern
from flamerecon.scenes.matlab import WORLD_UNITS

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def box(text: str) -> list[list[float]]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values) or any(
            lo >= hi for lo, hi in zip(values[:3], values[3:])):
        raise argparse.ArgumentTypeError(f"expected xmin,ymin,zmin,xmax,ymax,zmax with each min below its "
                                         f"max, got '{text}'")
    return [values[:3], values[3:]]


def unit(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"got '{text}'; give metres per world unit, a number > 0 (0.001 for "
                                         "millimetres)")
    return value


def pattern(text: str) -> ImagePattern:
    try:
        return ImagePattern(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def joined_axis(argv: list[str]) -> list[str]:
    """``--up -z`` as ``--up=-z``: argparse reads a value that starts with '-' as an option."""
    out, i = [], 0
    while i < len(argv):
        joined = argv[i] == "--up" and i + 1 < len(argv) and argv[i + 1] in UP_AXES
        out.append(f"--up={argv[i + 1]}" if joined else argv[i])
        i += 2 if joined else 1
    return out


def unit_said(given: float | None, named: str | None) -> str:
    """What the summary says of the unit: given, or how to give it (with the input's own name
    of its unit, e.g. MATLAB's WorldUnits 'mm', which is a label and may be MATLAB's default)."""
    label = f"the file's WorldUnits says '{named}'" if named else ""
    if given is not None:
        return f"{given:g} m per world unit" + (f" (--unit; {label})" if label else "")
    metres = WORLD_UNITS.get(named or "")
    return "not given (--unit METRES)" + (f"; {label}: --unit {metres:g} if the pattern was measured in {named}"
                                          if metres else f"; {label}" if label else "")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("source", choices=["pinf", "colmap", "matlab"], help="the format converted from")
    parser.add_argument("input", help="pinf: info.json or its folder; colmap: the text model's folder; "
                                      "matlab: the .json or .mat file")
    parser.add_argument("output", help="the calibration file written (YAML), e.g. OUT/calibration.yaml")
    parser.add_argument("--images", help="colmap, matlab: the folder of the images (colmap: default "
                                         "MODEL/../../images; matlab: the file's folder)")
    parser.add_argument("--pattern", type=pattern, help="colmap, matlab: file names of a flat image folder, "
                                                        "e.g. '{camera}_t{frame:04d}.png'")
    parser.add_argument("--holdout", help="comma-separated camera names held out by default")
    parser.add_argument("--bbox", type=box, help="the box xmin,ymin,zmin,xmax,ymax,zmax (world units)")
    parser.add_argument("--unit", type=unit, help="metres per world unit, written as the file's `unit`")
    parser.add_argument("--up", choices=UP_AXES, help="the world axis pointing up, written as the file's `up`")
    parser.add_argument("--force", action="store_true", help="replace an existing output file")
    args = parser.parse_args(joined_axis(sys.argv[1:] if argv is None else argv))
    if args.source == "pinf" and (args.images or args.pattern):
        parser.error("--images and --pattern are for colmap and matlab (pinf's info.json names each camera's "
                     "video)")

    def convert() -> None:
        output = Path(args.output)
        source = Path(args.input)
        if args.source == "pinf":
            conversion = pinf_to_opencv(source, output)
        elif args.source == "colmap":
            images = Path(args.images) if args.images else source.resolve().parent.parent / "images"
            conversion = colmap_to_opencv(source, images, output, args.pattern)
        else:
            images = Path(args.images) if args.images else source.parent
            conversion = matlab_to_opencv(source, images, output, args.pattern)
        record = conversion.record
        names = [c["name"] for c in record["cameras"]]
        if args.holdout:
            record["holdout"] = [h for h in args.holdout.split(",") if h]
            unknown = [h for h in record["holdout"] if h not in names]
            if unknown:
                raise SceneError(f"--holdout: '{unknown[0]}' is not a camera of {source} (its cameras: "
                                 f"{', '.join(names)})")
        if args.bbox:
            record["bbox"] = args.bbox
        if args.unit is not None:
            record["unit"] = args.unit
        if args.up is not None:
            record["up"] = args.up
        check_output(output, conversion, args.force)
        write_conversion(output, conversion, f"{args.source} {args.input}")
        for note in conversion.notes:
            print(note)
        frames = {len(f) for f in conversion.links.values()}
        print(f"{output}: {len(names)} cameras ({', '.join(names)})"
              + (f", {'/'.join(map(str, sorted(frames)))} frames each (linked into {output.parent}/NAME/)"
                 if frames else "")
              + f"; held out: {', '.join(record.get('holdout', [])) or 'none (set --holdout or scene.holdout)'}"
              f"; box: {record.get('bbox', 'from the silhouettes')}"
              f"; unit: {unit_said(args.unit, conversion.world_units)}"
              f"; up: {args.up or 'not given (--up)'}")

    return run_script(convert, args.debug)


if __name__ == "__main__":
    sys.exit(main())
