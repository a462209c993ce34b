#!/usr/bin/env bash
# The GPU-simulator benchmark, one command for one H100/H200 (at most about 8 minutes): MuJoCo Playground on MJX through
# sb3_cgac's torch-native path, raw simulator steps/s, CGAC's end-to-end steps/s at 1,024, 4,096 and 16,384 envs, and
# 3 minutes of learning of CGAC and of rsl_rl's PPO (benchmarks/gpu_playground.py). The table is OUT_DIR/table.md.
# The GPU machine reaches no registry: first download the wheels here (benchmarks/gpu_wheels.sh, 43 MB), then with the
# device tool: run(command="bash benchmarks/gpu.sh $OUT", carry=[".whl"], timeout_s=600).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-gpu-results}
shift || true
mkdir -p "$out"
python=${PYTHON:-python3}
if [ -d .whl ]; then
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1
# JAX takes 75% of the GPU's memory at its first use unless told not to: torch needs its share
export XLA_PYTHON_CLIENT_PREALLOCATE=false
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader; nproc
  "$python" -c "import torch, jax, mujoco; print('torch', torch.__version__, 'jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)"
} 2>&1 | tee "$out/machine.txt"
timeout 540 "$python" benchmarks/gpu_playground.py --out "$out" "$@" 2>&1 | tee "$out/log.txt"
echo "exit ${PIPESTATUS[0]}"
