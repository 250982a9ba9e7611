#!/usr/bin/env bash
# One device call: build with CUDA, run the whole test suite (CUDA tests included) and the
# CUDA benchmarks, leaving logs and JSON under $OUT. Each stage has its own time limit so
# the call ends inside the device tool's 10 minutes.
#   usage: tools/gpu_run.sh [build|test|bench|all]...
# FLOXELS_PROFILING=ON tools/gpu_run.sh build makes a profiling build (for
# tools/profile_solver.py's phase trace; see CMakeLists.txt); the default is a release build.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
stages=${*:-all}
log() { echo "[$(date +%T)] $*" | tee -a "$OUT/summary.log"; }
has() { [[ " $stages " == *" $1 "* || " $stages " == *" all "* ]]; }

if has build; then
  log "GPU: $(nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv,noheader)"
  log "torch $(python3 -c 'import torch;print(torch.__version__, torch.version.cuda)')"
  t0=$SECONDS
  FLOXELS_CUDA=ON timeout 400 python3 -m pip install -v --no-build-isolation --no-deps . >"$OUT/build.log" 2>&1
  rc=$?; log "build rc=$rc in $((SECONDS - t0)) s"
  if [ $rc -ne 0 ]; then grep -E "error|Error" "$OUT/build.log" | head -40; exit 1; fi
  python3 -c "import floxels_ext as f; print('cuda kernels:', f.ops.has_cuda_kernels())" | tee -a "$OUT/summary.log"
  python3 -c "import torch, floxels_ext; print('profiling build:', torch.ops.floxels.has_profiling())" \
    | tee -a "$OUT/summary.log"
fi
if has test; then
  t0=$SECONDS
  timeout ${TEST_TIMEOUT:-300} python3 -m pytest -q -rs tests ${PYTEST_ARGS:-} >"$OUT/tests.log" 2>&1
  log "tests rc=$? in $((SECONDS - t0)) s: $(tail -1 "$OUT/tests.log")"
  grep -E "^(FAILED|ERROR)" "$OUT/tests.log" | head -30 | tee -a "$OUT/summary.log"
fi
if has bench; then
  for b in ${BENCHES:-edt dt_loss trilinear cluster dbscan}; do
    t0=$SECONDS
    timeout ${BENCH_TIMEOUT:-90} python3 bench/bench_$b.py --device cuda >>"$OUT/bench.log" 2>&1
    log "bench $b rc=$? in $((SECONDS - t0)) s"
  done
  if [ "${EST:-1}" = 1 ]; then
    t0=$SECONDS
    timeout ${EST_TIMEOUT:-150} python3 bench/bench_estimator.py --device cuda ${EST_ARGS:-} >>"$OUT/bench.log" 2>&1
    log "bench estimator rc=$? in $((SECONDS - t0)) s"
  fi
  tar czf "$OUT/results.tgz" bench/results 2>/dev/null
fi
