#!/usr/bin/env bash
# The full-resolution frame and a short full-resolution sequence on CUDA, in one short run
# (issue 39): at most 6 minutes (the steps' time limits: 80 + 80 + 80 + 110 s). Prints per
# step its wall time, the GPU's and the process's peak memory and the held-out scores; the log
# and the run folders go to $OUT.
#
#   OUT=/some/folder bash scripts/gpu_check.sh [DATA]
#
# DATA: the ScalarFlow capture folder (info.json, train00..train04); default $FLAMERECON_DATA,
# else ../shared/data/scalarflow_real. The machine needs no network. Steps, each under its own
# time limit so that one slow step still leaves the others' figures:
#   1. the default run at 1/4 (device=cuda): fits the capture's cameras once (the calibration file)
#   2. the full-resolution frame, assembled operator (scene.downscale=1 grid.resolution=256)
#   3. the same frame with the matrix-free backend (no operator stored; every product marches)
#   4. frames 60-63 at full resolution through scripts/sequence_benchmark.py: one region operator
#      for the capture (projector.reuse=true), each frame's rows and columns taken from it
set -u
cd "$(dirname "$0")/.."
DATA=${1:-${FLAMERECON_DATA:-../shared/data/scalarflow_real}}
OUT=${OUT:-gpu_check_out}
mkdir -p "$OUT"
export FLAMERECON_DATA=$DATA FLAMERECON_CACHE_DIR=$OUT/cache
LOG=$OUT/gpu_check.log
: > "$LOG"
say() { echo "$@" | tee -a "$LOG"; }

say "gpu_check: $(date -u +%FT%TZ), data $DATA, $(python -c 'import torch; print(torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else "NO CUDA")' 2>&1)"
python -c "import numba" 2>/dev/null && say "numba: present (region operators on)" || say "numba: absent (each frame assembles its own operator)"

run() {  # run NAME LIMIT_S train.py overrides...: one train.py run, then its figures from metrics.json
  local name=$1 limit=$2; shift 2
  local start=$(date +%s.%N)
  timeout "$limit" python train.py device=cuda "$@" hydra.run.dir="$OUT/runs/$name" >> "$OUT/$name.out" 2>&1
  local rc=$? wall=$(python -c "import time; print(f'{time.time() - $start:.1f}')")
  python - "$OUT/runs/$name/metrics.json" "$name" "$rc" "$wall" <<'PY' 2>&1 | tee -a "$LOG"
import json, sys
path, name, rc, wall = sys.argv[1:]
try:
    m = json.load(open(path))
except OSError:
    print(f"{name}: exit {rc} after {wall} s wall, no metrics.json (see {name}.out)")
    raise SystemExit
held = {k: round(v["psnr"], 2) for k, v in m["heldout"].items()}
mem = m.get("memory", {})
split = ", ".join(f"{k} {v:.1f}" for k, v in m.get("timing", {}).items())
print(f"{name}: exit {rc}, {wall} s wall; held-out PSNR {held}; GPU peak {mem.get('device', float('nan')):.2f} GiB, "
      f"resident peak {mem.get('resident', float('nan')):.2f} GiB (bound {mem.get('bound', float('nan')):.2f}); "
      f"split [s] {split}")
PY
}

run default 80 scene=scalarflow
run full_assembled 80 scene=scalarflow scene.downscale=1 grid.resolution=256
run full_matrix_free 80 scene=scalarflow scene.downscale=1 grid.resolution=256 projector.backend=matrix_free

say "sequence (frames 60-63, full resolution, one region operator):"
timeout 110 python scripts/sequence_benchmark.py --frames 60 63 --out "$OUT/sequence.json" scene=scalarflow \
  scene.downscale=1 grid.resolution=256 device=cuda 2>>"$OUT/sequence.err" | tee -a "$LOG"
say "sequence exit ${PIPESTATUS[0]}; done $(date -u +%FT%TZ)"
