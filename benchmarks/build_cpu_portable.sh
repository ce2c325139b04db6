#!/usr/bin/env bash
# Builds the CPU benchmark (bench_cpu_bench_mid), the GEMM kernel tests and the convolution
# test (Winograd and im2col against float64) as static programs
# for two portable targets — x86-64-v4 (AVX-512 F/BW/DQ/VL: element-wise kernels and
# attention 16 lanes wide) and x86-64-v3 (AVX2) — so they run on another machine's CPU
# (cpu_side_by_side.sh picks one there). The GEMM micro-kernels beyond the target (AVX-512,
# AVX512-BF16) are chosen at run time in both; nothing is built for the build machine's CPU.
#
#   benchmarks/build_cpu_portable.sh [out dir, default build-perf/portable]
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
out="${1:-$repo/build-perf/portable}"
cxx="${CXX:-g++}"

# Header folders outside the compiler's defaults (Eigen lives in .../eigen3).
extra_include() {
  for d in /usr/include /usr/local/include; do [[ -e "$d/$1" ]] && return; done
  for d in /usr/include/eigen3 /usr/local/include/eigen3; do
    [[ -e "$d/$1" ]] && { echo "-isystem"; echo "$d"; return; }
  done
  echo "build_cpu_portable.sh: cannot find $1" >&2
  exit 1
}
includes=(-I"$repo/include")
for h in Eigen/Core xsimd/xsimd.hpp nlohmann/json.hpp doctest/doctest.h; do
  mapfile -t found < <(extra_include "$h")
  includes+=("${found[@]}")
done
flags=(-std=c++20 -O3 -DNDEBUG -fopenmp -static -Wall -Wextra -Wno-unused-parameter -Wno-psabi -Wno-maybe-uninitialized)  # GCC 12 false positives in avx512fintrin.h

build() {  # target, output, sources...
  local target=$1 output=$2
  shift 2
  mkdir -p "$(dirname "$output")"
  "$cxx" "${flags[@]}" -march="$target" -mtune=generic "${includes[@]}" "$@" -o "$output"
  echo "built $output"
}

pids=()
for target in x86-64-v4 x86-64-v3; do
  dir="$out/$target"
  build "$target" "$dir/bench_cpu_bench_mid" "$here/cpu_bench_mid.cpp" &
  pids+=($!)
  for t in cpu/gemm_isa cpu/gemm_kernels cpu/gemm_bf16 nn/dcae_conv; do
    build "$target" "$dir/test_${t/\//_}" "$repo/tests/main.cpp" "$repo/tests/$t.cpp" &
    pids+=($!)
    # two compilers at a time: the build machine is small
    if [[ ${#pids[@]} -ge 2 ]]; then wait "${pids[0]}"; pids=("${pids[@]:1}"); fi
  done
done
for p in "${pids[@]}"; do wait "$p"; done
ls -la "$out"/*/
