#!/usr/bin/env bash
# The full-resolution frame and a short full-resolution sequence on CUDA, in one short run
# (issue 39): at most 6 minutes (the steps' time limits: 20 + 80 + 80 + 70 + 110 s). Prints per
# step its wall time, the GPU's and the process's peak memory and the held-out scores; the log,
# each run's metrics.json and output go to $OUT (the run folders and the operator cache stay in
# a scratch folder: a full-resolution region operator is 2.8 GB).
#
#   OUT=/some/folder bash scripts/gpu_check.sh [DATA]
#
# DATA: the ScalarFlow capture folder (info.json, train00..train04); default $FLAMERECON_DATA,
# else .gpu_data/scalarflow_real in the repository, else ../shared/data/scalarflow_real. The
# machine needs no network: modules missing from the Python it finds (kornia, kornia-rs,
# hydra-core, omegaconf, antlr4, PyYAML, tqdm, ...) are installed from the wheels in .whl/ when
# that folder is there (train.py imports every one of them).
# Steps, each under its own time limit so that one slow step still leaves the others' figures:
#   1. the default run at 1/4 (device=cuda): fits the capture's cameras once (the calibration file)
#   2. the full-resolution frame, assembled operator (scene.downscale=1 grid.resolution=256)
#   3. the same frame with the matrix-free backend (no operator stored; every product marches)
#   4. frames 60-63 at full resolution through scripts/sequence_benchmark.py: one region operator
#      for the capture (projector.reuse=true), each frame's rows and columns taken from it
set -u
cd "$(dirname "$0")/.."
if [ -n "${1:-}" ]; then DATA=$1
elif [ -n "${FLAMERECON_DATA:-}" ]; then DATA=$FLAMERECON_DATA
elif [ -d .gpu_data/scalarflow_real ]; then DATA=$PWD/.gpu_data/scalarflow_real
else DATA=$PWD/../shared/data/scalarflow_real; fi
OUT=${OUT:-gpu_check_out}
SCRATCH=$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")
mkdir -p "$OUT"
export FLAMERECON_DATA=$DATA FLAMERECON_CACHE_DIR=$SCRATCH/cache
LOG=$OUT/gpu_check.log
: > "$LOG"
say() { echo "$@" | tee -a "$LOG"; }

missing=$(python - <<'PY'
import importlib.util
need = {"kornia": "kornia", "kornia_rs": "kornia-rs", "hydra": "hydra-core", "omegaconf": "omegaconf",
        "antlr4": "antlr4-python3-runtime", "yaml": "PyYAML", "tqdm": "tqdm", "numba": "numba",
        "cv2": "opencv-python-headless", "tensorboard": "tensorboard"}
print(" ".join(pkg for mod, pkg in need.items() if importlib.util.find_spec(mod) is None))
PY
)
if [ -n "$missing" ]; then
  if [ -d .whl ]; then
    say "installing from .whl/: $missing"
    timeout 20 python -m pip install -q --no-index --find-links .whl $missing >> "$OUT/pip.out" 2>&1 \
      || say "pip from .whl/ failed (see pip.out)"
  else
    say "missing and no .whl/ folder: $missing"
  fi
fi
[ -f "$DATA/info.json" ] || say "no ScalarFlow capture at $DATA (info.json missing): every step will fail"
say "gpu_check: $(date -u +%FT%TZ), data $DATA, $(python -c 'import torch; print("torch", torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else "NO CUDA")' 2>&1)"
python -c "import numba" 2>/dev/null && say "numba: present" || say "numba: absent"

run() {  # run NAME LIMIT_S train.py overrides...: one train.py run, then its figures from metrics.json
  local name=$1 limit=$2; shift 2
  local start=$(date +%s.%N)
  timeout "$limit" python train.py device=cuda "$@" hydra.run.dir="$SCRATCH/runs/$name" >> "$OUT/$name.out" 2>&1
  local rc=$? wall=$(python -c "import time; print(f'{time.time() - $start:.1f}')")
  cp "$SCRATCH/runs/$name/metrics.json" "$OUT/$name.metrics.json" 2>/dev/null
  python - "$SCRATCH/runs/$name/metrics.json" "$name" "$rc" "$wall" <<'PY' 2>&1 | tee -a "$LOG"
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
run full_matrix_free 70 scene=scalarflow scene.downscale=1 grid.resolution=256 projector.backend=matrix_free

say "sequence (frames 60-63, full resolution, one region operator):"
timeout 110 python scripts/sequence_benchmark.py --frames 60 63 --out "$OUT/sequence.json" scene=scalarflow \
  scene.downscale=1 grid.resolution=256 device=cuda 2>>"$OUT/sequence.err" | tee -a "$LOG"
say "sequence exit ${PIPESTATUS[0]}; done $(date -u +%FT%TZ)"
rm -rf "$SCRATCH"
