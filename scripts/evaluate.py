"""Held-out-view evaluation of a finished run.

    python scripts/evaluate.py RUN_DIR [--device auto|cpu|cuda] [--no-native]

Re-renders the run's views from its saved density.npz (and the scene named in its Hydra
config), writes RUN_DIR/metrics.json and RUN_DIR/renders/ (rendered | captured | error), and
prints the summary table. Per held-out view: PSNR and SSIM over the full frame at the working
resolution, PSNR inside the union of the captured and rendered silhouettes, and, when the run
works below native resolution (scene.downscale > 1), PSNR and SSIM over the full native frame;
each PSNR beside that of an all-black image (the floor).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys
from pathlib import Path

from flamerecon.device import resolve_device
from flamerecon.run.cli import run_script, script_parser
from flamerecon.run.lock import run_lock
from flamerecon.run.pipeline import evaluate, summary_table


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("run_dir", type=Path, help="a run folder written by train.py")
    parser.add_argument("--device", default="auto", help="auto (CUDA when present) | cpu | cuda")
    parser.add_argument("--no-native", dest="native", action="store_false",
                        help="skip the native-resolution scores (loading full-size frames)")
    args = parser.parse_args(argv)

    def score() -> None:
        resolve_device(args.device, "--device")
        with run_lock(args.run_dir):
            metrics = evaluate(args.run_dir, device=args.device, native=args.native)
        print(f"{args.run_dir}\n{summary_table(metrics)}")
        if args.native and "native" not in metrics.get("resolution", {}):
            print("native resolution: not scored separately; the run works at its capture's own resolution "
                  "(scene.downscale=1; the synthetic scene renders its images at the working size)")

    return run_script(score, args.debug)


if __name__ == "__main__":
    sys.exit(main())
