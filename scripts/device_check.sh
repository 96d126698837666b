#!/usr/bin/env bash
# The checks that need a CUDA device, as one command for a lent GPU machine (docs/cuda.md):
# the CUDA tests (tests/test_cuda.py), then benchmarks/kernels_cuda.py's default UV fit and
# its query and training sections; TEST_S, FIT_S, BENCH_S limit each (seconds, 0 skips).
# Runs under the machine's own python3 and torch; the packages its image lacks (trimesh,
# libigl, faiss-cpu) travel as wheels in .whl/ (docs/cuda.md says how to fetch them).
# Writes logs, JUnit XML and the benchmark JSON/Markdown to $1 (or $OUT).
set -u
out=${1:-${OUT:?give an output folder}}
mkdir -p "$out"
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/hktex_site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/hktex_site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.mem \
  --format=csv >"$out/nvidia_smi.txt" 2>&1
python3 -c "import torch, numpy, scipy; print('torch', torch.__version__, 'numpy', \
numpy.__version__, 'scipy', scipy.__version__, torch.cuda.get_device_name(0))"

step() {  # step SECONDS NAME COMMAND...: run with a limit (0 skips), log to $out/NAME.log
  local limit=$1 name=$2
  shift 2
  [ "$limit" -gt 0 ] || return 0
  echo "== $name ($(date -u +%T))"
  timeout "$limit" "$@" >"$out/$name.log" 2>&1
  echo "== $name rc=$? ($(date -u +%T))"
  tail -n 12 "$out/$name.log"
}
step "${TEST_S:-240}" test_cuda python3 -m pytest -p no:cacheprovider -o addopts= \
  tests/test_cuda.py --junitxml="$out/test_cuda.xml" -q -rs
step "${FIT_S:-360}" fit python3 benchmarks/kernels_cuda.py --sections fit \
  --name kernels_cuda_fit --out "$out"
step "${BENCH_S:-200}" bench python3 benchmarks/kernels_cuda.py --sections query,train \
  --out "$out"
