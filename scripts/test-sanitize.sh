#!/usr/bin/env bash
# The CPU test suite under AddressSanitizer + UndefinedBehaviorSanitizer (+ LeakSanitizer, and
# float-cast-overflow): configures, builds and runs every test with -DEPONA_SANITIZE=ON in
# build-asan (EPONA_ASAN_BUILD_DIR overrides). Any sanitizer report fails its test.
# Extra arguments go to ctest (e.g. -R io_).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
build=${EPONA_ASAN_BUILD_DIR:-build-asan}
jobs=${EPONA_JOBS:-$(nproc)}
start=$SECONDS
# -O1: the optimisation level the sanitizers are made for (full reports, ~2x faster to compile
# than -O3 — this build is half of CI's time).
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_CXX_FLAGS_RELEASE="-O1 -DNDEBUG" \
  -DEPONA_SANITIZE=ON -DEPONA_CUDA=OFF -DEPONA_TESTS=ON -DEPONA_BENCHMARKS=OFF -DEPONA_EXAMPLES=OFF
cmake --build "$build" -j "$jobs"
echo "test-sanitize: built in $((SECONDS - start)) s"
# halt_on_error + abort: a report is a failed test; detect_leaks: LeakSanitizer at exit;
# allocator_may_return_null: an impossible allocation returns null as it does without ASan, so the
# library's own "out of host memory" error is what gets tested (ASan would abort instead).
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:halt_on_error=1:abort_on_error=1:strict_string_checks=1:detect_stack_use_after_return=1:allocator_may_return_null=1}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
ctest --test-dir "$build" --output-on-failure -j "$jobs" "$@"
