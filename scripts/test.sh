#!/usr/bin/env bash
# The test command: installs dependencies, configures, builds and runs every test via ctest.
# GPU tests are compiled when nvcc is present and skip with a message when no GPU is present.
# The Python module (python/) and its pytest suite are on (EPONA_PYTHON); a sanitized build leaves
# them to a Release build (an ASan extension cannot load into python3), as .ci/run does.
#   scripts/test.sh [--sanitize] [extra CMake arguments]
# --sanitize: the same build and suite with AddressSanitizer + UBSan + LeakSanitizer in every C++
# program (C++ at -Og, build dir build-sanitize); CI runs this (.ci/run). The CUDA kernels themselves are
# checked with compute-sanitizer on a GPU (tests/cuda/sanitize_all.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
build=${EPONA_BUILD_DIR:-build}
extra=()
if [[ ${1:-} == --sanitize ]]; then
  shift
  source scripts/sanitizer-env.sh
  build=${EPONA_BUILD_DIR:-build-sanitize}
  extra=("${sanitize_cmake_args[@]}")
fi
jobs=${EPONA_JOBS:-$(nproc)}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DEPONA_TESTS=ON -DEPONA_BENCHMARKS=ON -DEPONA_EXAMPLES=ON \
  -DEPONA_PYTHON=ON "${extra[@]}" "$@"
cmake --build "$build" -j "$jobs"
ctest --test-dir "$build" --output-on-failure -j "$jobs"
