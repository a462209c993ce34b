#!/usr/bin/env bash
# The CUDA checks, for a machine with an NVIDIA GPU (CI has none): the CUDA tests, the update benchmark on the GPU,
# end-to-end steps/s with and without CUDA graphs, then the whole default test suite with every model on the GPU
# (device "auto"). Each part has its own time limit and a log in OUT_DIR; a failing part does not stop the others.
# The limits fit an H200 with 16 cores and pytest-xdist (about 10 minutes in all): scale them with
# CUDA_CHECK_TIME_SCALE=4 on a machine without pytest-xdist.
#   pip install -e ".[tests]" && bash benchmarks/cuda.sh [OUT_DIR]
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-cuda-results}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
python=${PYTHON:-python3}
# pytest-xdist, where installed, spreads the tests over processes (they share the GPU)
workers() { "$python" -c "import xdist" 2>/dev/null && echo "-n $1"; }

part() {  # part NAME SECONDS COMMAND...: run COMMAND with a time limit, its output to the screen and OUT_DIR/NAME
    local name=$1 seconds=$(($2 * ${CUDA_CHECK_TIME_SCALE:-1}))
    shift 2
    echo "=== $name (limit ${seconds}s): $*"
    local start=$SECONDS
    timeout "$seconds" "$@" 2>&1 | tee "$out/$name"
    echo "=== $name: exit ${PIPESTATUS[0]} after $((SECONDS - start))s"
}

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader; lscpu | grep "Model name"; nproc
  "$python" -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"; } 2>&1 | tee "$out/machine.txt"
part pytest-cuda.log 100 "$python" -m pytest -p no:cacheprovider -v -rs $(workers 8) tests/test_cuda_graphs.py tests/test_run.py::test_cuda \
    tests/test_learning.py::test_pendulum_entry_cuda_graphs tests/test_learning.py::test_pendulum_entry_reaches_minus_200
part updates.md 130 "$python" benchmarks/updates.py --device cuda --rounds 3 --chunk 0.25 \
    --paths default cuda-graphs bf16 bf16+cuda-graphs
part e2e.md 50 "$python" benchmarks/cuda_e2e.py --seconds 5
# The CUDA graph tests ran above; here each worker process runs many tests, and a failed capture would leave the
# process's CUDA random number generator unusable for the tests after it
part pytest-all.log 130 "$python" -m pytest -p no:cacheprovider -v $(workers 12) --durations 12 -k "not cuda_graphs" tests
