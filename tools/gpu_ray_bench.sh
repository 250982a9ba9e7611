#!/usr/bin/env bash
# One device call (kind nvidia-h100-x2): issue 32's dataset bench on 2 GPUs at a real split's size,
# the Ray cluster started before the jobs (as on a real cluster). Ray is not on the device image:
# .whl/ holds the stripped Ray wheel and its pure-Python dependencies (tools/strip_ray_wheel.py),
# carried with the call. Logs and JSON under $OUT.   OUT=... LIMIT=590 tools/gpu_ray_bench.sh
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 TORCH_CUDA_ARCH_LIST=9.0
T0=$SECONDS; S=$OUT/summary.log
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site
nvidia-smi -L | tee $S; df -h /tmp /dev/shm | tee -a $S
# outputs of a 120 x 150-frame dataset are ~80 GB: in RAM when /dev/shm can hold them (every row writes there, the long sequence too)
shm=$(df -BG --output=avail /dev/shm | tail -1 | tr -dc 0-9); [ "${shm:-0}" -gt 100 ] && export TMPDIR=/dev/shm; echo "TMPDIR=${TMPDIR:-/tmp}" | tee -a $S
tools/gpu_run.sh build > /dev/null 2>&1; tail -3 $S
echo "build done at $((SECONDS-T0)) s" | tee -a $S
python3 -m ray.scripts.scripts start --head --num-gpus 2 --num-cpus 32 --include-dashboard=false > $OUT/ray_start.log 2>&1
echo "ray start rc=$? at $((SECONDS-T0)) s" | tee -a $S
t=$((${LIMIT:-585} - (SECONDS - T0)))
timeout $t python3 bench/bench_ray.py --device cuda --gpus 1 2 --modes long ray --sequences ${SEQS:-120} --ray-address auto \
  --json $OUT/bench_ray.json > $OUT/bench_ray.log 2>&1
echo "ray bench rc=$? at $((SECONDS-T0)) s" | tee -a $S; tail -12 $OUT/bench_ray.log
python3 -m ray.scripts.scripts stop > /dev/null 2>&1
