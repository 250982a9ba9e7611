#!/usr/bin/env bash
# One device call (a host of 4 GPUs: kind nvidia-h100-x4; any count works): the dataset bench on
# Ray as issue 44 measures it, inside ~9 minutes. (a) builds with CUDA, (b) starts the Ray cluster
# before the jobs (as on a real cluster), (c) samples the host (tools/host_sampler.py: CPU per
# process and thread, GPU utilisation, page cache; py-spy dumps of saturated threads), (d) runs
# bench/bench_ray.py on 1, 2 and 4 GPUs with warm workers (SEQS x 150 frames, default 80), fresh
# workers on the largest count (their start in the row), and the first SUBSET sequences (16) on 2
# GPUs with fresh and warm workers, (e) writes a compact summary. Files under $OUT (at most 8):
#   summary.log      host, build, the bench table, each worker's start timeline, host load per row
#   bench_ray.log    bench_ray.py's output        bench_ray.json  its rows (timelines included)
#   host_summary.log host_sampler's per-row summary (busiest processes, their threads)
#   spy.txt          py-spy dumps of busy processes (when py-spy is there)
#   rest.tgz         raw samples, GPU utilisation, build log, Ray's logs
# Ray is not on the device image: .whl/ holds the stripped Ray wheel, its pure-Python dependencies
# (tools/strip_ray_wheel.py) and py-spy, carried with the call (carry [".whl"]).
# WPG="1 2": also the rows with 2 workers sharing each GPU (bench_ray --workers-per-gpu; the first
# value's rows come first, and the cold and subset rows use it).
# MODES="long ray procs": also the control without Ray (bench_ray --modes procs: K x W plain runs).
# PROCS_E="1 2": also procs rows of W/2 processes a GPU with --engines 2 each (bench_ray --procs-engines).
# PRESTART=1: the cluster starts with Ray's worker prestart and module preload
#   (floxels_ext.lidar.dataset.ray_preload.RAY_ENV, as docs/datasets-and-ray.md tells users), and
#   the bench waits (up to 90 s) for the idle workers' imports before its rows.
# MPS=1: a CUDA MPS control daemon on the host (the driver's default pipe, /tmp/nvidia-mps) before
#   ray start, so that the workers sharing each GPU run their kernels side by side (as
#   docs/datasets-and-ray.md tells users); stopped after ray stop.
# SKIP_BUILD=1: the package is built already (a second pass in the same call). DATA=DIR: bench_ray's
#   dataset directory (kept between passes; made if missing).
# ROUNDS=R repeats the Ray (and procs) rows R times, interleaved; SPY=N py-spy dumps of N busy workers of each kind.
# RUN_ARGS="--preset accurate": floxels run options for every row (bench_ray --run-args; its default preset is paper).
#   OUT=... [PRESTART=1] [LIMIT=540] [SEQS=80] [SUBSET=16] [GPUS="1 2 4"] [WPG="1"] [COLD=K] [MODES="long ray"] tools/gpu_ray_bench.sh
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 TORCH_CUDA_ARCH_LIST=9.0
T0=$SECONDS; LIMIT=${LIMIT:-540}; S=$OUT/summary.log; W=/tmp/gpu_ray_bench
rm -rf $W; mkdir -p $W $OUT
left() { echo $((LIMIT - (SECONDS - T0))); }
log() { echo "[$((SECONDS - T0)) s] $*" | tee -a $S; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  && export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
NG=$(nvidia-smi -L | wc -l); NC=$(nproc); GPUS=${GPUS:-"1 2 $NG"}; GPUS=$(echo $GPUS | tr ' ' '\n' | awk -v n=$NG '$1<=n && !seen[$1]++' | tr '\n' ' ')
lscpu | grep -E "^(Thread|Core|Socket|Model name)" 2>&1 | tee -a $S > $W/lscpu.txt
log "host: $NG x $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1), $NC cores, $(lscpu | grep -m1 'NUMA node(s)'), $(free -g | awk '/Mem/{print $2}') GiB"
log "ray $(python3 -c 'import ray; print(ray.__version__)' 2>&1), torch $(python3 -c 'import torch; print(torch.__version__)'), py-spy: $(command -v py-spy || echo none)"
# outputs of SEQS x 150 frames are ~2.5 MB a frame: in RAM when /dev/shm can hold them (every row deletes its own)
shm=$(df -BG --output=avail /dev/shm | tail -1 | tr -dc 0-9); [ "${shm:-0}" -gt 100 ] && export TMPDIR=/dev/shm
log "TMPDIR=${TMPDIR:-/tmp}"
# (a)
if [ "${SKIP_BUILD:-0}" = 1 ]; then log "build skipped (SKIP_BUILD=1)"; else
  OUT=$W tools/gpu_run.sh build > /dev/null 2>&1; log "build: $(grep -h 'build rc\|cuda kernels' $W/summary.log | tr '\n' ' ')"; fi
# (b)
if [ "${MPS:-0}" = 1 ]; then
  unset CUDA_MPS_PIPE_DIRECTORY; mkdir -p $W/mps_log
  CUDA_MPS_LOG_DIRECTORY=$W/mps_log nvidia-cuda-mps-control -d; log "MPS control daemon (default pipe) rc=$?"
fi
if [ "${PRESTART:-0}" = 1 ]; then
  env $(python3 -c 'from floxels_ext.lidar.dataset.ray_preload import RAY_ENV as e; print(" ".join(f"{k}={v}" for k, v in e.items()))') \
    python3 -m ray.scripts.scripts start --head --num-gpus $NG --num-cpus $NC --include-dashboard=false --disable-usage-stats \
    > $W/ray_start.log 2>&1
  log "ray start (prestart + preload) rc=$?"
  for i in $(seq 180); do  # the idle workers' preloads (each maps the compiled ops when done)
    n=$(grep -l 'floxels_ext/_C' /proc/[0-9]*/maps 2>/dev/null | wc -l); [ "$n" -ge "$NC" ] && break; sleep 0.5
  done
  log "preloaded idle workers: $n of $NC after $((i / 2)) s"
else
  python3 -m ray.scripts.scripts start --head --num-gpus $NG --num-cpus $NC --include-dashboard=false --disable-usage-stats \
    > $W/ray_start.log 2>&1
  log "ray start rc=$?"
fi
# (c)
python3 tools/host_sampler.py --out $W/hs --stop-file $W/hs/stop --interval 0.5 --spy ${SPY:-2} --spy-match "${SPY_MATCH:-FloxelsWorker|floxels_ext run}" > $W/hs.log 2>&1 &
HS=$!
# (d)
cold=${COLD:-$(echo $GPUS | awk '{print $NF}')}; coldf="--cold $cold"; [ "$cold" = none ] && coldf=""
t=$(( $(left) - 45 ))
log "bench_ray: --gpus $GPUS --workers-per-gpu ${WPG:-1} --cold $cold --subset ${SUBSET:-16} --subset-gpus 2, limit $t s"
timeout $t python3 bench/bench_ray.py --device cuda --gpus $GPUS --workers-per-gpu ${WPG:-1} --modes ${MODES:-long ray} \
  --procs-engines ${PROCS_E:-1} --sequences ${SEQS:-80} --rounds ${ROUNDS:-1} --ray-address auto $coldf ${DATA:+--data $DATA} --subset ${SUBSET:-16} --subset-gpus 2 \
  ${RUN_ARGS:+"--run-args=$RUN_ARGS"} --json $OUT/bench_ray.json \
  > $OUT/bench_ray.log 2>&1
log "bench_ray rc=$?"
mkdir -p $W/hs; touch $W/hs/stop; wait $HS
python3 -m ray.scripts.scripts stop > /dev/null 2>&1
if [ "${MPS:-0}" = 1 ]; then
  log "MPS clients: $(grep -c 'NEW CLIENT' $W/mps_log/control.log 2>/dev/null)"; echo quit | nvidia-cuda-mps-control
fi
# (e)
if [ -f $OUT/bench_ray.json ]; then
  python3 tools/host_sampler.py --summarise $W/hs --windows $OUT/bench_ray.json > $OUT/host_summary.log 2>&1
fi
{ echo; echo "== bench (frames/s over the wall; per GPU / long sequence; scaling efficiency vs the 1-GPU warm row)"
  sed -n '/^mode /,/^wrote /p' $OUT/bench_ray.log | grep -v '^wrote '
  [ -s $OUT/bench_ray.log ] && grep -E 'failed \(exit|Traceback|Error' $OUT/bench_ray.log | head -5
  echo; echo "== host per row (busiest 5 processes)"
  awk '/^== /{n=0; print; next} {if (n++ < 5) print}' $OUT/host_summary.log 2>/dev/null
} | tee -a $S
for f in $W/hs/spy/*.txt; do [ -f "$f" ] && { cat "$f"; echo; }; done > $OUT/spy.txt 2>/dev/null
[ -s $OUT/spy.txt ] || rm -f $OUT/spy.txt
cp -r /tmp/ray/session_latest/logs $W/ray_logs 2>/dev/null
find $W/ray_logs -name '*.log' -size +2M -delete 2>/dev/null
tar czf $OUT/rest.tgz -C $W . 2>/dev/null
log "done"
