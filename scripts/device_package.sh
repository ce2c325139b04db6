#!/usr/bin/env bash
# Collects prebuilt programs for a GPU machine (no doctest, xsimd or network there) into one
# folder: the programs named, plus the run-time libraries the GPU machine may lack (libgomp),
# in <out>/lib, which the device scripts put on LD_LIBRARY_PATH. Carry <out> with the device
# call (tests/cuda/*_run.sh and benchmarks/*_run.sh take it as their bin dir).
# Usage: scripts/device_package.sh <build dir> <out dir> <program>...
set -euo pipefail
build=$1 out=$2
shift 2
mkdir -p "$out/lib"
for name in "$@"; do
  path=$(find "$build" -type f -name "$name" -perm -u+x -print -quit)
  [[ -n $path ]] || { echo "device_package: $name not built in $build" >&2; exit 1; }
  cp "$path" "$out/"
done
for lib in libgomp.so.1; do
  path=$(ldconfig -p | awk -v l="$lib" '$1 == l {print $NF; exit}')
  [[ -n $path ]] && cp -L "$path" "$out/lib/"
done
du -sh "$out"
