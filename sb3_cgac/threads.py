"""
A short spin for torch's OpenMP threads, so that they sleep while a simulator's own threads (envpool) step the envs.

After each parallel region libgomp's workers spin for several milliseconds by default, taking the cores from the
simulator; a short spin keeps them awake between the ops of an update but asleep during env steps, at the same update
speed (docs/throughput.md has the measurements). libgomp reads the setting once, when torch is loaded, so it only
applies if this module runs before ``import torch``; a user's own ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` wins.
"""

import os
import sys

THREAD_SPIN_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
SHORT_SPIN_COUNT = "10000"


def configure_thread_spin() -> bool:
    """
    Set ``GOMP_SPINCOUNT`` unless the user set a spin policy.

    :return: Whether torch's threads follow a chosen spin policy: False when torch was loaded before this call
        without one (then it is too late to change it)
    """
    user_configured = any(name in os.environ for name in THREAD_SPIN_SETTINGS)
    if not user_configured:
        os.environ["GOMP_SPINCOUNT"] = SHORT_SPIN_COUNT
    return user_configured or "torch" not in sys.modules


# Runs on the first import of sb3_cgac (its __init__ imports this module before torch)
THREAD_SPIN_CONFIGURED = configure_thread_spin()
