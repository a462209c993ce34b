"""The README's set-up commands are the ones CI runs."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).parents[1]


def readme_commands() -> list[str]:
    """The lines of the README's bash blocks, in order."""
    blocks = re.findall(r"```bash\n(.*?)\n```", (ROOT / "README.md").read_text(), flags=re.DOTALL)
    return [line for block in blocks for line in block.splitlines()]


def test_readme_starts_with_the_two_setup_commands():
    text = (ROOT / "README.md").read_text()
    commands = readme_commands()
    first_block = text.index("```")
    assert text[:first_block].count("\n") < 6, "the set-up commands must come first"
    train, test = commands[0], commands[1]
    for command in (train, test):
        assert "pip install torch==2.13.0" in command and command.startswith("python3 -m venv")
    script = re.search(r"python (\S+\.py)", train)
    assert script is not None and (ROOT / script.group(1)).exists()


def test_ci_runs_the_readme_commands():
    ci = (ROOT / ".ci" / "run").read_text()
    for name, command in zip(("TRAIN_COMMAND", "TEST_COMMAND"), readme_commands()[:2], strict=True):
        match = re.search(rf"^{name}='(.*)'$", ci, flags=re.MULTILINE)
        assert match is not None, name
        assert match.group(1) == command


@pytest.mark.parametrize("name", ["myosuite", "mjlab"])
def test_ci_runs_the_readme_own_environment_commands(name):
    """The extras that pin their own dependencies: a venv, a command and a test file each."""
    ci = (ROOT / ".ci" / "run").read_text()
    commands = [command for command in readme_commands() if f".venv-{name} " in command]
    assert len(commands) == 1 and f"tests/test_{name}.py" in commands[0]
    match = re.search(rf"^{name.upper()}_COMMAND='(.*)'$", ci, flags=re.MULTILINE)
    assert match is not None and match.group(1) == commands[0]
