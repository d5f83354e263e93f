#!/usr/bin/env bash
# Build .whl/mitsuba-trim.zip: Mitsuba 3.9.1's cp312 wheel (62.6 MB) less what mitsuba:cuda does not
# load, so that it travels to a GPU machine within the 64 MiB a call may carry.  Kept: the
# cuda_ad_rgb and scalar_rgb variants, every shared library the core links (libmitsuba.so NEEDS
# libembree3.so, even on CUDA: the first call of 2026-11-28 dropped it and the import failed) and
# the plug-ins a one-shape scene loads (LD_DEBUG=files on mitsuba:llvm: diffuse, merge, sdfgrid,
# uniform) with a few more.  Run from the repository root on the development machine.
set -euo pipefail
w=$(mktemp -d)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 -d "$w" mitsuba==3.9.1
mkdir "$w/t" && (cd "$w/t" && python3 -m zipfile -e "$w"/mitsuba-3.9.1-*.whl .)
m="$w/t/mitsuba"
rm -f "$m"/llvm_ad_* "$m"/cuda_ad_mono* "$m"/cuda_ad_spectral* "$m"/scalar_spectral* "$m"/scalar_mono*
rm -rf "$m/include" "$m/mitsuba_stubs" "$m/data/sunsky"
find "$w/t" -name '*.pyi' -delete
keep='^(diffuse|merge|sdfgrid|uniform|independent|path|perspective|obj|ply|serialized|regular|srgb|box|hdrfilm|instance|shapegroup)\.so$'
for f in "$m"/plugins/*.so; do basename "$f" | grep -qE "$keep" || rm -f "$f"; done
# every library a kept module needs is in the tree, or is Dr.Jit's (the drjit wheel, installed beside it)
missing=$(for f in "$m"/*.so "$m"/plugins/*.so; do LD_LIBRARY_PATH="$m" ldd "$f" | grep "not found"; done \
  | grep -v -E "libdrjit-(core|extra)|libnanothread" | sort -u || true)
[ -z "$missing" ] || { echo "trimmed too much: $missing"; exit 1; }
mkdir -p .whl && rm -f .whl/mitsuba-trim.zip
(cd "$w/t" && python3 -m zipfile -c "$OLDPWD/.whl/mitsuba-trim.zip" .)
ls -la .whl/mitsuba-trim.zip
rm -rf "$w"
