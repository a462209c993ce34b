"""experiments/action_noise.py: the reward left by Gaussian actions around the zero action, per step or per episode."""

from action_noise import main  # experiments/ is on sys.path (conftest.py)


def test_action_noise_episode_returns(capsys):
    # Pendulum-v1's episodes are truncated at 200 steps: 4 episodes of 2 envs end together, twice; the zero action
    # (no torque) scores a negative return, and noisy actions a different one
    main(["--env", "Pendulum-v1", "--backend", "dummy", "--n-envs", "2", "--stds", "0", "0.5", "--episodes", "4"])
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()[2:]]
    assert [row[:2] for row in rows] == [["| 0.0", "4"], ["| 0.5", "4"]]
    assert [row[3] for row in rows] == ["200", "200"]
    zero, noisy = (float(row[2].split()[0]) for row in rows)
    assert zero < 0 and noisy != zero


def test_action_noise_per_step(capsys):
    main(["--env", "Pendulum-v1", "--backend", "dummy", "--n-envs", "2", "--stds", "0", "--steps", "10"])
    row = capsys.readouterr().out.splitlines()[2].split(" | ")
    assert row[0] == "| 0.0" and float(row[1]) < 0 and row[3] == "0"
