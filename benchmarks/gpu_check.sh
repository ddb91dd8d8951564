#!/usr/bin/env bash
# The GPU checks, for a machine with an NVIDIA GPU and CuPy: the `gpu` tests (the CPU tests'
# cases on CuPy) and the GPU benchmark rows beside the same engine on that machine's CPU.
# Usage: benchmarks/gpu_check.sh [OUT_DIR] [bench_gpu options]   (rows in OUT_DIR/gpu_rows.json, log in
# OUT_DIR/gpu_check.log). Options after OUT_DIR go to benchmarks/bench_gpu.py, e.g. the tolerance row alone
# on fewer samples (about 2 minutes): benchmarks/gpu_check.sh OUT --rows tolerance --tolerance-samples 200;
# the paper setting (about 80 s): benchmarks/gpu_check.sh OUT --rows paper
# Missing Python packages may be given as wheels in .whl/ (installed to /tmp/site, no network needed);
# the project itself runs from this checkout (PYTHONPATH), so nothing is built.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-benchmarks/results}
mkdir -p "$out"
py=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD:$PYTHONPATH PYTHONUNBUFFERED=1
{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  "$py" -c "import cupy, numpy; print('cupy', cupy.__version__, 'numpy', numpy.__version__)"
  "$py" -m pytest -q -p no:cacheprovider -m gpu tests/doedesign/test_backend.py tests/masks/test_tolerance_device.py
  "$py" -m benchmarks.bench_gpu --out "$out/gpu_rows.json" "${@:2}"
} 2>&1 | tee "$out/gpu_check.log"
