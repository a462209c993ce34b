import os
import sys

# After each parallel region, torch's OpenMP (libgomp) workers spin for about 300k iterations, several ms,
# taking the cores from a simulator's own threads (envpool) while it steps. A short spin keeps them awake
# between the ops of an update but asleep during env steps. Measured on 2 cores (benchmarks/throughput.py,
# tests/test_learning.py): CGAC's collection at 256 envpool HalfCheetah envs went from 56-64% to 66-102% (median
# 82%) of envpool's own speed, with the same update speed; OMP_WAIT_POLICY=PASSIVE collected as fast but made
# small-network training twice as slow.
# libgomp reads the setting once, when torch is loaded: it only applies if sb3_cgac is imported first, and never
# overrides a user's own OMP_WAIT_POLICY or GOMP_SPINCOUNT.
THREAD_SPIN_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
THREAD_SPIN_CONFIGURED = "torch" not in sys.modules or any(name in os.environ for name in THREAD_SPIN_SETTINGS)
if not any(name in os.environ for name in THREAD_SPIN_SETTINGS):
    os.environ["GOMP_SPINCOUNT"] = "10000"

from sb3_cgac.cgac import CGAC  # noqa: E402
from sb3_cgac.policies import MlpPolicy, MultiInputPolicy  # noqa: E402

# Read version from file
version_file = os.path.join(os.path.dirname(__file__), "version.txt")
with open(version_file) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = ["CGAC", "MlpPolicy", "MultiInputPolicy", "__version__"]
