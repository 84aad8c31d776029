from schemas.config import TasksConfig
from stages.generate_tasks import generate_tasks


def test_tasks_come_from_environment_metadata_with_paraphrases():
    tasks = generate_tasks(TasksConfig(envs=["Lift", "Stack"], colours=["red", "green", "blue"]), seed=0)
    ids = [t.task_id for t in tasks]
    assert "lift-red" in ids and "stack-red-green" in ids
    assert len(tasks) == 3 + 6  # 3 colours for Lift's one cube; ordered pairs for Stack's two
    for task in tasks:
        assert len(set(task.instructions)) >= 3
        for colour in task.object_colours.values():
            assert all(colour in text for text in task.instructions)


def test_generation_is_deterministic_for_a_seed():
    config = TasksConfig(envs=["Stack"], colours=["red", "green", "blue", "yellow"], paraphrases=3)
    assert generate_tasks(config, 3) == generate_tasks(config, 3)
    variants = {tuple(t.instructions) for seed in range(8) for t in generate_tasks(config, seed)[:1]}
    assert len(variants) > 1  # the seed picks which paraphrases


def test_unseen_colours_make_unseen_tasks():
    tasks = generate_tasks(TasksConfig(envs=["Lift"], colours=["red", "blue", "yellow"], unseen_colours=["yellow"]), 0)
    assert {t.task_id: t.split for t in tasks} == {"lift-red": "seen", "lift-blue": "seen", "lift-yellow": "unseen"}
