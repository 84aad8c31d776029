import re
import subprocess
from pathlib import Path

import pytest

from envs.suite import generate_tasks
from schemas.config import PRESETS, CampaignConfig, ConfigError, load_config
from schemas.keys import derive_seed, unit_key
from stages.explore import curriculum_subgoals
from tests.conftest import SIM2ACT


@pytest.mark.parametrize("preset", ["smoke", "default"])
def test_presets_validate(preset):
    config = load_config(preset)
    assert config.name == preset
    assert config.iterations >= 2


def test_file_and_overrides_stack_on_the_preset(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("explore: {episodes_per_task: 6}\n")
    config = load_config("smoke", path, {"iterations": 3})
    assert (config.explore.episodes_per_task, config.iterations) == (6, 3)
    assert config.explore.episodes_per_shard == load_config("smoke").explore.episodes_per_shard


@pytest.mark.parametrize(
    ("yaml_text", "field", "words"),
    [
        ("explore: {episods_per_task: 3}\n", "explore.episods_per_task", "unknown key"),
        ("train: {epochs: many}\n", "train.epochs", "valid integer"),
        ("explore: {episodes_per_task: -2}\n", "explore.episodes_per_task", "greater than 0"),
        ("tasks: {specs: [lift, juggle]}\n", "tasks.specs", "unknown spec 'juggle'"),
        ("tasks: {horizon: {stak: 10}}\n", "tasks.horizon", "not one of tasks.specs"),
        ("tasks: {include: [lift-magenta]}\n", "tasks.include", "unknown task 'lift-magenta'"),
        ("tasks: {specs: [lift, stack, lift]}\n", "tasks", "expected each spec once, got 'lift' 2 times"),
        ("- just a list\n", "", "mapping"),
    ],
)
def test_bad_config_is_refused_in_one_line_before_any_work(tmp_path, yaml_text, field, words):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml_text)
    workspace = tmp_path / "ws"
    result = subprocess.run(
        [SIM2ACT, "run", "--preset", "smoke", "--config", str(bad), "--workspace", str(workspace)],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert field in lines[0] and words in lines[0], lines[0]
    assert not workspace.exists()


def test_negative_iterations_on_the_command_line(tmp_path):
    result = subprocess.run(
        [SIM2ACT, "run", "--iterations", "-1", "--workspace", str(tmp_path / "ws")], capture_output=True, text=True
    )
    assert result.returncode == 2 and "iterations" in result.stderr
    assert not (tmp_path / "ws").exists()


def test_unit_keys_follow_what_the_unit_reads():
    config = CampaignConfig()
    key = unit_key("explore", 1, config.explore, ["task-a"])
    assert key == unit_key("explore", 1, CampaignConfig().explore, ["task-a"])
    assert key != unit_key("explore", 1, config.explore.model_copy(update={"expert_noise": 0.3}), ["task-a"])
    assert key != unit_key("explore", 2, config.explore, ["task-a"])
    assert key != unit_key("explore", 1, config.explore, ["task-b"])


def test_seeds_are_stable_and_distinct():
    assert derive_seed("c", 0, "lift-red", 0, 1) == derive_seed("c", 0, "lift-red", 0, 1)
    seeds = {derive_seed("c", 0, "lift-red", shard, episode) for shard in range(10) for episode in range(10)}
    assert len(seeds) == 100


def test_config_error_is_a_value_error():
    with pytest.raises(ConfigError, match="unknown preset"):
        load_config("huge")


def test_set_overrides_name_fields_by_path_and_are_validated_like_the_file():
    from schemas.config import parse_settings

    overrides = parse_settings(["train.contrastive_weight=0", "tasks.colours=[red, blue]", "train.model.vision=resnet18"])
    config = load_config("smoke", None, overrides)
    assert (config.train.contrastive_weight, config.tasks.colours, config.train.model.vision) == (0.0, ["red", "blue"], "resnet18")
    assert config.train.epochs == load_config("smoke").train.epochs  # the rest stays the preset's
    with pytest.raises(ConfigError, match=r"^train\.model\.vision: "):
        load_config("smoke", None, parse_settings(["train.model.vision=alexnet"]))
    with pytest.raises(ConfigError, match="is not FIELD.PATH=VALUE"):
        parse_settings(["contrastive_weight"])


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_loads_and_yields_its_tasks(preset):
    config = load_config(preset, None)
    tasks = generate_tasks(config.tasks, config.seed)
    assert tasks and any(t.split == "seen" for t in tasks)
    if config.explore.curriculum:  # a curriculum needs a long-horizon task whose sub-tasks it can chain
        assert curriculum_subgoals(config, tasks)


@pytest.mark.parametrize("path", sorted(Path(__file__).resolve().parents[2].glob("docs/quality/*.yaml")),
                         ids=lambda path: path.name)
def test_every_campaign_file_of_the_docs_loads_on_the_preset_its_commands_name(path):
    """docs/quality's files are run by the commands in their own comments: those must work."""
    presets = set(re.findall(r"--preset (\S+)", path.read_text()))
    assert len(presets) == 1, f"{path.name}: expected its commands to name one preset, got {presets}"
    preset = presets.pop()
    config = load_config(preset, path)
    assert generate_tasks(config.tasks, config.seed)
    # A file names its own campaign, or keeps its preset's name on purpose: then it explores and is evaluated on the
    # preset's very episodes, and changes one thing against it (hard-mix-epochs: the training budget).
    assert config.name in {path.stem, preset}, f"{path.name}: expected name {path.stem!r} or {preset!r}, got {config.name!r}"


@pytest.mark.parametrize("path", sorted(Path(__file__).resolve().parents[2].glob("docs/tasks/*.yaml")),
                         ids=lambda path: path.name)
def test_every_task_file_of_the_docs_is_valid(path, capsys):
    """docs/tasks's files are given to `sim2act eval --tasks` by the docs' commands: `tasks validate` accepts them."""
    from flows.cli import main

    assert main(["tasks", "validate", str(path)]) == 0
    assert capsys.readouterr().out.strip().endswith("valid")


def test_tasks_validate_counts_what_a_presets_campaign_would_bind(tmp_path, capsys):
    """The README's file names red and purple; the default preset binds red, green, blue and yellow only:
    `tasks validate` said 2 tasks where the campaign got 1."""
    from flows.cli import main

    spec = tmp_path / "my_tasks.yaml"
    spec.write_text("defaults: {family: robosuite, expert: pick_place, horizon: 80}\nspecs:\n  - name: my-lift\n"
                    "    env: Lift\n    objects: {target: {colours: [red, purple]}}\n"
                    "    templates: ['lift the {target} one', 'raise the {target} cube', 'pick up the {target} block']\n")
    assert main(["tasks", "validate", str(spec), "--preset", "default"]) == 0
    assert capsys.readouterr().out.strip() == (f"{spec}: 1 spec(s), 2 task(s); 1 in a campaign of preset default "
                                               "(its tasks.colours), valid")


def test_each_split_gets_at_least_its_episodes_per_split():
    from schemas.config import EvaluateConfig

    assert EvaluateConfig(episodes_per_task=3).episodes_per_case(7) == 3  # off: every case alike
    bounded = EvaluateConfig(episodes_per_task=3, episodes_per_split=45)
    assert [bounded.episodes_per_case(n) for n in (1, 3, 7, 15, 30)] == [45, 15, 7, 3, 3]


def test_every_error_the_cli_turns_into_one_line_is_a_sim2act_error():
    from dashboards.panels import PanelError
    from envs.replay import ReplayError
    from flows.cli.common import TrackingUnreachable
    from flows.run_lock import WorkspaceBusy
    from flows.service import ServiceError
    from schemas.errors import Sim2ActError
    from schemas.settings import SecretsFileError
    from warehouse.catalog import CatalogMissing, CatalogVersionError
    from warehouse.export_lerobot import ExportError
    from warehouse.shard_writer import DiskFull
    from warehouse.sql import ReadOnlyViolation
    from warehouse.training_reader import SelectionError

    for error in (ConfigError, PanelError, ReplayError, WorkspaceBusy, ServiceError, CatalogMissing,
                  CatalogVersionError, ExportError, DiskFull, ReadOnlyViolation, SelectionError, TrackingUnreachable,
                  SecretsFileError):
        assert issubclass(error, Sim2ActError), error


def test_up_takes_one_flag_per_service_setting_and_refuses_a_bad_one_in_one_line(capsys, tmp_path):
    from flows.cli import build_parser, main
    from schemas.service import ServiceConfig

    up = build_parser()._subparsers._group_actions[0].choices["up"]
    flags = {option for action in up._actions for option in action.option_strings}
    assert {f"--{name.replace('_', '-')}" for name in ServiceConfig.model_fields} <= flags
    assert main(["up", "--prefect-port", "80", "--workspace", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sim2act: config error:") and "prefect_port" in err[0]
    assert not (tmp_path / "ws").exists()  # refused before anything was written


def test_run_refuses_adapt_tasks_that_are_not_the_campaign_s_seen_tasks_in_one_line(capsys, tmp_path):
    from flows.cli import main

    assert main(["run", "--preset", "smoke", "--set", "adapt.episodes_per_task=[1]", "--set", "adapt.tasks=[lift-teal]",
                 "--workspace", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["sim2act: config error: adapt.tasks: expected task ids of the campaign's seen tasks (`sim2act tasks` "
                   "lists them), got lift-teal"]
    assert not (tmp_path / "ws").exists()  # refused before anything was written


def test_tasks_validate_refuses_a_name_the_built_in_suite_has(tmp_path, capsys):
    """It said "valid", and every campaign and `tasks list --spec-file` then refused the file."""
    from flows.cli import main

    spec = tmp_path / "mine.yaml"
    spec.write_text("defaults: {family: robosuite, expert: pick_place, horizon: 80}\nspecs:\n  - name: lift\n"
                    "    env: Lift\n    objects: {target: {colours: [red]}}\n"
                    "    templates: ['lift the {target} one', 'raise the {target} cube', 'pick up the {target} block']\n")
    assert main(["tasks", "validate", str(spec)]) == 2
    assert capsys.readouterr().err.strip() == (f"sim2act: config error: {spec}: spec name 'lift' is already defined "
                                               "(in task_specs/robosuite.yaml): give yours another name")
    builtin = Path(__file__).resolve().parents[2] / "schemas" / "task_specs" / "robosuite.yaml"
    assert main(["tasks", "validate", str(builtin)]) == 0  # the suite's own file is not a clash with itself


@pytest.mark.parametrize(("overrides", "said"), [
    ({}, "iterations: expected at least 1, or 0 with baselines.agents set (the baselines alone), got 0 and no baselines"),
    ({"baselines": {"agents": ["expert", "sac"]}},
     "baselines.env_steps: expected the RL agents' budget (a number, or one per family) where iterations is 0 "
     "(no exploration to take it from), got none"),
    ({"baselines": {"agents": ["expert"]}, "adapt": {"episodes_per_task": [10]}},
     "adapt.episodes_per_task: expected [] where iterations is 0 (no champion to adapt), got [10]"),
])
def test_a_campaign_of_no_iteration_must_say_what_it_measures(overrides, said):
    with pytest.raises(ConfigError) as refused:
        load_config("smoke", None, {"iterations": 0, **overrides})
    assert str(refused.value) == said
    alone = load_config("smoke", None, {"iterations": 0, "baselines": {"agents": ["expert", "ppo"], "env_steps": 500}})
    assert alone.iterations == 0  # the baselines alone: the experts need no budget, the RL agents have theirs
    assert load_config("smoke", None, {"iterations": 0, "baselines": {"agents": ["expert"]}}).iterations == 0
