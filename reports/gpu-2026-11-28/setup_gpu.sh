# sourced by run_gpu.sh and run_gpu2.sh: the wheels the image lacks, and the entry points of the plug-in backends
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
