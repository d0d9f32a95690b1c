"""What a user of a new capture waits for: ``python train.py scene=scalarflow`` on frame A
with an empty calibration folder (the cameras fitted, then the frame), then on frame B reading
the cameras fitted (a later frame); prints each run's wall time, its split and the load average.

    python scripts/first_run.py [--frames 65 67] [--out FOLDER] [train.py overrides ...]

``scene=scalarflow`` unless the overrides choose a scene. Each run is a ``train.py`` process
as a user starts it (imports, loading, outputs included), into ``FOLDER/frame<N>`` with
``calibration.folder=FOLDER/calibration`` (default: a temporary folder, removed after). The
held-out scores are printed with the frames: the scalarflow settings were chosen on frames 15-59.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import json
import os
import sys
import tempfile
from pathlib import Path

from flamerecon.errors import ConfigError
from flamerecon.run.cli import at_least, output_folder, run_script, script_parser, timed_child

TRAIN = Path(__file__).resolve().parents[1] / "train.py"


def timed_run(frame: int, folder: Path, overrides: list[str]) -> tuple[float, dict]:
    """Wall seconds of one ``train.py`` process on ``frame`` and its metrics.json."""
    run_dir = folder / f"frame{frame}"
    scene = [] if any(o.startswith("scene=") for o in overrides) else ["scene=scalarflow"]
    command = [sys.executable, str(TRAIN), *scene, f"scene.frame={frame}",
               f"calibration.folder={folder / 'calibration'}", *overrides, f"hydra.run.dir={run_dir}"]
    seconds = timed_child(command, f"train.py on frame {frame}")
    return seconds, json.loads((run_dir / "metrics.json").read_text())


def report(what: str, frame: int, seconds: float, metrics: dict) -> str:
    """One line: the wall time, the run's own split, the cameras' source, the load average."""
    timing, calibration = metrics.get("timing", {}), metrics.get("calibration") or {}
    split = ", ".join(f"{k} {timing[k]:.1f}" for k in ("calibration", "solve", "total") if k in timing)
    cameras = f"cameras {calibration['source']}" if calibration else "no camera refinement"
    heldout = list(metrics["heldout"].values())
    psnr, detail = (sum(v[k] for v in heldout) / len(heldout) for k in ("psnr", "detail"))
    return (f"{what} (frame {frame}, {cameras}): {seconds:.1f} s wall ({split} s in the run); held-out "
            f"{psnr:.2f} dB, detail {detail:.3f}; load average {os.getloadavg()[0]:.2f}")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--frames", type=at_least(0), nargs=2, default=[65, 67], metavar=("A", "B"),
                        help="the first run's frame and the later frame's (default: 65 67, both holding as much "
                        "smoke as the video's later frames; an early frame holds little and solves faster)")
    parser.add_argument("--out", type=output_folder, help="keep the runs and the calibration file here")
    parser.add_argument("overrides", nargs="*", help="train.py overrides")
    args = parser.parse_args(argv)

    def run() -> None:
        print(f"load average {os.getloadavg()[0]:.2f} on {len(os.sched_getaffinity(0))} usable cores", flush=True)
        with tempfile.TemporaryDirectory(prefix="flamerecon-first-run-") as tmp:
            folder = args.out or Path(tmp)
            if (folder / "calibration").exists() and any((folder / "calibration").iterdir()):
                raise ConfigError(f"--out: {folder / 'calibration'} is not empty; give a new folder, the "
                                      "first run must fit the cameras")
            for what, frame in (("first run", args.frames[0]), ("later frame", args.frames[1])):
                seconds, metrics = timed_run(frame, folder, args.overrides)
                print(report(what, frame, seconds, metrics), flush=True)

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
