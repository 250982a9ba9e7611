#!/usr/bin/env bash
# One device call (one GPU): is one process alone slower as a client of a CUDA MPS daemon than
# without MPS? (The thirteenth session's D1: bench_run's in-memory ceiling, `paper` in one
# process, gave 254 frames/s in a process that `--mps auto` had made an MPS client, against 333
# in a plain one: one sample each.) Runs bench/bench_speed.py (whole frame, sequence rate) in
# separate processes, plain and as the only client of a daemon started here, alternating.
#   OUT=... [ROUNDS=2] [SKIP_BUILD=1] [SPEED_ARGS="--repeats 5 --seq-repeats 1"] tools/gpu_mps_single.sh
# Writes $OUT/mps_single.log (one line a run) and $OUT/mps_single.tgz (each run's JSON and log).
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
OUT=${OUT:-/tmp/mps_single}; mkdir -p "$OUT"; W=/tmp/mps_single_work; rm -rf $W; mkdir -p $W/pipe $W/log
S=$OUT/mps_single.log
log() { echo "[$SECONDS s] $*" | tee -a $S; }
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  FLOXELS_CUDA=ON timeout 300 python3 -m pip install --no-build-isolation --no-deps . > $W/build.log 2>&1
  log "build rc=$?"
fi
export CUDA_MPS_PIPE_DIRECTORY=$W/pipe CUDA_MPS_LOG_DIRECTORY=$W/log
nvidia-cuda-mps-control -d; log "MPS daemon rc=$?"
unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
for r in $(seq ${ROUNDS:-2}); do
  order="plain mps"; [ $((r % 2)) = 0 ] && order="mps plain"
  for m in $order; do
    j=$W/speed_${m}_$r
    if [ $m = mps ]; then
      CUDA_MPS_PIPE_DIRECTORY=$W/pipe CUDA_MPS_LOG_DIRECTORY=$W/log timeout 200 python3 bench/bench_speed.py \
        --device cuda --no-reference --no-cpu ${SPEED_ARGS:---repeats 5 --seq-repeats 1} --json $j.json > $j.log 2>&1
    else
      timeout 200 python3 bench/bench_speed.py --device cuda --no-reference --no-cpu \
        ${SPEED_ARGS:---repeats 5 --seq-repeats 1} --json $j.json > $j.log 2>&1
    fi
    rc=$?
    log "$m round $r: rc $rc $(python3 -c "
import json; d = json.load(open('$j.json'))
print(f\"whole frame {1e3 * d['frame_s']:.2f} ms, sequence {d['seq_fps']:.1f} frames/s\")" 2>&1)"
  done
done
echo quit | CUDA_MPS_PIPE_DIRECTORY=$W/pipe nvidia-cuda-mps-control
grep -h "server\|client" $W/log/control.log 2>/dev/null | tail -5 > $W/control_tail.log
tar czf $OUT/mps_single.tgz -C $W $(cd $W; ls *.json *.log 2>/dev/null)
log "done"
