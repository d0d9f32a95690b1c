"""Held-out-view evaluation of a finished run.

    python scripts/evaluate.py RUN_DIR [--device auto|cpu|cuda]

Re-renders the run's views from its saved density.npz (and the scene named in its Hydra
config), writes RUN_DIR/metrics.json and RUN_DIR/renders/, and prints the summary table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flamerecon.errors import FlameReconError
from flamerecon.pipeline import evaluate, summary_table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run folder written by train.py")
    parser.add_argument("--device", default="auto", help="auto (CUDA when present) | cpu | cuda")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    args = parser.parse_args(argv)
    try:
        metrics = evaluate(args.run_dir, device=args.device)
    except (FlameReconError, FileNotFoundError) as err:
        if args.debug:
            raise
        print(f"flamerecon: error: {err}", file=sys.stderr)
        return getattr(err, "exit_code", 2)
    print(f"{args.run_dir}\n{summary_table(metrics)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
