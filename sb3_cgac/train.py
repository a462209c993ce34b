"""
Train with rl-baselines3-zoo's own trainer, CGAC included (extra ``zoo``)::

    python -m sb3_cgac.train --algo cgac --env HalfCheetah-v5 --vec-env envpool --seed 0 --eval-freq 20000 -P

Every rl_zoo3 flag keeps working (``python -m rl_zoo3.train --help`` lists them). ``--algo cgac``, ``ppo`` and
``sac`` read this package's ``hyperparams/*.yml`` unless ``-conf`` names another file, and ``--vec-env`` also
accepts ``envpool``, ``gymnasium`` and ``gymnasium_async``.
"""

from sb3_cgac.threads import configure_thread_spin

if __name__ == "__main__":
    configure_thread_spin()  # before sb3_cgac.zoo loads torch

from sb3_cgac.zoo import train

if __name__ == "__main__":
    train()
