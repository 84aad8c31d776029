"""`sim2act bench rl` trains a real SB3 agent briefly in a worker and reports its step's cost."""

import tempfile

from flows.cli import main


def test_bench_rl_times_an_agents_step_with_its_updates(tmp_path, monkeypatch, capsys):
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # this process's and a forked worker's
    monkeypatch.setenv("TMPDIR", str(temp))  # a spawned worker's
    out = tmp_path / "bench-rl.md"
    args = ["bench", "rl", "--preset", "smoke", "--agent", "ppo", "--steps", "64",
            "--workspace", str(tmp_path / "none"), "--out", str(out)]
    assert main(args) == 0
    table = out.read_text()
    [row] = [line.split(" | ") for line in table.splitlines() if line.startswith("| ppo")]
    env_ms, training_ms = float(row[3]), float(row[4])
    assert 0 < env_ms < training_ms  # a training step is the environment's step and its share of an update
    assert row[7] == "–"  # no workspace explored the campaign: no budget to price
    assert "`sim2act bench rl --preset smoke" in table and not (tmp_path / "none").exists()
    assert not list(temp.glob("SB3-*"))  # SB3's default logger would leave a folder per learn() in /tmp


def test_bench_rl_refuses_bad_input_before_any_work(capsys):
    assert main(["bench", "rl", "--preset", "smoke", "--steps", "0"]) == 2
    assert "--steps must be at least 1" in capsys.readouterr().err
    assert main(["bench", "rl", "--preset", "smoke", "--set", "baselines.agents=[expert]"]) == 2
    assert "expected an RL agent" in capsys.readouterr().err
