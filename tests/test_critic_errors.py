"""experiments/critic_errors.py: the critics' minibatch errors of a run, retraced from a YAML entry."""

from pathlib import Path

from critic_errors import main  # experiments/ is on sys.path (conftest.py)

CONF = Path(__file__).parents[1] / "docs/results/one-setting-screen/conf/cgac_one14.yml"


def test_critic_errors_rows(capsys):
    # 128 envs, batch 512: the updates start once the window holds 4 steps per env; a row for the updates of each
    # iteration from there, printed as the next one starts, until training stops at 768 steps
    main(["--conf", str(CONF), "--stop", "768", "--every", "1"])
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line[2:3].isdigit()]
    assert [row[0] for row in rows] == ["| 512", "| 640"]
    for row in rows:
        median, p90, p99, largest = (float(value) for value in row[1:5])
        assert 0.0 <= median <= p90 <= p99 <= largest
        assert all(0.0 <= float(share) <= 1.0 for share in row[9].split(" / "))
