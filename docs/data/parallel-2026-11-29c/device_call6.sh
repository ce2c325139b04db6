#!/usr/bin/env bash
# Session 37, call 6 (nvidia-h200-x2): call 5's memcheck still listed 2 "already enabled" reports:
# the once-per-pair flags were per activation type. Now one table for the process.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c6
source tests/cuda/device_env.sh
elapsed() { echo "$(( ($(date +%s%N) - $1) / 1000000 )) ms"; }
start=$(date +%s%N)
timeout 240 $SAN --tool memcheck --leak-check full $BIN/test_cuda_peer_shard_sum > $OUT/memcheck.log 2>&1
summary "memcheck test_cuda_peer_shard_sum rc=$? $(elapsed $start) $(grep -h 'ERROR SUMMARY\|LEAK SUMMARY\|test cases:\|assertions:' $OUT/memcheck.log | tr '\n' ' ')"
