#!/usr/bin/env bash
# One device call (one GPU): floxels run's engines with and without CUDA MPS (--mps auto / off),
# each in its own bench process (an MPS daemon started by one run serves the later runs of that
# process), interleaved, with the GPU's busy share per run (tools/host_sampler.py). Checks what
# the twelfth session left open (bench/RESULTS.md, "The engines through CUDA MPS"): short runs,
# where only engine 0 got tasks and MPS was the slower once (M5), and the busy share.
#   OUT=... [FRAMES="128 768"] [ROUNDS=2] [PRESET=accurate] [LIMIT=560] [SKIP_BUILD=1] [CEILING=1] tools/gpu_mps_check.sh
# CEILING=1: each run also times the in-memory ceiling (paper preset) in its process, and the line
# gives each layout's ratio to it. The simulated files stay in /tmp/mps_check_data between calls
# of the script on one machine (a second pass, e.g. PRESET=paper, builds none).
# (MAX_ITERS=N: fewer optimiser iterations, for a dry run of the script on a CPU)
# Writes $OUT/summary.log (each run's frames/s, engines, mps) and $OUT/mps_check.tgz (the bench
# JSON and logs, the sampler's per-run summary).
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
OUT=${OUT:-/tmp/mps_check}; mkdir -p "$OUT"; W=/tmp/mps_check_work; rm -rf $W; mkdir -p $W; D=/tmp/mps_check_data; mkdir -p $D
NOCEIL=--no-ceiling; [ "${CEILING:-0}" = 1 ] && NOCEIL=
T0=$SECONDS; LIMIT=${LIMIT:-560}; S=$OUT/summary.log; PRESET=${PRESET:-accurate}
left() { echo $((LIMIT - (SECONDS - T0))); }
log() { echo "[$((SECONDS - T0)) s] $*" | tee -a $S; }
log "GPU: $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1), $(nproc) cores"
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  FLOXELS_CUDA=ON timeout 300 python3 -m pip install --no-build-isolation --no-deps . > $W/build.log 2>&1
  log "build rc=$?"
fi
python3 tools/host_sampler.py --out $W/hs --stop-file $W/hs/stop --interval 0.25 > $W/hs.log 2>&1 &
HS=$!
for F in ${FRAMES:-128 768}; do
  # the simulated files first, untimed (a 768-frame pair of layouts takes ~85 s to build)
  timeout $(left) python3 bench/bench_run.py --frames $F --data $D/d$F --no-ceiling --max-iters 5 \
    --json $W/prep_$F.json > $W/prep_$F.log 2>&1
  log "files for $F frames rc=$?"
  for r in $(seq ${ROUNDS:-2}); do
    order="auto off"; [ $((r % 2)) = 0 ] && order="off auto"
    for m in $order; do
      [ "$(left)" -lt 30 ] && { log "out of time"; break 3; }
      j=$W/run_${F}_${m}_$r
      timeout $(left) python3 bench/bench_run.py --frames $F --data $D/d$F $NOCEIL ${MAX_ITERS:+--max-iters $MAX_ITERS} \
        --run-args "--preset $PRESET --mps $m" --windows $j.windows.json --json $j.json > $j.log 2>&1
      rc=$?
      log "$F frames, mps $m, round $r: rc $rc $(python3 -c "
import json; d = json.load(open('$j.json'))['runs']
print(', '.join(f\"{k} {v['frames_per_s']:.1f} frames/s ({v['summary'].get('engines', 1)} engines, mps {v['summary'].get('mps')}, {v.get('ratio_to_ceiling', float('nan')):.2f}x ceiling)\" for k, v in d.items()))" 2>&1)"
      python3 -c "import json; w = json.load(open('$j.windows.json')); [x.update(name='$F $m r$r ' + x['name']) for x in w]; print(json.dumps(w))" > $j.win 2>/dev/null
    done
  done
done
touch $W/hs/stop; wait $HS
python3 - "$W" <<'PY'
import glob, json, sys
rows = []
for f in sorted(glob.glob(sys.argv[1] + "/*.win")):
    try:
        rows += json.load(open(f))
    except ValueError:
        pass  # a run that failed wrote no windows
json.dump(rows, open(sys.argv[1] + "/windows.json", "w"))
PY
python3 tools/host_sampler.py --summarise $W/hs --windows $W/windows.json > $W/busy.txt 2>&1
grep -E "^== " $W/busy.txt | head -40 | tee -a $S
tar czf $OUT/mps_check.tgz -C $W $(cd $W; ls *.json *.log busy.txt hs/summary.json 2>/dev/null)
log "done"
