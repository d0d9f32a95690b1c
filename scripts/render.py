"""Render a finished run's density from new cameras, and draw its figures.

    PYTHONPATH=. python scripts/render.py RUN_DIR [--camera orbit:ANGLE,ELEV[,DIST]]...
        [--camera CAMERAS.json [--view NAME]...] [--turntable N] [--figures]

Writes into RUN_DIR/renders/ (or --out):
  orbit_az<A>_el<E>_d<D>.png   one per orbit camera (degrees, world units; DIST defaults to a
                               distance that frames the flame)
  camera_<name>.png            one per camera of a calibration file (the run's cameras.json
                               format: name, K, world_to_camera, width, height)
  turntable.mp4, turntable.gif N views on a full circle
  top_view.png, views_10.png, slices.png   the paper's Fig. 5 and 6 and slices through the
                                           brightest region
Nothing asked for means --figures. Every figure and orbit stands on the run's up axis (its
metrics.json's scene.up; --up overrides) and measures lengths in its unit where it is known.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import json
import sys
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import cv2
import numpy as np
import torch

from flamerecon.device import resolve_device
from flamerecon.geometry.axes import UP_AXES, axis_name, up_vector
from flamerecon.geometry.cameras import make_cameras
from flamerecon.outputs.atomic import make_folder
from flamerecon.outputs.export import load_density, recorded_conventions
from flamerecon.outputs.figures import (
    framing_distance,
    orbit_cameras,
    render_views,
    slices_figure,
    support_box,
    to_rgb8,
    top_view_figure,
    turntable_frames,
    views_around,
    write_gif,
    write_mp4,
    write_png,
)
from flamerecon.outputs.names import file_stem
from flamerecon.run.cli import output_folder, run_script, script_parser
from flamerecon.scenes.calibration import check_intrinsics, check_rigid


def read_cameras_json(path: Path, only: list[str] | None = None):
    """(names, kornia cameras) from a cameras.json: a list of cameras or {"cameras": [...]},
    each with name, K (3x3), world_to_camera (4x4, OpenCV), width, height."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read camera file ({err})") from err
    entries = data.get("cameras") if isinstance(data, dict) else data
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: field 'cameras' must be a non-empty list of cameras")
    names, Ks, w2cs, sizes = [], [], [], []
    for n, cam in enumerate(entries):
        name = str(cam.get("name", n)) if isinstance(cam, dict) else str(n)
        if only and name not in only:
            continue
        try:
            K = np.asarray(cam["K"], dtype=np.float64).reshape(3, 3)
            w2c = np.asarray(cam["world_to_camera"], dtype=np.float64).reshape(4, 4)
            size = (int(cam["height"]), int(cam["width"]))
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path}: camera {name}: missing or bad field {err}") from err
        check_intrinsics(K, path, f"camera {name}: K")
        check_rigid(w2c, path, f"camera {name}: world_to_camera")
        if min(size) < 1:
            raise ValueError(f"{path}: camera {name}: width and height must be positive, got {size[::-1]}")
        names.append(name)
        Ks.append(K)
        w2cs.append(w2c)
        sizes.append(size)
    if only:
        missing = sorted(set(only) - set(names))
        if missing:
            raise ValueError(f"{path}: no camera named {missing}")
    if len(set(sizes)) != 1:
        raise ValueError(f"{path}: cameras of different image sizes {sorted(set(sizes))}; "
                         "pick one size with --view")
    (height, width), = set(sizes)
    cams = make_cameras(torch.tensor(np.stack(Ks)), torch.tensor(np.stack(w2cs)), height, width)
    return names, cams


def parse_orbit(spec: str) -> tuple[float, float, float | None]:
    """'orbit:ANGLE,ELEV[,DIST]' -> (azimuth deg, elevation deg, distance or None)."""
    values = spec.split(":", 1)[1].split(",")
    if len(values) not in (2, 3):
        raise ValueError(f"--camera {spec}: expected orbit:ANGLE,ELEV or orbit:ANGLE,ELEV,DIST")
    try:
        numbers = [float(v) for v in values]
    except ValueError as err:
        raise ValueError(f"--camera {spec}: not numbers ({err})") from err
    return numbers[0], numbers[1], numbers[2] if len(numbers) == 3 else None


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """An (H, W, 3) uint8 render with ``text`` in its top-left corner, to be read alone (left
    as it is where the text would not fit: the file's name says the same)."""
    image = np.ascontiguousarray(image)
    (width, height), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
    if width + 8 <= image.shape[1] and 3 * height <= image.shape[0]:
        cv2.putText(image, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("run_dir", type=Path, help="run folder holding density.npz")
    parser.add_argument("--camera", action="append", default=[],
                        help="orbit:ANGLE,ELEV[,DIST] or a cameras.json file (repeatable)")
    parser.add_argument("--view", action="append", help="only these cameras of a camera file")
    parser.add_argument("--turntable", type=int, default=0, metavar="N",
                        help="turntable video and GIF of N frames")
    parser.add_argument("--figures", action="store_true", help="top view, 10 views, slices")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--fov", type=float, default=40.0, help="vertical field of view, degrees")
    parser.add_argument("--elevation", type=float, default=15.0,
                        help="elevation of the turntable and the 10 views, degrees")
    parser.add_argument("--up", choices=["auto", *UP_AXES, "x", "y", "z"], default="auto",
                        help="the world axis the flame rises along (default auto: the run's scene.up, "
                             "from its metrics.json; +y for a run that recorded none)")
    parser.add_argument("--vmax", type=float, default=None,
                        help="value shown white (default: brightest pixel; 1 matches captured)")
    parser.add_argument("--fps", type=float, default=24.0)
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--out", type=output_folder, default=None, help="default: RUN_DIR/renders")
    args = parser.parse_args(argv)

    def run() -> None:
        for path in render(args):
            print(path)

    return run_script(run, args.debug)


def render(args: argparse.Namespace) -> list[Path]:
    device = resolve_device(args.device, "--device")
    for flag, least in (("width", 1), ("height", 1), ("turntable", 0), ("fps", 1)):
        if not getattr(args, flag) >= least:
            raise ValueError(f"--{flag}: got {getattr(args, flag)}; give a number >= {least}")
    if not 0 < args.fov < 180:
        raise ValueError(f"--fov: got {args.fov}; give a field of view between 0 and 180 degrees")
    density, lo, hi, _ = load_density(args.run_dir)
    volume = torch.from_numpy(density).to(device)
    facts = recorded_conventions(args.run_dir)
    axis = facts["up"] if args.up == "auto" else axis_name(args.up)
    out = make_folder(args.out or args.run_dir / "renders")
    up = up_vector(axis)
    written: list[Path] = []
    for spec in args.camera:
        if spec.startswith("orbit:"):
            azimuth, elevation, distance = parse_orbit(spec)
            near, far = support_box(density, lo, hi)
            if distance is None:
                distance = framing_distance(near, far, args.fov)
            cams = orbit_cameras([azimuth], elevation, distance, (near + far) / 2, args.width,
                                 args.height, args.fov, up)
            names = [f"orbit_az{azimuth:g}_el{elevation:g}_d{distance:.3g}"]
            labels = [f"azimuth {azimuth:g} deg, elevation {elevation:g} deg, distance {distance:.3g}"]
        else:
            names, cams = read_cameras_json(Path(spec), args.view)
            labels = [f"camera {name}" for name in names]
            names = [f"camera_{file_stem(name)}" for name in names]  # <view>.png is the pipeline's held-out figure
        images = render_views(volume, lo, hi, cams)
        for name, label, image in zip(names, labels, images):
            written.append(write_png(out / f"{name}.png", labelled(to_rgb8(image, args.vmax), label)))
    if args.turntable:
        frames = turntable_frames(volume, lo, hi, args.turntable, args.elevation, args.width,
                                  args.height, args.fov, up, vmax=args.vmax)
        written.append(write_mp4(out / "turntable.mp4", frames, args.fps))
        written.append(write_gif(out / "turntable.gif", frames, min(args.fps, 25.0)))
    if args.figures or not (args.camera or args.turntable):
        try:
            written.append(top_view_figure(out / "top_view.png", density, lo, hi, axis, str(args.run_dir),
                                           facts["unit"]))
        except ImportError as err:
            print(f"flamerecon: top_view.png skipped: {err}", file=sys.stderr)
        sheet = views_around(volume, lo, hi, 10, args.elevation, args.width, args.height,
                             args.fov, up, vmax=args.vmax)
        written.append(write_png(out / "views_10.png", sheet))
        try:
            written.append(slices_figure(out / "slices.png", density, lo, hi,
                                         title=str(args.run_dir), up=axis, unit=facts["unit"]))
        except ImportError as err:
            print(f"flamerecon: slices.png skipped: {err}", file=sys.stderr)
    return written


if __name__ == "__main__":
    sys.exit(main())
