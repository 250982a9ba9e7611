#!/usr/bin/env bash
# Issue 47's map (bench/accurate_map.py) on every GPU of a host, in one device call: one process
# per GPU on its share of the cases (--shard K/N, CUDA_VISIBLE_DEVICES=K), all on one cache, each
# simulating its own cases first; then one --cached-only run writes the tables of every finished
# case. Run from a built checkout (PYTHONPATH set to it) where ../shared/data (or ./shared/data
# for a copy under .ab/) holds the real scans. Files under $OUT: accurate_map.{json,md}, shard
# logs (shards.log), summary.log.
#   OUT=... [LIMIT=540] [ARGS="--today --real av2 kitti"] [SEEDS="60 61 62"] [SHARD_GPUS="0 1 2 3"] tools/gpu_map_shards.sh
set -u
export PYTHONUNBUFFERED=1
T0=$SECONDS; LIMIT=${LIMIT:-540}; S=$OUT/summary.log; C=${CACHE:-/tmp/amc}
log() { echo "[$((SECONDS - T0)) s] $*" | tee -a $S; }
# SHARD_GPUS="1 2 3": the GPUs to use (default every GPU; e.g. leave GPU 0 to the CUDA tests)
G=(${SHARD_GPUS:-$(seq 0 $(( $(nvidia-smi -L | wc -l) - 1 )))}); N=${#G[@]}; NC=$(nproc); SW=$(( NC / (N + 1) - 2 )); [ $SW -lt 1 ] && SW=1
ARGS=${ARGS:-"--today --real av2 kitti"}; SEEDS=${SEEDS:-"60 61 62"}
budget=$(( LIMIT - (SECONDS - T0) - 90 ))
log "$N GPUs, $NC cores: $N shards, $SW simulation workers each, budget $budget s; seeds $SEEDS; $ARGS"
for k in $(seq 0 $((N - 1))); do
  CUDA_VISIBLE_DEVICES=${G[$k]} timeout $((budget + 60)) python3 bench/accurate_map.py --device cuda --seeds $SEEDS $ARGS \
    --shard $k/$N --sim-workers $SW --budget $budget --cache $C --json /tmp/map_shard$k.json > /tmp/map_shard$k.log 2>&1 &
done
wait
for k in $(seq 0 $((N - 1))); do echo "== shard $k/$N"; tail -4 /tmp/map_shard$k.log; done > $OUT/shards.log
cat /tmp/map_shard*.log | grep -E 'Traceback|Error' | head -5 | tee -a $S
CUDA_VISIBLE_DEVICES=${G[0]} timeout 120 python3 bench/accurate_map.py --device cuda --seeds $SEEDS $ARGS --cached-only \
  --cache $C --json $OUT/accurate_map.json --md $OUT/accurate_map.md > $OUT/accurate_map.log 2>&1
log "report rc=$?: $(grep -c '' $OUT/accurate_map.md 2>/dev/null) lines"
tail -3 $OUT/accurate_map.log | tee -a $S
