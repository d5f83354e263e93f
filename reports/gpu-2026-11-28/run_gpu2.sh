#!/usr/bin/env bash
# The second GPU call of 2026-11-28: what the first (run_gpu.sh) could not finish: mitsuba:cuda
# (the first call's setup had no `unzip`), and the certified probe's user field and jax:gpu mesh rows.
set -u
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
D=reports/gpu-2026-11-28
LOG=gpu2.txt  # the log/stage helpers of setup_gpu.sh write here
source $D/setup_gpu.sh
nvidia-smi -L | tee "$OUT/gpu2.txt"
python3 -c "import mitsuba, drjit; print('mitsuba', mitsuba.__version__, 'drjit', drjit.__version__)" 2>&1 | tail -2 | tee -a "$OUT/gpu2.txt"
stage conformance_mitsuba 60 "$OUT/conf_mitsuba.txt" python3 -m bench conformance --backend mitsuba:cuda --fast
stage speed_mesh 80 "$OUT/speed_mesh2.txt" python3 -m bench speed --mesh --backend mitsuba:cuda,embree --no-peers \
  --side 512 --repeats 3 --out "$OUT/speed_mesh2.json"
stage certified_user 60 "$OUT/certified2.txt" python3 $D/certified_gpu.py torch:cuda,jax:gpu 1 user
stage certified_fin_jax 80 "$OUT/certified2.txt" python3 $D/certified_gpu.py jax:gpu 1 fin
log done
