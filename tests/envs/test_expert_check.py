"""The scripted experts measured in worker processes; a campaign's own randomisation measured only where an
expert can feel it."""

from envs.expert_check import felt_apart, measure_experts, said
from envs.suite import generate_tasks
from schemas.config import RandomiseConfig, TasksConfig


def test_experts_are_measured_per_task_in_worker_processes_under_randomisation():
    tasks = generate_tasks(TasksConfig(specs=["lift", "mw-reach"], colours=["red"]), seed=0)
    rows = measure_experts(tasks, episodes=2, noise=0.1, randomise=RandomiseConfig(), workers=2, command="test")
    assert [r.task_id for r in rows] == ["lift-red", "mw-reach"]
    assert all(r.episodes == 2 and r.successes == 2 and 0 < r.mean_length < 80 and r.randomised for r in rows)


def test_only_what_a_camera_less_expert_feels_calls_for_its_own_check():
    assert felt_apart(RandomiseConfig()) == {}  # the shipped table's conditions
    assert felt_apart(RandomiseConfig(light=(0.2, 2.0), tint=0.5, camera_shift_m=0.1, colour_jitter=0.1)) == {}
    apart = felt_apart(RandomiseConfig(mass=(100.0, 100.0), friction=(0.5, 1.0)))
    assert apart == {"mass": (100.0, 100.0), "friction": (0.5, 1.0)}
    assert said(apart) == "randomise.mass=[100.0, 100.0], randomise.friction=[0.5, 1.0]"
    assert felt_apart(RandomiseConfig(enabled=False, mass=(2.0, 2.0))) == {"enabled": False}  # nothing drawn at all
    assert said({"enabled": False}) == "randomise.enabled=false"
