#!/usr/bin/env bash
# Device calls of bench/compare.py at full scale (issue 20), each inside the 10-minute limit.
#   bench/compare_gpu.sh build|PART...   (from the repository root; OUT = output folder)
# build: CUDA build + baseline/solver tests + bench_baselines; the parts are listed below.
# A prebuilt _C*.so in python/floxels_ext (from an earlier build call) skips the build.
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/cmp_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0
T0=$SECONDS; LIMIT=${LIMIT:-570}
# a _C*.so carried in python/floxels_ext (from an earlier build call) is used without a build
if ls python/floxels_ext/_C*.so >/dev/null 2>&1; then export PYTHONPATH=$PWD/python; fi
left() { echo $((LIMIT - (SECONDS - T0))); }
cmp() {  # name, args...
  local name=$1; shift
  local t=$(left); [ "$t" -lt 20 ] && { echo "SKIPPED $name (no time left)"; return; }
  (cd bench && timeout "$t" python3 compare.py --device cuda --part "$name" --json "$OUT/$name.json" "$@" \
     > "$OUT/$name.log" 2>&1); echo "part $name rc=$? at $((SECONDS - T0)) s"; tail -n 25 "$OUT/$name.log"
}
for stage in "$@"; do
  case $stage in
    build)
      OUT=$OUT tools/gpu_run.sh build || exit 1
      so=$(python3 -c 'import floxels_ext,os,glob;print(glob.glob(os.path.dirname(floxels_ext.__file__)+"/_C*.so")[0])')
      cp "$so" "$OUT/" && cp "$so" python/floxels_ext/ && export PYTHONPATH=$PWD/python && rm -f "$OUT/build.log"
      timeout 150 python3 -m pytest -q tests/baselines/test_baselines.py tests/ops/test_solver.py > "$OUT/tests.log" 2>&1
      echo "tests rc=$?"; grep -E "passed|failed|^FAILED|^ERROR" "$OUT/tests.log" | tail -n 12
      (cd bench && timeout 90 python3 bench_baselines.py --device cuda --iters 200 --cdist-iters 10 \
         --json "$OUT/baselines.json" 2>&1 | tail -n 6) ;;
    main) cmp simA --methods floxels nsfp fastnsf --ablations none ;;
    readings) cmp simB --methods floxels2 nsfp_wd nsfp_lr8e-3 fastnsf_noes --ablations none --no-npz ;;
    av2b) cmp av2b --dataset av2 --av2 ../av2_pair.npz --methods nsfp_wd nsfp_lr8e-3 fastnsf_noes --ablations none --no-npz ;;
    ablations) cmp simC --methods --ablations loss scans voxel port ;;
    es) cmp simD --methods --ablations es ;;
    av2) cmp av2 --dataset av2 --av2 ../av2_pair.npz --methods floxels nsfp fastnsf --ablations loss port voxel ;;
    # issue 33: the accurate preset and its ingredients, simulator on held-out seeds, AV2 pair
    beyond) cmp beyond_sim --methods --ablations beyond beyond-only beyond-loo --seeds 10 11 12 ;;
    beyondav2) cmp beyond_av2 --dataset av2 --av2 "${AV2:-../av2_pair.npz}" --methods --ablations beyond beyond-only beyond-loo ;;
    simnew) (cp python/floxels_ext/_C*.so pynew/floxels_ext/ && export PYTHONPATH=$PWD/pynew
             cmp simnew --methods floxels nsfp fastnsf --ablations none) ;;
    *) echo "unknown stage $stage"; exit 2 ;;
  esac
done
