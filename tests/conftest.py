"""Settings shared by the whole test session."""

import os
import pathlib
import sys

import pytest

# The experiment drivers live outside the installed package: tests import them from experiments/
sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))


@pytest.fixture(autouse=True, scope="session")
def sb3_log_folder(tmp_path_factory: pytest.TempPathFactory) -> None:
    # SB3's configure() makes an empty /tmp/SB3-<timestamp> folder for every learn() without a log folder; one folder
    # of the session's own instead (subprocesses inherit it), so that a long-lived machine is not filled with them
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3-logs")))
