"""
The timing helpers of the benchmarks: candidates take turns in short chunks, so that this machine's speed drift
(+-20% within seconds) hits all of them alike, and the machine is described the same way in every table.
"""

import functools
import os
import platform
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any


def take_turns(
    work: Mapping[str, Callable[[], float]], chunk: float, rounds: int | None = None, seconds: float | None = None
) -> dict[str, list[tuple[float, float]]]:
    """
    Run each candidate's ``work`` for about ``chunk`` seconds (as many calls as fit, at least one), one candidate after
    the other, for ``rounds`` turns each or until every candidate has run ``seconds`` in all.

    :param work: Candidate name -> a function that does some work and returns how many units it did
    :return: Candidate name -> (units, seconds) of each of its turns
    """
    if (rounds is None) == (seconds is None):
        raise ValueError("take_turns: give either rounds or seconds")
    turns: dict[str, list[tuple[float, float]]] = {name: [] for name in work}

    def done() -> bool:
        if rounds is not None:
            return all(len(candidate) >= rounds for candidate in turns.values())
        return all(sum(elapsed for _, elapsed in candidate) >= seconds for candidate in turns.values())  # type: ignore[operator]

    while not done():
        for name, function in work.items():
            units, start = 0.0, time.perf_counter()
            while True:
                units += function()
                elapsed = time.perf_counter() - start
                if elapsed >= chunk:
                    break
            turns[name].append((units, elapsed))
    return turns


def rate(turns: list[tuple[float, float]]) -> float:
    """Units per second over all turns."""
    return sum(units for units, _ in turns) / sum(elapsed for _, elapsed in turns)


def machine(threads: int, device: str = "cpu") -> str:
    """One line: CPU, cores, the instruction sets that matter for float32 and bfloat16 matmuls, torch, threads."""
    import torch as th

    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    isa = [name for name in ("avx512f", "avx512_bf16", "amx_bf16") if f" {name}" in flags]
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores ({', '.join(isa) or 'no AVX-512'}), "
        f"torch {th.__version__}, {threads} torch threads, device {device}"
    )


class PhaseTimer:
    """
    Wall-clock spent inside the functions it wraps, with the CUDA device (if any) synchronised before and after each
    call, so that kernels queued by other code count where they run: a split of a run's time, not a rate.
    """

    def __init__(self) -> None:
        self.seconds = 0.0

    def wrap(self, function: Callable) -> Callable:
        import torch as th

        synchronize = th.cuda.synchronize if th.cuda.is_available() else lambda: None

        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            synchronize()
            start = time.perf_counter()
            result = function(*args, **kwargs)
            synchronize()
            self.seconds += time.perf_counter() - start
            return result

        return timed
