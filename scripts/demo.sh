#!/usr/bin/env bash
# The main job: installs dependencies, builds, and runs the demo on the bundled model.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
build=${EPONA_BUILD_DIR:-build}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DEPONA_TESTS=OFF -DEPONA_BENCHMARKS=OFF -DEPONA_EXAMPLES=ON
cmake --build "$build" -j "$(nproc)" --target example_demo
"$build/examples/example_demo" "$@"
