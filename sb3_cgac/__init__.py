import os

# First, before anything loads torch: torch's OpenMP threads must not spin while envpool steps (see threads.py)
from sb3_cgac import threads  # noqa: F401
from sb3_cgac.cgac import CGAC
from sb3_cgac.policies import MlpPolicy, MultiInputPolicy

# Read version from file
version_file = os.path.join(os.path.dirname(__file__), "version.txt")
with open(version_file) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = ["CGAC", "MlpPolicy", "MultiInputPolicy", "__version__"]
