"""
sb3_cgac: CGAC for Stable-Baselines3. Importing the package loads nothing else (``CGAC`` and the policies load on
first use), so that ``sb3_cgac.threads.configure_thread_spin()`` can still run before torch is loaded.
"""

import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sb3_cgac.cgac import CGAC
    from sb3_cgac.policies import MlpPolicy, MultiInputPolicy

# Read version from file
version_file = os.path.join(os.path.dirname(__file__), "version.txt")
with open(version_file) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = ["CGAC", "MlpPolicy", "MultiInputPolicy", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "CGAC":
        from sb3_cgac.cgac import CGAC

        return CGAC
    if name in ("MlpPolicy", "MultiInputPolicy"):
        from sb3_cgac import policies

        return getattr(policies, name)
    raise AttributeError(f"module 'sb3_cgac' has no attribute {name!r}")
