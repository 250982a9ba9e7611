#!/usr/bin/env bash
# Runs the GPU DBSCAN kernel THROUGH TORCH under compute-sanitizer initcheck and memcheck.
# (scripts/gpu_dbscan_stress.sh does the same and more without torch.)
cd "$(dirname "$0")/.."
for tool in initcheck memcheck; do
  timeout 120 compute-sanitizer --tool $tool --print-limit 20 python3 scripts/gpu_debug_dbscan.py ${1:-20000} 2 2>&1 | tail -25
done
