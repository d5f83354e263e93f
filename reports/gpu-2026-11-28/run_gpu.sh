#!/usr/bin/env bash
# The GPU checks of 2026-11-28, as one script on a lent GPU machine (from the repository root,
# with the wheels in .whl/ carried: see README.md beside this file).  Every stage has a time
# limit and appends its exit status and wall time to $OUT/gpu.txt, so that a stage that fails
# or runs long costs only its own rows.
set -u
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
# backend ids and scale (a dry run on a CPU: TORCH=torch:cpu JAX=jax:cpu MI=mitsuba:llvm SCALE=8 DRY=1)
TORCH=${TORCH:-torch:cuda} JAX=${JAX:-jax:gpu} MI=${MI:-mitsuba:cuda} SCALE=${SCALE:-1} SIDE=${SIDE:-1024}
D=reports/gpu-2026-11-28
LOG=gpu.txt  # the log/stage helpers of setup_gpu.sh write here
source reports/gpu-2026-11-28/setup_gpu.sh
nvidia-smi -L | tee "$OUT/gpu.txt"
log "$(git log -1 --format='%h %s' 2>/dev/null | cut -c1-100) (the device copy's git metadata)"
log "nproc $(nproc); optix: $(ldconfig -p | grep -c -i nvoptix) in ldconfig, $(ls /usr/local/nvidia/lib64 2>/dev/null | grep -c -i optix) in /usr/local/nvidia/lib64"
python3 - <<'PY' 2>&1 | tee -a "$OUT/gpu.txt"
import importlib, sys
print("python", sys.version.split()[0])
for m in ("numpy", "torch", "jax", "jaxlib", "scipy", "trimesh", "igl", "embreex", "drjit", "mitsuba", "numba"):
    try:
        print(m, getattr(importlib.import_module(m), "__version__", "?"))
    except Exception as exc:
        print(m, "not importable:", type(exc).__name__, str(exc)[:200])
import torch, jax
print("torch.cuda", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
print("jax devices", jax.devices())
from impls import registry
for b in ("torch:cuda", "jax:gpu", "mitsuba:cuda", "embree", "warp:cuda"):  # what the device offers
    r = registry.resolve(b)
    print(b, type(r).__name__, getattr(r, "reason", ""))
PY
# 1. conformance (torch, then mitsuba; jax beside it) while the certified probe runs
( stage conformance_torch 200 "$OUT/conf_cuda.txt" python3 -m bench conformance --backend $TORCH --fast
  stage conformance_mitsuba 60 "$OUT/conf_cuda.txt" python3 -m bench conformance --backend $MI --fast ) &
stage conformance_jax 260 "$OUT/conf_jax.txt" python3 -m bench conformance --backend $JAX --fast &
stage certified 260 "$OUT/certified.txt" python3 $D/certified_gpu.py $TORCH,$JAX $SCALE
wait
# 2. timings, alone on the machine: 2^20 pinhole rays, hybrid_secant at its defaults; then the meshes' engines
stage speed 150 "$OUT/speed.txt" python3 -m bench speed --backend numpy,torch:cpu,$TORCH,$JAX --no-peers \
  --side $SIDE --repeats 3 --out "$OUT/speed.json"
stage speed_mesh 120 "$OUT/speed_mesh.txt" python3 -m bench speed --mesh --backend embree,$MI \
  --side $(( SIDE / 2 )) --repeats 3 --out "$OUT/speed_mesh.json"
log "done"
