"""Check a capture before reconstructing it: each camera's silhouette, the box, and whether the
cameras agree (docs/own_capture.md, "What to check first").

    python scripts/check_capture.py scene=opencv scene.root=DIR [train.py overrides ...] [--out DIR]

Prints a line per camera (silhouette share of the image, share of it outside the box's outline,
IoU of it with the visual hull carved by the other cameras) and what to do about each problem,
and writes OUT/capture_check.png (OUT: DIR/check/ beside the capture's calibration file; where
that folder cannot be written, outputs/check/<date>/<time>): every camera's image with its
silhouette (green), the other cameras' hull (cyan) and the box (yellow). A camera whose pose or
focal length is wrong shows a low IoU, its cyan outline beside its green silhouette; one whose
box is behind it or out of view gets the convention its pose looks written in. It cannot see
errors the silhouettes do not show: a principal point off by half a pixel or one (a 1-based
one, MATLAB's) at the usual sizes (docs/own_capture.md). Exit status 0 when it finds no
problem, 1 when it lists one (2: bad input).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import argparse
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from flamerecon.evaluate.capture_check import check_capture, check_figure
from flamerecon.outputs.figures import write_png
from flamerecon.resources import config_dir
from flamerecon.run.cli import output_folder, run_script, script_parser
from flamerecon.run.config import options_from_config
from flamerecon.scenes import load_scene


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides, key=value (scene=..., scene.root=...)")
    parser.add_argument("--out", type=output_folder, help="output folder (default: check/ beside the capture's "
                                                             "calibration file)")
    args = parser.parse_intermixed_args(argv)  # --out before or after the overrides

    def run() -> int:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name="train", overrides=list(args.overrides))
        options = options_from_config(cfg)
        scene = load_scene(cfg.scene)
        bbox = options.grid.bbox
        checks, masks, footprints = check_capture(scene, options.silhouette.as_dict(), bbox)
        H, W = scene.image_size
        lo, hi = bbox if bbox is not None else (scene.bbox_min, scene.bbox_max)
        print(f"{scene.source}: {scene.num_views} cameras, {W} x {H} px, box {list(lo)} to {list(hi)}, "
              f"held out by default: {scene.default_holdout or 'none'}")
        print(f"{'camera':10} {'silhouette':>10} {'outside box':>12} {'hull IoU':>9}")
        for c in checks:
            print(f"{c.name:10} {100 * c.silhouette:9.1f}% {100 * c.outside_box:11.1f}% {c.hull_iou:9.2f}")
        problems = [f"  {c.name}: {p}" for c in checks for p in c.problems]
        print(f"PROBLEMS ({len(problems)})\n" + "\n".join(problems) if problems else "no problem found")
        folder, note = (args.out, "") if args.out is not None else beside(scene.source)
        path = write_png(Path(folder) / "capture_check.png", check_figure(scene, checks, masks, footprints, bbox))
        print(f"picture: {path}{note}")
        return 1 if problems else 0

    return run_script(run, args.debug)


def beside(source: str) -> tuple[Path, str]:
    """The folder for the picture: check/ beside the capture's calibration file (or in its
    folder), else, where that cannot be written (or the scene has no file), a dated folder under
    outputs/check/; and a note saying why when it is the latter."""
    fallback = Path("outputs/check") / time.strftime("%Y-%m-%d") / time.strftime("%H-%M-%S")
    capture = Path(source)
    if not capture.exists():
        return output_folder(str(fallback)), ""
    folder = (capture.parent if capture.is_file() else capture) / "check"
    try:
        return output_folder(str(folder)), ""
    except argparse.ArgumentTypeError as err:
        return output_folder(str(fallback)), f" ({folder} cannot be written: {err})"


if __name__ == "__main__":
    sys.exit(main())
