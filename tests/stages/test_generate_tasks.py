import pytest

from envs.suite import generate_tasks, short_horizons, subtask_instructions
from schemas.config import ConfigError, TasksConfig
from schemas.task_spec import load_specs, parse_spec_file


def test_the_suite_has_over_100_tasks_in_three_families_each_said_three_ways():
    suite = load_specs()
    tasks = generate_tasks(TasksConfig(specs=list(suite), weak_experts="keep"), seed=0)
    by_family = {}
    for task in tasks:
        by_family[task.family] = by_family.get(task.family, 0) + 1
        assert len(set(task.instructions)) >= 3
        for colour in task.object_colours.values():
            assert all(colour in text for text in task.instructions)
    assert len({t.task_id for t in tasks}) == len(tasks) >= 100
    # robosuite: lift, stack, four PickPlace objects, square nut, round nut, both nuts, door
    assert by_family == {"robosuite": 6 + 30 + 4 + 6 + 6 + 12 + 6, "metaworld": 50, "navigation": 6 + 6 + 6 + 30}


def test_colour_bindings_come_from_the_environment_roles():
    tasks = generate_tasks(TasksConfig(specs=["lift", "stack"], colours=["red", "green", "blue"], weak_experts="keep"), seed=0)
    ids = [t.task_id for t in tasks]
    assert "lift-red" in ids and "stack-red-green" in ids and "stack-red-red" not in ids
    assert len(tasks) == 3 + 6  # 3 colours for Lift's one cube; ordered pairs for Stack's two


def test_generation_is_deterministic_for_a_seed():
    config = TasksConfig(specs=["stack"], colours=["red", "green", "blue", "yellow"], paraphrases=3)
    assert generate_tasks(config, 3) == generate_tasks(config, 3)
    variants = {tuple(t.instructions) for seed in range(8) for t in generate_tasks(config, seed)[:1]}
    assert len(variants) > 1  # the seed picks which paraphrases


def test_splits_hold_out_colours_and_whole_tasks():
    tasks = generate_tasks(TasksConfig(specs=["lift"], colours=["red", "blue", "orange"], unseen_colours=["blue"]), 0)
    assert {t.task_id: t.split for t in tasks} == {"lift-red": "seen", "lift-blue": "unseen", "lift-orange": "unseen"}
    metaworld = {t.task_id: t.split for t in generate_tasks(TasksConfig(specs=["mw-push-back", "mw-push"], weak_experts="keep"), 0)}
    assert metaworld == {"mw-push-back": "unseen", "mw-push": "seen"}


def test_held_out_paraphrases_are_kept_apart_from_the_ones_explored():
    tasks = generate_tasks(TasksConfig(specs=["lift", "nav-room"], colours=["red"]), 0)
    for task in tasks:
        assert task.unseen_instructions and not set(task.unseen_instructions) & set(task.instructions)
        assert task.object_colours.popitem()[1] in task.unseen_instructions[0]


SPEC = """
defaults: {family: robosuite, expert: pick_place, horizon: 50}
specs:
  - name: my-lift
    env: Lift
    objects: {target: {colours: [red, purple]}}
    templates: ["lift the {target} one", "raise the {target} cube", "pick up the {target} block"]
"""


def test_a_user_adds_tasks_by_writing_a_file(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(SPEC)
    tasks = generate_tasks(TasksConfig(specs=["my-lift"], spec_files=[path]), 0)
    assert [t.task_id for t in tasks] == ["my-lift-red", "my-lift-purple"]
    assert tasks[0].instruction == "lift the red one" and tasks[0].horizon == 50


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (("env: Lift", "env: Lifft"), "my-lift.env: unknown robosuite environment 'Lifft'"),
        (("{target: {colours", "{cube: {colours"), "template 'lift the {target} one' names ['target']"),
        (("expert: pick_place", "expert: metaworld_policy"), "my-lift.expert: metaworld_policy does not drive"),
        (("expert: pick_place", "expert: open_door"), "my-lift.expert: Lift is solved by pick_place, not open_door"),
        (("horizon: 50", "horizon: -5"), "specs.0.horizon: Input should be greater than 0"),
        (("colours: [red, purple]", "colours: [red, mauve]"), "specs.0.objects.target.colours.1"),
        (('"raise the {target} cube", ', ""), "specs.0.templates: List should have at least 3 items"),
        (("env: Lift", 'env: Lift\n    split: {unseen_templates: ["lift the {target} one"]}'),
         "'lift the {target} one' is both seen and held out"),
        (("env: Lift", 'env: Lift\n    split: {unseen_templates: ["hoist the {colour} one"]}'),
         "template 'hoist the {colour} one' names ['colour']"),
        (('"raise the {target} cube"', '"raise the cube"'), "template 'raise the cube' does not name ['target']"),
        (('"raise the {target} cube"', '"raise the {} cube"'), "template 'raise the {} cube' has a positional field"),
        (("env: Lift", "env: Lift\n    subtasks: [{spec: lift, objects: {target: cube}}]"),
         "subtasks: lift takes the colour of ['cube'], which are not in objects"),
        (("env: Lift", "env: Lift\n    subtasks: [{spec: lifft, objects: {target: target}}]"),
         "my-lift.subtasks: unknown spec 'lifft'"),
        (("env: Lift", "env: Lift\n    subtasks: [{spec: stack, objects: {pick: target}}]"),
         "my-lift.subtasks: stack has roles ['pick', 'place'], the sub-task binds ['pick']"),
        (("env: Lift", "env: Lift\n    subtasks: [{spec: lift, objects: {target: target}}]"),
         "my-lift.subtasks: robosuite environments do not report which goal is being pursued"),
    ],
)
def test_a_broken_spec_is_refused_with_the_field_and_reason(tmp_path, change, words):
    path = tmp_path / "broken.yaml"
    path.write_text(SPEC.replace(*change))
    with pytest.raises(ConfigError) as error:
        generate_tasks(TasksConfig(specs=["my-lift"], spec_files=[path]), 0)
    assert words in str(error.value) and str(path) in str(error.value)


def test_a_long_horizon_task_names_its_subtasks_in_its_own_colours():
    suite = load_specs()
    tasks = {t.task_id: t for t in generate_tasks(TasksConfig(specs=["nav-room-sequence", "lift"], colours=["red", "blue"]), 0)}
    assert subtask_instructions(tasks["nav-room-sequence-blue-red"], suite) == ["go to the blue room", "go to the red room"]
    assert subtask_instructions(tasks["lift-red"], suite) == []


def test_spec_names_are_unique():
    with pytest.raises(ConfigError, match="appears twice"):
        parse_spec_file(SPEC + SPEC.split("specs:")[1], "twice.yaml")


def test_a_horizon_shorter_than_the_experts_episodes_is_said_per_spec():
    config = TasksConfig(specs=["lift", "mw-reach"], colours=["red"], horizon={"lift": 20, "mw-reach": 500})
    line = short_horizons(config, generate_tasks(config, 0))
    assert "lift 20 < " in line and "mw-reach" not in line  # Lift's expert takes ~44 steps; 500 is past mw-reach's
    assert short_horizons(TasksConfig(specs=["lift"]), generate_tasks(TasksConfig(specs=["lift"]), 0)) == ""
