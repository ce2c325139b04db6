#!/usr/bin/env bash
# The test command: installs dependencies, configures, builds and runs every test via ctest.
# GPU tests are compiled when nvcc is present and skip with a message when no GPU is present.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
build=${EPONA_BUILD_DIR:-build}
jobs=${EPONA_JOBS:-$(nproc)}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DEPONA_TESTS=ON -DEPONA_BENCHMARKS=ON -DEPONA_EXAMPLES=ON "$@"
cmake --build "$build" -j "$jobs"
ctest --test-dir "$build" --output-on-failure -j "$jobs"
