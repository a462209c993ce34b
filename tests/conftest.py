"""Settings shared by the whole test session."""

import os
import pathlib
import sys

import pytest

# The experiment drivers live outside the installed package: tests import them from experiments/
sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))

# Under pytest-xdist (the README's `-n 2`) each worker gets its share of the cores: torch's default of one thread per
# core in every worker, and libgomp's threads spinning between ops, would make the workers fight over the same cores
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    from sb3_cgac.threads import configure_thread_spin

    configure_thread_spin()  # before torch is loaded
    _share = str(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    os.environ.setdefault("OMP_NUM_THREADS", _share)  # read when torch loads, here and in the tests' subprocesses


@pytest.fixture(autouse=True, scope="session")
def sb3_log_folder(tmp_path_factory: pytest.TempPathFactory) -> None:
    # SB3's configure() makes an empty /tmp/SB3-<timestamp> folder for every learn() without a log folder; one folder
    # of the session's own instead (subprocesses inherit it), so that a long-lived machine is not filled with them
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3-logs")))
