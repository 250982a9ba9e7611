#!/usr/bin/env bash
# Runs the GPU DBSCAN kernel under compute-sanitizer initcheck and memcheck (uninitialised
# or out-of-bounds global reads would explain its intermittent failures).
cd "$(dirname "$0")/.."
export FLOXELS_EXPERIMENTAL_GPU_DBSCAN=1
for tool in initcheck memcheck; do
  timeout 120 compute-sanitizer --tool $tool --print-limit 20 python3 scripts/gpu_debug_dbscan.py ${1:-20000} 2 2>&1 | tail -25
done
