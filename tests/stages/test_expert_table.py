from schemas.config import RandomiseConfig, TasksConfig
from stages.expert_table import ExpertRow, markdown, measure_experts
from stages.generate_tasks import generate_tasks


def test_experts_are_measured_per_task_in_worker_processes():
    tasks = generate_tasks(TasksConfig(specs=["lift", "mw-reach"], colours=["red"]), seed=0)
    rows = measure_experts(tasks, episodes=2, noise=0.1, randomise=RandomiseConfig(), workers=2)
    assert [r.task_id for r in rows] == ["lift-red", "mw-reach"]
    assert all(r.episodes == 2 and r.successes == 2 and 0 < r.mean_length < 80 for r in rows)


def test_the_table_flags_tasks_below_target():
    rows = [
        ExpertRow(task_id="good", family="robosuite", split="seen", episodes=10, successes=10, mean_length=40),
        ExpertRow(task_id="weak", family="metaworld", split="seen", episodes=10, successes=7, mean_length=150),
    ]
    text = markdown(rows, "sim2act tasks experts", 0.1, randomised=True)
    assert "1 of 2 tasks are below" in text and "`sim2act tasks experts`" in text
    assert "| weak | metaworld | seen | 70% | 10 | 150 | below target |" in text
    assert "| good | robosuite | seen | 100% | 10 | 40 |  |" in text
