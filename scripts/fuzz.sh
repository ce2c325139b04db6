#!/usr/bin/env bash
# Builds the libFuzzer targets (clang, ASan + UBSan + LSan) and runs each for a given time.
#   scripts/fuzz.sh [SECONDS] [TARGET ...]     default: 60 s, every fuzz/fuzz_<target>.cpp
# Runs EPONA_FUZZ_JOBS targets at a time (default 2) at nice 10. Each target starts from its seed
# corpus fuzz/corpus/<target>/ and grows fuzz/corpus-work/<target>/ (git-ignored, kept between
# runs); crash/leak/timeout inputs go to fuzz/corpus-work/artifacts/<target>/, logs to
# fuzz/corpus-work/logs/. Prints executions, exec/s, coverage (cov = edges, ft = features) and
# corpus size per target (also written to fuzz/corpus-work/summary.md); exits 1 if any target
# found something. Reproduce a finding: build-fuzz/fuzz/fuzz_<target> <artifact>
# (EPONA_FUZZ_VERBOSE=1 prints whether each input was accepted or refused, and why).
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-60}
shift || true
build=${EPONA_FUZZ_BUILD_DIR:-build-fuzz}
jobs=${EPONA_FUZZ_JOBS:-2}
work=fuzz/corpus-work

scripts/setup.sh
dpkg-query -W -f='${Status}' libomp-dev 2>/dev/null | grep -q "install ok installed" || {
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get install -y -qq --no-install-recommends libomp-dev >/dev/null  # OpenMP for clang
}
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_CXX_COMPILER=clang++ -DEPONA_CUDA=OFF \
  -DEPONA_TESTS=OFF -DEPONA_EXAMPLES=OFF -DEPONA_BENCHMARKS=OFF -DEPONA_FUZZ=ON >/dev/null

if (($#)); then
  targets=("$@")
else
  targets=()
  for f in fuzz/fuzz_*.cpp; do t=${f#fuzz/fuzz_}; targets+=("${t%.cpp}"); done
fi
nice -n 10 cmake --build "$build" -j "$jobs" --target "${targets[@]/#/fuzz_}"

# Dictionaries (fuzz/dict/*.dict) each target gets, concatenated (libFuzzer takes one).
declare -A dicts=(
  [safetensors]="json safetensors" [zip]="zip" [pickle]="pickle" [torch_checkpoint]="pickle"
  [config_json]="json config" [npy]="npy" [poses_csv]="csv" [poses_json]="json poses" [poses_npy]="npy"
  [trajectory_csv]="csv" [trajectory_json]="json poses" [image]="image")
# Seconds one input may run before it counts as a hang: 10, and 30 for images (decoding and
# resizing up to ImageReadOptions::max_pixels = 33 Mpixel legitimately takes seconds under ASan).
declare -A timeouts=([image]=30)
mkdir -p "$work/logs" "$build/dicts"
stamp=$work/logs/.started
touch "$stamp"  # findings are the artifacts newer than this

run_target() {
  local t=$1 dict="$build/dicts/$1.dict" args=()
  : >"$dict"
  for d in ${dicts[$t]:-}; do [ -f "fuzz/dict/$d.dict" ] && cat "fuzz/dict/$d.dict" >>"$dict"; done
  [ -s "$dict" ] && args+=(-dict="$dict")
  mkdir -p "$work/$t" "$work/artifacts/$t" fuzz/corpus/"$t"
  # -rss_limit_mb/-malloc_limit_mb: an input that makes a reader allocate 1 GB at once or hold
  # over 2 GB (an unchecked size) is a finding.
  nice -n 10 "$build/fuzz/fuzz_$t" "$work/$t" "fuzz/corpus/$t" "${args[@]}" -max_total_time="$seconds" \
    -timeout="${timeouts[$t]:-10}" -rss_limit_mb=2048 -malloc_limit_mb=1024 -print_final_stats=1 \
    -artifact_prefix="$work/artifacts/$t/" >"$work/logs/$t.log" 2>&1 || true
  echo "fuzz: $t finished"
}

# At most $jobs targets at a time.
for t in "${targets[@]}"; do
  while (($(jobs -rp | wc -l) >= jobs)); do wait -n || true; done
  run_target "$t" &
done
wait

# Summary from each log: libFuzzer's final stats and its last status line.
summary=$work/summary.md
found=0
{
  echo "| target | seconds run | executions | exec/s | cov | ft | corpus (files/bytes) | peak RSS MB | findings |"
  echo "|---|---|---|---|---|---|---|---|---|"
  for t in "${targets[@]}"; do
    log=$work/logs/$t.log
    final_stat() { sed -n "s/^stat::$1: *//p" "$log" | tail -1; }
    status=$(grep -E '^#[0-9]+.*cov: ' "$log" | tail -1)
    field() { sed -n "s/.* $1: \([^ ]*\).*/\1/p" <<<"$status"; }
    artifacts=$(find "$work/artifacts/$t" -type f -newer "$stamp" | wc -l)
    what=$(grep -m1 -oE 'ERROR: (AddressSanitizer|LeakSanitizer|UndefinedBehaviorSanitizer|libFuzzer)[^(]*|epona fuzz: [^:]*|runtime error: .*' "$log" || true)
    ((artifacts)) && found=1
    ran=$(sed -n 's/^Done [0-9]* runs in \([0-9]*\) second.*/\1/p' "$log" | tail -1)
    echo "| $t | ${ran:-stopped early} | $(final_stat number_of_executed_units) | $(final_stat average_exec_per_sec) | $(field cov) | $(field ft) |" \
         "$(field corp) | $(final_stat peak_rss_mb) | $( ((artifacts)) && echo "$artifacts: ${what:-see log}" || echo none) |"
  done
} | tee "$summary"
exit $found
