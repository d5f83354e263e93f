#!/usr/bin/env bash
# The GPU check of 2026-11-28 (second): sphere tracing's bracket refinement and the certificate
# withdrawal, on torch:cuda and jax:gpu beside numpy, as one script on a lent GPU machine, from the
# repository root, with the wheels the image lacks in .whl/ (array-api-compat).  Every stage has a
# time limit and appends its exit status and wall time to $OUT/gpu.txt.
set -u
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
D=reports/gpu-2026-11-28b
SIDE=${SIDE:-512}
log() { echo "$*" | tee -a "$OUT/gpu.txt"; }
stage() {  # stage NAME LIMIT_S OUTFILE CMD...
  local name=$1 limit=$2 out=$3; shift 3
  local t0=$(date +%s)
  echo "== $name: $*" >> "$out"
  timeout "$limit" "$@" >> "$out" 2>&1
  log "$name rc $? wall $(( $(date +%s) - t0 )) s"
}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl 2>&1 | tail -3
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi -L | tee "$OUT/gpu.txt"
python3 - <<'PY' 2>&1 | tee -a "$OUT/gpu.txt"
import importlib, sys
print("python", sys.version.split()[0])
for m in ("numpy", "torch", "jax", "jaxlib", "scipy", "array_api_compat", "pytest"):
    try:
        print(m, getattr(importlib.import_module(m), "__version__", "?"))
    except Exception as exc:
        print(m, "not importable:", type(exc).__name__, str(exc)[:200])
PY
stage conformance_jax 240 "$OUT/conf_jax.txt" python3 -m bench conformance --backend jax:gpu --fast &
stage conformance_torch 240 "$OUT/conf_cuda.txt" python3 -m bench conformance --backend torch:cuda --fast &
stage refine 420 "$OUT/refine.txt" python3 $D/refine_gpu.py torch:cuda,jax:gpu,numpy $SIDE
wait
log done
