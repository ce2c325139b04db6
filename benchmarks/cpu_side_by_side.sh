#!/usr/bin/env bash
# CPU side by side: epona's bench-mid benchmark (bench_cpu_bench_mid) and the official PyTorch
# code (benchmarks/pytorch/official_bench.py, float32) on the same CPU, in one session, at 2
# threads and at all physical cores; prints a table of medians and epona/PyTorch ratios.
#
#   benchmarks/cpu_side_by_side.sh --official <checkout of Kevin-thu/Epona> [--bench <binary or dir>]
#       [--threads "2 all"] [--repeats 7] [--warmup 2] [--out <dir>] [--tests <dir>] [--no-extras]
#
# --bench: bench_cpu_bench_mid, or a folder holding x86-64-v4/ and x86-64-v3/ builds of it
#   (benchmarks/build_cpu_portable.sh); the v4 build is used when the CPU has AVX-512 F/BW/DQ/VL.
#   Default: build-perf/portable.
# --tests: a folder with portable test programs (test_cpu_gemm_*, test_nn_dcae_conv) to run on this CPU first.
# The main columns run the default dispatch: for bf16 weights the AMX tiles where the CPU (and
#   the OS) offer them, else the AVX512-BF16 dot products, else widening.
# Extras (unless --no-extras): the other AVX-512 tile (EPONA_CPU_TILE) on gemm2048 + MST,
#   bf16 weights widened to float32 (EPONA_CPU_ISA=avx512) on MST + VisDiT, and, where the
#   default is AMX, the AVX512-BF16 dot-product kernels (EPONA_CPU_ISA=avx512bf16) on the bf16
#   calls, and the DC-AE decode with im2col convolutions instead of Winograd
#   (EPONA_CPU_CONV=direct): what the kernel choices are worth on this CPU.
# The PyTorch run hides the GPUs (CUDA_VISIBLE_DEVICES=) so that nothing of it can run there.
# Raw JSON lines and the table are kept in --out (default: out/cpu_side_by_side).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"

official="" bench="$repo/build-perf/portable" threads="2 all" repeats=7 warmup=2
out="$repo/out/cpu_side_by_side" tests="" extras=1 python="${PYTHON:-python3}"
while [[ $# -gt 0 ]]; do
  case "$1" in
    --official) official="$2"; shift 2 ;;
    --bench) bench="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --warmup) warmup="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --tests) tests="$2"; shift 2 ;;
    --no-extras) extras=0; shift ;;
    -h|--help) sed -n '2,20p' "${BASH_SOURCE[0]}"; exit 0 ;;
    *) echo "cpu_side_by_side.sh: unknown argument '$1' (--help)" >&2; exit 2 ;;
  esac
done

die() { echo "cpu_side_by_side.sh: $*" >&2; exit 1; }
[[ -n "$official" ]] || die "--official <path of the official checkout> is required"
[[ -d "$official/models" ]] || die "'$official' does not look like the official checkout (no models/ folder)"
"$python" -c 'import torch' 2>/dev/null || die "$python cannot import torch"

has_flag() { grep -m1 '^flags' /proc/cpuinfo | tr ' ' '\n' | grep -qx "$1"; }
if [[ -d "$bench" ]]; then
  if has_flag avx512f && has_flag avx512bw && has_flag avx512dq && has_flag avx512vl; then
    bench_bin="$bench/x86-64-v4/bench_cpu_bench_mid"; build="x86-64-v4"
  else
    bench_bin="$bench/x86-64-v3/bench_cpu_bench_mid"; build="x86-64-v3"
  fi
else
  bench_bin="$bench"; build="as given"
fi
[[ -x "$bench_bin" ]] || die "no epona benchmark at '$bench_bin' (build it with benchmarks/build_cpu_portable.sh)"

physical_cores() {
  local n
  n=$(lscpu -p=Core,Socket 2>/dev/null | grep -v '^#' | sort -u | wc -l || true)
  [[ "$n" -gt 0 ]] 2>/dev/null && echo "$n" || nproc
}
all=$(physical_cores)
thread_list=()
for t in $threads; do
  [[ "$t" == all ]] && t=$all
  [[ "$t" =~ ^[0-9]+$ && "$t" -gt 0 ]] || die "bad thread count '$t'"
  thread_list+=("$t")
done

mkdir -p "$out"
rm -f "$out"/*.jsonl "$out"/*.log
log() { echo "== $*" | tee -a "$out/run.log"; }

log "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ //'), $all physical cores, $(nproc) logical"
log "cpu flags: $(for f in avx2 fma avx512f avx512bw avx512vl avx512_bf16 amx_bf16 amx_tile; do has_flag $f && printf '%s ' $f; done)"
log "torch: $("$python" -c 'import torch; print(torch.__version__, "| mkldnn", torch.backends.mkldnn.is_available(), "| default threads", torch.get_num_threads())')"
log "epona: $bench_bin ($build)"

if [[ -n "$tests" ]]; then
  testdir="$tests"
  [[ -d "$tests/$build" ]] && testdir="$tests/$build"
  for t in "$testdir"/test_cpu_gemm_* "$testdir"/test_nn_dcae_conv; do
    [[ -x "$t" ]] || continue
    if "$t" > "$out/$(basename "$t").log" 2>&1; then log "test $(basename "$t"): passed"
    else log "test $(basename "$t"): FAILED (see $out/$(basename "$t").log)"; tail -20 "$out/$(basename "$t").log"; fi
  done
fi

calls="mst,traj_eval,vis_eval,dcae_decode,gemm2048"
for t in "${thread_list[@]}"; do
  log "PyTorch float32, $t threads"
  pt="$out/pytorch_$t.jsonl"
  if ! CUDA_VISIBLE_DEVICES= OMP_NUM_THREADS=$t "$python" "$here/pytorch/official_bench.py" --official "$official" \
      --device cpu --config bench-mid --threads "$t" --dcae-size 128x256 --only "$calls" --repeats "$repeats" \
      --warmup "$warmup" > "$pt" 2> "$out/pytorch_$t.log"; then
    log "PyTorch run failed (tail of its log below); retrying one call at a time"
    tail -15 "$out/pytorch_$t.log"
    : > "$pt"
    for c in ${calls//,/ }; do
      CUDA_VISIBLE_DEVICES= OMP_NUM_THREADS=$t "$python" "$here/pytorch/official_bench.py" --official "$official" \
        --device cpu --config bench-mid --threads "$t" --dcae-size 128x256 --only "$c" --repeats "$repeats" \
        --warmup "$warmup" >> "$pt" 2>> "$out/pytorch_$t.log" || log "PyTorch '$c' failed at $t threads"
    done
  fi
  log "epona, $t threads"
  "$bench_bin" --threads "$t" --repeats "$repeats" --warmup "$warmup" > "$out/epona_$t.jsonl" 2> "$out/epona_$t.log" \
    || { tail -15 "$out/epona_$t.log"; die "epona benchmark failed at $t threads"; }
  if [[ $extras == 1 ]]; then
    other_tile=tall
    grep -q '"tile": "14x32"' "$out/epona_$t.jsonl" && other_tile=wide
    EPONA_CPU_TILE=$other_tile "$bench_bin" --threads "$t" --repeats "$repeats" --warmup "$warmup" --weights f32 \
      --calls gemm2048,mst | grep -v '"machine"' | sed 's/"name": "/"name": "tile:/' >> "$out/epona_extra_$t.jsonl" || true
    if grep -q '"avx512_bf16": true' "$out/epona_$t.jsonl"; then
      EPONA_CPU_ISA=avx512 "$bench_bin" --threads "$t" --repeats "$repeats" --warmup "$warmup" --weights bf16 \
        --calls mst,vis_eval | grep -v '"machine"' | sed 's/"name": "/"name": "widened:/' >> "$out/epona_extra_$t.jsonl" || true
    fi
    EPONA_CPU_CONV=direct "$bench_bin" --threads "$t" --repeats "$repeats" --warmup "$warmup" --weights f32 \
      --calls dcae_decode | grep -v '"machine"' | sed 's/"name": "/"name": "im2col:/' >> "$out/epona_extra_$t.jsonl" || true
    if grep -q '"active_isa": "amx"' "$out/epona_$t.jsonl"; then  # AMX by default: the dot products beside it
      EPONA_CPU_ISA=avx512bf16 "$bench_bin" --threads "$t" --repeats "$repeats" --warmup "$warmup" --weights bf16 \
        --calls mst,traj_eval,vis_eval 2>> "$out/epona_$t.log" | grep -v '"machine"' \
        | sed 's/"name": "/"name": "avx512bf16:/' >> "$out/epona_extra_$t.jsonl" \
        || log "AVX512-BF16 run failed at $t threads (see $out/epona_$t.log)"
    fi
  fi
done

"$python" - "$out" "${thread_list[@]}" <<'PY' | tee "$out/table.md"
import json, sys, os
out, threads = sys.argv[1], sys.argv[2:]

def load(path):
    rows = []
    if os.path.exists(path):
        for line in open(path):
            line = line.strip()
            if line.startswith("{"):
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    pass
    return rows

calls = [("mst", "MST evaluate, 10 frames"), ("traj_eval", "TrajDiT one evaluation"),
         ("vis_eval", "VisDiT one evaluation"), ("dcae_decode", "DC-AE decode 128x256"),
         ("gemm2048", "fp32 GEMM 2048³ (ceiling)")]
machine = next((r for r in load(os.path.join(out, f"epona_{threads[0]}.jsonl")) if r["name"] == "machine"), {})
print(f"CPU: {machine.get('cpu', '?')}; epona kernels: {machine.get('active_isa', '?')} (bf16 weights: "
      f"{'AMX tiles' if machine.get('active_isa') == 'amx' else 'as named'}), AVX-512 tile {machine.get('tile', '?')}")
print()
print("| call | threads | PyTorch fp32 ms | epona fp32 ms | fp32 ratio | epona bf16w ms | bf16w ratio | epona fp32 GFLOP/s |")
print("|---|---:|---:|---:|---:|---:|---:|---:|")
verdicts = []
for t in threads:
    pt = {r["name"]: r for r in load(os.path.join(out, f"pytorch_{t}.jsonl")) if "ms" in r}
    ep = {(r["name"], r.get("weights")): r for r in load(os.path.join(out, f"epona_{t}.jsonl")) if "ms" in r}
    for name, label in calls:
        p, f, b = pt.get(name), ep.get((name, "f32")), ep.get((name, "bf16"))
        fmt = lambda r: f"{r['ms']:.1f}" if r else "—"
        ratio = lambda r: f"{r['ms'] / p['ms']:.2f}" if r and p else "—"
        gf = f"{f['gflops']:.0f}" if f else "—"
        print(f"| {label} | {t} | {fmt(p)} | {fmt(f)} | {ratio(f)} | {fmt(b)} | {ratio(b)} | {gf} |")
        if p and f and name != "gemm2048":
            verdicts.append(f"{'ok  ' if f['ms'] <= p['ms'] else 'MISS'} fp32 no slower: {label}, {t} threads "
                            f"({f['ms']:.1f} vs {p['ms']:.1f} ms)")
        if p and b and name in ("mst", "vis_eval"):
            verdicts.append(f"{'ok  ' if p['ms'] / b['ms'] >= 1.5 else 'MISS'} bf16 >= 1.5x PyTorch fp32: {label}, "
                            f"{t} threads ({p['ms'] / b['ms']:.2f}x)")
print()
print("ratio = epona / PyTorch (below 1: epona faster). bf16w = bf16 weights, fp32 accumulation, default kernels.")
print()
for v in verdicts:
    print(v)
extra = [r for t in threads for r in load(os.path.join(out, f"epona_extra_{t}.jsonl")) if "ms" in r]
if extra:
    print()
    print("Kernel choices on this CPU (epona; compare with the rows above):")
    print()
    print("| variant | weights | threads | ms | GFLOP/s |")
    print("|---|---|---:|---:|---:|")
    for r in extra:
        print(f"| {r['name']} ({r['isa']}, {r['tile']}) | {r['weights']} | {r['threads']} | {r['ms']:.1f} | {r['gflops']:.0f} |")
PY
log "raw results in $out"
