#!/usr/bin/env bash
# The CPU test suite alone under AddressSanitizer + UndefinedBehaviorSanitizer (+ LeakSanitizer,
# float-cast-overflow), without CUDA, examples or benchmarks: the quick check while developing
# (build-asan; EPONA_ASAN_BUILD_DIR overrides). CI runs the whole suite that way:
# scripts/test.sh --sanitize. Extra arguments go to ctest (e.g. -R io_).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
source scripts/sanitizer-env.sh
build=${EPONA_ASAN_BUILD_DIR:-build-asan}
jobs=${EPONA_JOBS:-$(nproc)}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release "${sanitize_cmake_args[@]}" -DEPONA_CUDA=OFF \
  -DEPONA_TESTS=ON -DEPONA_BENCHMARKS=OFF -DEPONA_EXAMPLES=OFF
cmake --build "$build" -j "$jobs"
ctest --test-dir "$build" --output-on-failure -j "$jobs" "$@"
