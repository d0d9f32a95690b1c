"""Convert another tool's calibration into an OpenCV calibration file for scene=opencv.

    python scripts/convert_capture.py pinf DATA/info.json OUT/calibration.yaml
    python scripts/convert_capture.py colmap sparse/0 OUT/calibration.yaml --images images/
    python train.py scene=opencv scene.root=OUT              # then reconstruct from it

pinf: a PINF/HyFluid info.json (or its folder): cameras, their videos or frame folders, the box
(voxel_matrix, voxel_scale) and the held-out cameras (test_videos). colmap: COLMAP's text model
(cameras.txt, images.txt; `colmap model_converter --output_type TXT` writes it from a binary one),
one camera per image, named by its file stem, the images in --images (default: the model folder's
../../images, COLMAP's layout). --holdout names held-out cameras, --bbox gives the box
(--bbox=xmin,ymin,zmin,xmax,ymax,zmax in world units); else the loader estimates it from the silhouettes.
Check the result with scripts/check_capture.py scene=opencv scene.root=OUT (docs/own_capture.md).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import sys
from pathlib import Path

from flamerecon.run.cli import run_script, script_parser
from flamerecon.scenes.convert import colmap_to_opencv, pinf_to_opencv, write_calibration


def box(text: str) -> list[list[float]]:
    import argparse

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or any(lo >= hi for lo, hi in zip(values[:3], values[3:])):
        raise argparse.ArgumentTypeError(f"expected xmin,ymin,zmin,xmax,ymax,zmax with each min below its "
                                         f"max, got '{text}'")
    return [values[:3], values[3:]]


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("source", choices=["pinf", "colmap"], help="the format converted from")
    parser.add_argument("input", help="pinf: info.json or its folder; colmap: the text model's folder")
    parser.add_argument("output", help="the calibration file written (YAML), e.g. OUT/calibration.yaml")
    parser.add_argument("--images", help="colmap: the folder of the images (default MODEL/../../images)")
    parser.add_argument("--holdout", help="comma-separated camera names held out by default")
    parser.add_argument("--bbox", type=box, help="the box xmin,ymin,zmin,xmax,ymax,zmax (world units)")
    args = parser.parse_args(argv)

    def convert() -> None:
        output = Path(args.output)
        if args.source == "pinf":
            record = pinf_to_opencv(args.input, output)
        else:
            images = Path(args.images) if args.images else Path(args.input).resolve().parent.parent / "images"
            record = colmap_to_opencv(args.input, images, output)
        if args.holdout:
            record["holdout"] = [h for h in args.holdout.split(",") if h]
        if args.bbox:
            record["bbox"] = args.bbox
        write_calibration(output, record, f"{args.source} {args.input}")
        print(f"{output}: {len(record['cameras'])} cameras ({', '.join(c['name'] for c in record['cameras'])})"
              f"; held out: {', '.join(record.get('holdout', [])) or 'none (set --holdout or scene.holdout)'}"
              f"; box: {record.get('bbox', 'from the silhouettes')}")

    return run_script(convert, args.debug)


if __name__ == "__main__":
    sys.exit(main())
