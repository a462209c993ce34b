"""
A short spin for torch's OpenMP threads, so that they sleep while a simulator's own threads (envpool) step the envs.

After each parallel region libgomp's workers spin for several milliseconds by default, taking the cores from the
simulator; a short spin keeps them awake between the ops of an update but asleep during env steps, at the same update
speed (docs/performance.md has the measurements). libgomp reads the setting once, when torch is loaded, so
:func:`configure_thread_spin` only has an effect when it runs before ``import torch``:

.. code-block:: python

    from sb3_cgac.threads import configure_thread_spin

    configure_thread_spin()  # first, before anything imports torch
    from sb3_cgac import CGAC

This module imports nothing that loads torch. The command-line tools (``sb3_cgac.train``, ``sb3_cgac.compare``) call
it; a user's own ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` wins.
"""

import os
import sys

THREAD_SPIN_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
SHORT_SPIN_COUNT = "10000"


def configure_thread_spin() -> bool:
    """
    Set ``GOMP_SPINCOUNT`` for this process and its children, unless the user set a spin policy.

    :return: Whether torch's threads follow a chosen spin policy: False when torch was loaded before this call
        without one (then it is too late to change it)
    """
    if not thread_spin_configured() and "torch" not in sys.modules:
        os.environ["GOMP_SPINCOUNT"] = SHORT_SPIN_COUNT
    return thread_spin_configured()


def thread_spin_configured() -> bool:
    """Whether a spin policy is set in the environment (by the user or by :func:`configure_thread_spin`)."""
    return any(name in os.environ for name in THREAD_SPIN_SETTINGS)
