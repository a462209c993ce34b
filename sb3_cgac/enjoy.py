"""
Replay a trained agent with rl-baselines3-zoo's ``enjoy``, CGAC included (extra ``zoo``)::

    python -m sb3_cgac.enjoy --algo cgac --env HalfCheetah-v5 -f logs --exp-id 1 -n 1000 --no-render

Models trained on envpool replay on the gymnasium env of the same id (the spaces match).
"""

from sb3_cgac.threads import configure_thread_spin

if __name__ == "__main__":
    configure_thread_spin()  # before sb3_cgac.zoo loads torch

from sb3_cgac.zoo import enjoy

if __name__ == "__main__":
    enjoy()
