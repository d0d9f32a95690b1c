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

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from omegaconf import OmegaConf

from flamerecon.errors import FlameReconError
from flamerecon.evaluate.scores import score
from flamerecon.outputs.atomic import atomic_append_text
from flamerecon.run.pipeline import calibrated_scene, mean_of, prepare, resolve_device, solve
from flamerecon.run.runner import script_error
from flamerecon.scenes import load_scene


def measure(cfg, mode: str) -> dict:
    """Refine as ``mode`` says, solve with the refined cameras and score."""
    started = time.perf_counter()
    cfg = OmegaConf.merge(cfg, {"calibration": {"refine": mode}})
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="train.py overrides, key=value")
    parser.add_argument("--frames", default="", help="comma-separated scene.frame values (default: the config's)")
    parser.add_argument("--modes", default="pose,pose+intrinsics", help="refinement modes besides none")
    parser.add_argument("--out", type=Path, help="append the rows to this JSON-lines file")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    args = parser.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    try:
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
            base = compose(config_name="train", overrides=args.overrides)
        frames = [int(f) for f in args.frames.split(",") if f] or [int(base.scene.get("frame", 0))]
        print(f"  {'frame':>5} {'mode':<16} {'held-out':>9} {'training':>9} {'black':>7} "
              f"{'max box px':>10} {'seconds':>8}")
        for frame in frames:
            cfg = OmegaConf.merge(base, {"scene": {"frame": frame}})
            for mode in [m for m in args.modes.split(",") if m]:
                row = measure(cfg, mode)
                if "none_heldout_psnr" in row and mode == args.modes.split(",")[0]:
                    print(f"  {frame:>5} {'none':<16} {row['none_heldout_psnr']:9.2f} {row['none_train_psnr']:9.2f} "
                          f"{row['heldout_black']:7.2f} {0.0:10.2f}", flush=True)
                shift = max((c["box_px"] for c in row.get("cameras", {}).values()), default=0.0)
                print(f"  {frame:>5} {mode:<16} {row['heldout_psnr']:9.2f} {row['train_psnr']:9.2f} "
                      f"{row['heldout_black']:7.2f} {shift:10.2f} {row['seconds']:8.1f}", flush=True)
                if args.out:
                    atomic_append_text(args.out, json.dumps(row) + "\n")
    except (FlameReconError, FileNotFoundError, HydraException) as err:
        return script_error(err, args.debug)
    print(f"load average {os.getloadavg()[0]:.1f} at the end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
