#!/usr/bin/env bash
# Builds the torch-free DBSCAN stress harness (scripts/dbscan_stress.cu + csrc/cuda/dbscan.cu)
# and runs it: many checked calls on lidar-like clouds up to 200k points against an
# independent CPU DBSCAN, then compute-sanitizer memcheck / racecheck / synccheck / initcheck
# on small sizes. Prints one summary line per stage; exit status 1 if any stage failed.
#   usage: scripts/gpu_dbscan_stress.sh [calls (default 200)] [sanitizer max n (default 5000)]
# Takes a few minutes (the CPU reference dominates): run it in its own device call.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
BIN=${BIN:-/tmp/dbscan_stress}
ARCH=${ARCH:-sm_90}
calls=${1:-200}; san_n=${2:-5000}
fail=0
nvcc -std=c++20 -arch=$ARCH -O3 -lineinfo --expt-relaxed-constexpr -Xcompiler -ffp-contract=off -I csrc \
  scripts/dbscan_stress.cu csrc/cuda/dbscan.cu -o "$BIN" >"$OUT/dbscan_stress_build.log" 2>&1 \
  || { echo "dbscan_stress: build FAILED"; cat "$OUT/dbscan_stress_build.log"; exit 1; }

timeout 240 "$BIN" --calls "$calls" >"$OUT/dbscan_stress.log" 2>&1; rc=$?
echo "stress (rc=$rc): $(tail -1 "$OUT/dbscan_stress.log")"; [ $rc -eq 0 ] || fail=1

# Sanitizers on small sizes (each call is ~100x slower under them). racecheck/synccheck check
# shared memory and barriers (cub's kernels); memcheck/initcheck global memory.
for tool in memcheck racecheck synccheck initcheck; do
  extra=""; [ $tool = memcheck ] && extra="--leak-check full"
  timeout 75 compute-sanitizer --tool $tool $extra --error-exitcode 3 --print-limit 20 \
    "$BIN" --max-n "$san_n" --reps 1 --no-time >"$OUT/dbscan_$tool.log" 2>&1; rc=$?
  echo "compute-sanitizer $tool (rc=$rc): $(grep -E 'ERROR SUMMARY|dbscan_stress:' "$OUT/dbscan_$tool.log" | tr '\n' ' ')"
  [ $rc -eq 0 ] || { fail=1; grep -m 20 -E '=========' "$OUT/dbscan_$tool.log"; }
done
exit $fail
