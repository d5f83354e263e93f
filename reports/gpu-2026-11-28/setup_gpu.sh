# sourced by run_gpu.sh and run_gpu2.sh: the stage runner, the wheels the image lacks, and the entry points
# of the plug-in backends.  (The two calls of 2026-11-28 ran with log and stage written out in each script.)
log() { echo "$*" | tee -a "$OUT/$LOG"; }
stage() {  # stage NAME LIMIT_S OUTFILE CMD...: a time limit, its exit status and wall time in $OUT/$LOG
  local name=$1 limit=$2 out=$3; shift 3
  local t0=$(date +%s)
  echo "== $name: $*" >> "$out"
  timeout "$limit" "$@" >> "$out" 2>&1
  log "$name rc $? wall $(( $(date +%s) - t0 )) s"
}
if [ -z "${DRY:-}" ]; then
# the wheels the machine's image lacks, and the entry points that name the plug-in backends
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl 2>&1 | tail -3
python3 -m zipfile -e .whl/mitsuba-trim.zip /tmp/site  # trimmed: the cuda_ad_rgb variant and the plug-ins it loads
mkdir -p /tmp/site/isobench-0.0.dist-info
printf 'Metadata-Version: 2.1\nName: isobench\nVersion: 0.0\n' > /tmp/site/isobench-0.0.dist-info/METADATA
python3 - > /tmp/site/isobench-0.0.dist-info/entry_points.txt <<'PY'
import tomllib
eps = tomllib.load(open("pyproject.toml", "rb"))["project"]["entry-points"]["isobench.backends"]
print("[isobench.backends]"); [print(f"{k} = {v}") for k, v in eps.items()]
PY
export PYTHONPATH=/tmp/site:$PWD
fi
