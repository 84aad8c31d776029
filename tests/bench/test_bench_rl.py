"""`sim2act bench rl` trains a real SB3 agent briefly in a worker and reports its step's cost."""

import tempfile

import numpy as np

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
    assert main(["bench", "rl", "--preset", "smoke", "--set", "baselines.agents=[sac]",
                 "--set", "baselines.families=[metaworld]"]) == 2  # the smoke campaign's tasks are robosuite's
    assert capsys.readouterr().err.rstrip().endswith("over ['robosuite'] (baselines.families: ['metaworld'])")


def test_sacs_encoders_side_by_side_and_in_the_agents_key(tmp_path):
    """`--sac-encoder critic --sac-encoder separate`: SAC once per encoder in one run, PPO once; the stage keys
    the critic's shared encoder apart, and SB3's layout keeps the key it had before the option."""
    from bench.rl import RLStepCost, rl_cases
    from envs.suite import generate_tasks
    from schemas.config import CampaignConfig, TasksConfig
    from schemas.workspace import Workspace
    from stages.baselines import rl_units

    # episodes ended at their first success, as the agents before baselines.end_on_success were trained
    config = CampaignConfig(name="t", tasks=TasksConfig(specs=["lift", "nav-room"], colours=["red", "green"]),
                            baselines={"agents": ["ppo", "sac"], "end_on_success": True})
    tasks = generate_tasks(config.tasks, config.seed)
    cases = rl_cases(config, tasks, 10, {}, ["critic", "separate"])
    assert [(c.algorithm, c.family, c.config.baselines.sac_encoder) for c in cases if c.algorithm == "sac"] == [
        ("sac", "robosuite", "critic"), ("sac", "robosuite", "separate")]
    assert [c.family for c in cases if c.algorithm == "ppo"] == ["navigation", "robosuite"]
    cost = RLStepCost(algorithm="sac", family="robosuite", tasks=2, steps=1, env_ms=1, cpu_ms=2, wall_ms=2, budget=None,
                      precision="fp32", sac_encoder="critic")
    assert cost.agent == "sac (critic encoder)"

    said = {text: np.zeros(4, dtype=np.float32) for t in tasks for text in t.instructions}

    def keys(encoder: str) -> dict[str, str]:
        variant = config.model_copy(update={"baselines": config.baselines.model_copy(update={"sac_encoder": encoder})})
        units = rl_units(Workspace.at(tmp_path), variant, "tasks", tasks, said, {"robosuite": 500, "navigation": 500})
        return {u.algorithm: u.unit_key for u in units if u.family == "robosuite"}

    critic, separate = keys("critic"), keys("separate")
    assert critic["ppo"] == separate["ppo"] and critic["sac"] != separate["sac"]
    assert separate["sac"] == "baselines-76879ac549ae2f08"  # SB3's layout: its key from before the option
