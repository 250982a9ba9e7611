#!/usr/bin/env bash
# In-place developer build: compiles _C into .devbuild/ and copies it next to the Python
# sources, so `PYTHONPATH=python pytest` works without reinstalling. Users should use the
# README's pip command instead.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
prefix=$($PY -c 'import torch; print(torch.utils.cmake_prefix_path)')
gen=()
command -v ninja >/dev/null && gen=(-G Ninja)
cmake -S . -B .devbuild "${gen[@]}" -DCMAKE_BUILD_TYPE=Release -DPython_EXECUTABLE="$(command -v $PY)" \
      -DCMAKE_PREFIX_PATH="$prefix" "$@" >/dev/null
cmake --build .devbuild -j "${JOBS:-2}"
cp .devbuild/_C*.so python/floxels_ext/
echo "built $(ls python/floxels_ext/_C*.so)"
