import pytest

from bench.expert_table import markdown
from envs import suite as suite_module
from envs.suite import generate_tasks
from schemas.config import ConfigError, TasksConfig
from schemas.experts import ExpertRow, ExpertTable, load_expert_table, save_expert_table


def _row(task_id: str, successes: int, command: str = "sim2act tasks experts") -> ExpertRow:
    return ExpertRow(task_id=task_id, family="robosuite", split="seen", episodes=10, successes=successes,
                     mean_length=40, noise=0.1, randomised=True, command=command, measured_on="2026-11-22")


def test_a_partial_run_replaces_only_its_rows_and_the_table_names_every_command(tmp_path):
    record = tmp_path / "experts.json"
    save_expert_table(ExpertTable().merged([_row("good", 10), _row("weak", 7)]), record)
    table = load_expert_table(record).merged([_row("weak", 9, command="sim2act tasks experts --task weak")])
    assert table.rows["good"].successes == 10 and table.rows["weak"].successes == 9
    save_expert_table(table.merged([_row("worse", 8)]), record)
    text = markdown(load_expert_table(record), ["weak", "good", "worse"], "experts.json")
    assert "`sim2act tasks experts --task weak`" in text and "`sim2act tasks experts` on 2026-11-22" in text
    assert "1 of 3 tasks are below" in text
    lines = [line for line in text.splitlines() if line.startswith("| ") and "task |" not in line]
    assert [line.split(" | ")[0] for line in lines] == ["| weak", "| good", "| worse"]  # suite order
    assert lines[2].endswith("| 80% | 10 | 40 | below target |")


def test_campaigns_leave_out_tasks_whose_expert_is_below_target(monkeypatch):
    flagged = ExpertTable().merged([_row("lift-green", 6)])
    monkeypatch.setattr(suite_module, "load_expert_table", lambda: flagged)
    config = TasksConfig(specs=["lift"], colours=["red", "green", "blue"], max_tasks_per_spec=2)
    assert [t.task_id for t in generate_tasks(config, 0)] == ["lift-red", "lift-blue"]  # still two
    kept = config.model_copy(update={"weak_experts": "keep"})
    assert [t.task_id for t in generate_tasks(kept, 0)] == ["lift-red", "lift-green"]
    with pytest.raises(ConfigError, match="'lift-green' has a scripted expert below target"):
        generate_tasks(config.model_copy(update={"include": ["lift-green"]}), 0)
