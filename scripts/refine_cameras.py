"""Camera self-calibration, measured: held-out and training PSNR with calibration.refine
none / pose / pose+intrinsics on each frame, everything else as the config says.

    python scripts/refine_cameras.py --frames 10,33,66 [--modes pose,pose+intrinsics] \
        [--out FILE.jsonl] scene=scalarflow [train.py overrides ...]

``none`` is the density solved with the unrefined cameras, the first solve of every refinement
(the same problem and solver as a run with ``calibration.refine=none``). Prints one row per
frame and mode (held-out and training PSNR, the largest correction, seconds) and appends them
to ``--out`` as JSON lines.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import json
import os
import sys
import time

from omegaconf import OmegaConf

from flamerecon.evaluate.scores import score
from flamerecon.outputs.atomic import atomic_append_text
from flamerecon.run.cli import compose_train, frame_list, output_file, run_script, script_parser
from flamerecon.run.pipeline import calibrated_scene, mean_of, prepare, resolve_device, solve
from flamerecon.scenes import load_scene

MODES = ("pose", "pose+intrinsics")


def modes(text: str) -> list[str]:
    """argparse type: 'pose,pose+intrinsics' -> ['pose', 'pose+intrinsics'] (at least one)."""
    chosen = [m for m in text.split(",") if m]
    wrong = [m for m in chosen if m not in MODES]
    if wrong or not chosen:
        raise argparse.ArgumentTypeError(f"got '{text}'; give comma-separated modes out of {', '.join(MODES)}")
    return chosen


def measure(cfg, mode: str) -> dict:
    """Refine as ``mode`` says, solve with the refined cameras and score."""
    started = time.perf_counter()
    cfg = OmegaConf.merge(cfg, {"calibration": {"refine": mode, "score_before": True}})  # the none row
    device = resolve_device(cfg.device)
    scene, record = calibrated_scene(cfg, load_scene(cfg.scene), device)
    setup = prepare(cfg, scene, device)
    result, _, _ = solve(cfg, setup)
    silhouette = OmegaConf.to_container(cfg.silhouette, resolve=True)
    metrics, _ = score(scene, setup.volume(result.x), setup.grid, setup.train, setup.holdout, setup.step,
                       silhouette)
    row = {"frame": int(cfg.scene.get("frame", 0)), "mode": mode,
           "heldout_psnr": mean_of(metrics["heldout"], "psnr"), "train_psnr": mean_of(metrics["train"], "psnr"),
           "heldout_black": mean_of(metrics["heldout"], "psnr_black"), "seconds": time.perf_counter() - started}
    if record is not None:
        row.update(none_heldout_psnr=record["heldout_psnr_before"], none_train_psnr=record["train_psnr_before"],
                   cameras=record["cameras"], rounds=record["rounds"])
    return row


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides, key=value")
    parser.add_argument("--frames", type=frame_list, help="comma-separated scene.frame values (default: the config's)")
    parser.add_argument("--modes", type=modes, default=list(MODES), help="refinement modes besides none")
    parser.add_argument("--out", type=output_file, help="append the rows to this JSON-lines file")
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args: argparse.Namespace) -> None:
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    base = compose_train(args.overrides, default_scene=None)
    frames = args.frames or [int(base.scene.get("frame", 0))]
    print(f"  {'frame':>5} {'mode':<16} {'held-out':>9} {'training':>9} {'black':>7} "
          f"{'max box px':>10} {'seconds':>8}")
    for frame in frames:
        cfg = OmegaConf.merge(base, {"scene": {"frame": frame}})
        for mode in args.modes:
            row = measure(cfg, mode)
            if "none_heldout_psnr" in row and mode == args.modes[0]:
                print(f"  {frame:>5} {'none':<16} {row['none_heldout_psnr']:9.2f} {row['none_train_psnr']:9.2f} "
                      f"{row['heldout_black']:7.2f} {0.0:10.2f}", flush=True)
            shift = max((c["box_px"] for c in row.get("cameras", {}).values()), default=0.0)
            print(f"  {frame:>5} {mode:<16} {row['heldout_psnr']:9.2f} {row['train_psnr']:9.2f} "
                  f"{row['heldout_black']:7.2f} {shift:10.2f} {row['seconds']:8.1f}", flush=True)
            if args.out:
                atomic_append_text(args.out, json.dumps(row) + "\n")
    print(f"load average {os.getloadavg()[0]:.1f} at the end", flush=True)


if __name__ == "__main__":
    sys.exit(main())
