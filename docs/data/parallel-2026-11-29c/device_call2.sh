#!/usr/bin/env bash
# Session 37, call 2 (nvidia-h200-x2): call 1's peer-group test failed 336 of 2201 checks; which.
set -u
tar xJf .devcalls/pkgP.tar.xz -C .devcalls
BIN=$PWD/.devcalls/pkgP
OUT=$OUT/s37c2
source tests/cuda/device_env.sh
timeout 100 $BIN/test_cuda_peer_shard_sum > $OUT/peer.log 2>&1
summary "test_cuda_peer_shard_sum rc=$?"
grep -h "TEST CASE\|logged:\|^  [a-z0-9].*elements" $OUT/peer.log | sed 's/round [0-9], rank [0-9]//' | sort | uniq -c | sort -rn | head -60 | tee -a $OUT/summary.txt
grep -h "test cases\|assertions" $OUT/peer.log | tee -a $OUT/summary.txt
rm -f $OUT/peer.log.big
