"""
The callback that evaluates one (run, seed) pair of a comparison on its schedule and stops it at its budget. A module
of its own: it loads Stable-Baselines3 (and torch), which compare's main process does not load.
"""

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv, sync_envs_normalization

from sb3_cgac.compare.files import COLUMNS, record_train_stats, run_paths, train_stats_path, write_csv_atomically


class EvaluateWithinBudget(BaseCallback):
    """
    Evaluates the deterministic policy every ``args.eval_every`` (minutes, or a fraction of the steps), before training
    and at its end, writing the pair's evaluations and training statistics as it goes; stops training at the budget.
    The budget's clock stops during evaluations.

    :param args: The comparison's arguments (``sb3_cgac.compare.cli``) with the pair's run and seed
    :param eval_env: The evaluation envs (rank 0's)
    :param world_size: Ranks of data-parallel training: the budget and the CSVs count the env steps of all of them
    """

    def __init__(self, args: argparse.Namespace, eval_env: VecEnv, world_size: int = 1):
        super().__init__()
        self.args = args
        self.eval_env = eval_env
        self.world_size = world_size
        self.csv_path = run_paths(Path(args.out), args.run, args.seed)[0]
        self.rows: list[str] = []
        self.train_rows: list[dict[str, str]] = []
        self.seconds, self.resumed, self.next_evaluation = 0.0, 0.0, 0.0
        self.successes: list[bool] = []
        self.metrics: dict[str, list[float]] = {}

    def _on_training_start(self) -> None:
        self.seconds, self.resumed = 0.0, time.perf_counter()
        self.evaluate()

    def clock(self) -> float:
        """Training wall-clock so far, evaluations left out."""
        return self.seconds + time.perf_counter() - self.resumed

    def steps(self) -> int:
        return self.num_timesteps * self.world_size

    def record_episode(self, locals_: dict[str, Any], _globals: dict[str, Any]) -> None:
        """``evaluate_policy``'s callback: as SB3's EvalCallback records is_success, the info of each episode's last step."""
        if not locals_["done"]:
            return
        info = locals_["info"]
        if self.args.success_key:
            self.successes.append(bool(info.get(self.args.success_key, False)))
        for key in self.args.metrics:
            if key in info.get("episode", {}):
                self.metrics[key].append(float(info["episode"][key]))

    def evaluate(self) -> None:
        args = self.args
        self.seconds = self.clock()
        self.next_evaluation = (
            self.seconds + args.eval_every * 60 if args.minutes else self.steps() + args.eval_every * args.steps
        )
        sync_envs_normalization(self.training_env, self.eval_env)
        self.successes, self.metrics = [], {key: [] for key in args.metrics}
        returns, lengths = evaluate_policy(
            self.model,
            self.eval_env,
            n_eval_episodes=args.eval_episodes,
            deterministic=True,
            callback=self.record_episode,
            return_episode_rewards=True,
        )
        values = [args.run, str(args.seed), str(self.steps()), f"{self.seconds:.2f}"]
        values += [f"{np.mean(returns):.3f}", f"{np.mean(lengths):.1f}"]
        values += [f"{np.mean(self.successes) if self.successes else 0.0:.3f}"] if args.success_key else []
        values += [f"{np.mean(found):.6g}" if found else "" for found in self.metrics.values()]
        self.rows.append(",".join(values) + "\n")
        header = ",".join(COLUMNS + (["success_rate"] if args.success_key else []) + list(args.metrics))
        write_csv_atomically(self.csv_path, header + "\n" + "".join(self.rows))
        path = train_stats_path(Path(args.out), args.run, args.seed)
        logged, episodes = self.model.logger.name_to_value, self.model.ep_info_buffer or ()
        record_train_stats(path, self.train_rows, logged, self.steps(), self.seconds, episodes)
        self.resumed = time.perf_counter()

    def _on_step(self) -> bool:
        args = self.args
        if args.minutes and self.clock() >= args.minutes * 60:
            return False
        if args.steps and self.steps() >= args.steps:
            return True  # the step budget's last rollout: the end of training evaluates the final model
        if (self.clock() if args.minutes else self.steps()) >= self.next_evaluation:
            self.evaluate()
        return True

    def _on_training_end(self) -> None:
        self.evaluate()
