"""Bad input to `sim2act` is one line naming what is wrong, before any work and with nothing written: the
cases a review found (2026-12-05) ending in a traceback after the work, a half-written file, or a message
that hid the bad value."""

from __future__ import annotations

import logging
import re
import socket

import pytest

from flows.cli import main
from schemas.config import CampaignConfig, ConfigError
from schemas.workspace import Workspace


def _refused(capsys, argv: list[str]) -> str:
    """The one line a refused command says (argparse's or ours), its exit status 2."""
    try:
        status = main(argv)
    except SystemExit as exit:  # argparse refuses a flag's value as it reads the flags
        status = exit.code
    assert status == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1, lines  # argparse's refusals too: no usage block before them
    return lines[0]


def test_an_output_file_that_could_not_be_written_is_refused_before_the_work(tmp_path, capsys):
    """Once the report (or a label audit's replays, an experts table's episodes) ran whole first, then crashed on
    writing it, leaving `<out>.tmp` beside it."""
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    folder = tmp_path / "folder"
    folder.mkdir()
    assert "argument --out: expected a file to write, got the folder" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--out", str(folder)])
    assert f"got {a_file}/sub/labels.md, under {a_file}: a file, not a folder" in _refused(
        capsys, ["labels", "--workspace", str(tmp_path / "ws"), "--iteration", "0", "--out", str(a_file / "sub" / "labels.md")])
    assert "argument --record: expected a file to write" in _refused(
        capsys, ["tasks", "experts", "--task", "lift-red", "--record", str(folder)])
    assert "argument --scratch: expected a folder (made if missing)" in _refused(
        capsys, ["bench", "warehouse", "--quick", "--scratch", str(a_file / "scratch")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "folder"] and not any(folder.iterdir())


def test_write_text_atomically_leaves_no_temporary_when_it_fails(tmp_path):
    from schemas.workspace import write_text_atomically

    (tmp_path / "report.md").mkdir()
    with pytest.raises(OSError):
        write_text_atomically(tmp_path / "report.md", "text")
    assert [p.name for p in tmp_path.iterdir()] == ["report.md"]


@pytest.mark.parametrize(("flags", "words"), [
    (["--episodes", "0"], "argument --episodes: expected 1 or more, got 0"),
    (["--workers", "0"], "argument --workers: expected 1 or more, got 0"),
    (["--noise", "-1"], "argument --noise: expected a noise from 0 to 1, got -1"),
    (["--noise", "inf"], "argument --noise: expected a noise from 0 to 1, got inf"),  # measured for minutes
    (["--task", "lift-redd"], "--task: expected task ids of the suite (`sim2act tasks list`), got lift-redd"),
])
def test_tasks_experts_refuses_bad_counts_before_measuring_or_recording(tmp_path, capsys, flags, words):
    """--episodes 0 saved a record of 0 episodes, then divided by it."""
    record = tmp_path / "experts.json"
    line = _refused(capsys, ["tasks", "experts", "--task", "lift-red", "--record", str(record),
                             "--out", str(tmp_path / "experts.md"), *flags])
    assert words in line and not list(tmp_path.iterdir())


def test_a_workspace_that_is_a_file_or_under_one_is_refused_naming_it(tmp_path, capsys, monkeypatch):
    """Under a file: `run` made its catalog and failed at the first shard folder, `report` a traceback."""
    a_file = tmp_path / "ws"
    a_file.write_text("x")
    for command in (["run", "--preset", "smoke"], ["report"], ["sql", "SELECT 1"], ["warehouse", "verify"]):
        assert f"expected a workspace folder (or a path for a new one), got {a_file}: a file" in _refused(
            capsys, [*command, "--workspace", str(a_file)])
        assert f"got {a_file / 'sub'}, under {a_file}: a file" in _refused(
            capsys, [*command, "--workspace", str(a_file / "sub")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ws"]
    monkeypatch.setenv("SIM2ACT_WORKSPACE", str(a_file / "sub"))  # the default comes from it: said so
    from flows.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["status"])
    assert f"got {a_file / 'sub'} (from $SIM2ACT_WORKSPACE), under {a_file}: a file" in capsys.readouterr().err


def test_config_files_and_settings_that_cannot_be_read_are_one_line(tmp_path, capsys):
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes("name: café\n".encode("latin-1"))
    assert f"--config: {latin1} is not UTF-8 text (byte 0xe9 at offset 9); save it as UTF-8" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--config", str(latin1)])
    assert f"tasks validate: {latin1} is not UTF-8 text" in _refused(capsys, ["tasks", "validate", str(latin1)])
    assert "--config: expected a YAML file, got the folder" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--config", str(tmp_path)])
    assert "--set train.lr: train was set to 1 by an earlier --set; expected a section" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--set", "train=1", "--set", "train.lr=2"])
    assert "expected FIELD.PATH=VALUE with no empty part in '.x'" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--set", ".x=1"])
    assert not (tmp_path / "ws").exists()


def test_a_model_the_catalog_lists_without_its_checkpoint_or_a_registry_that_is_not_there(tmp_path, monkeypatch):
    """A deleted models/ folder crashed `eval` and `shadow` in torch.load; `--model champion` on a workspace with no
    registry created one (an empty MLflow store) before saying it had no champion."""
    import flows.model_eval as model_eval
    from schemas.workspace import Workspace

    workspace = Workspace.at(tmp_path / "ws")

    class Listed:  # the catalog's models row of a model whose folder is gone
        def __init__(self, path):
            pass

        def query(self, sql, params=()):
            return [("models/train-0123456789abcdef/policy.pt", 0)]

    monkeypatch.setattr(model_eval, "Catalog", Listed)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    with pytest.raises(ConfigError, match="train-0123456789abcdef is in the catalog of .*, but its checkpoint .* is missing"):
        model_eval.resolve_model(workspace, CampaignConfig(), "train-0123456789abcdef")
    with pytest.raises(ConfigError, match="'champion' is a registry reference, but .* has no model registry"):
        model_eval.resolve_model(workspace, CampaignConfig(), "champion")
    assert not workspace.root.exists()


def test_the_dashboard_says_where_it_cannot_serve_before_saying_it_serves(tmp_path, capsys):
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    try:
        line = _refused(capsys, ["dashboard", "--workspace", str(tmp_path / "ws"), "--port", str(port)])
    finally:
        taken.close()
    assert f"cannot serve the dashboard at 127.0.0.1:{port}: Address already in use" in line
    assert "argument --port: expected a port from 1 to 65535, got 99999" in _refused(
        capsys, ["dashboard", "--workspace", str(tmp_path / "ws"), "--port", "99999"])


def test_a_catalog_duckdb_cannot_open_is_one_line(tmp_path, capsys):
    from schemas.workspace import Workspace

    workspace = Workspace.at(tmp_path / "ws")
    workspace.catalog.parent.mkdir(parents=True)
    workspace.catalog.write_text("not a DuckDB file\n" * 300)
    for command in (["warehouse", "verify"], ["report"]):
        line = _refused(capsys, [*command, "--workspace", str(workspace.root)])
        assert f"the warehouse catalog {workspace.catalog} cannot be opened" in line and "restore it" in line


def test_a_bench_case_that_does_not_exist_is_one_line(capsys):
    line = _refused(capsys, ["bench", "train", "--quick", "--cases", "bogus"])
    assert "bench train: --cases: expected some of" in line and line.endswith("got bogus")


def test_a_nightly_cron_line_refused_shows_the_value():
    from pydantic import ValidationError

    from schemas.service import ServiceConfig

    with pytest.raises(ValidationError, match=r"got '61 \* \* \*'"):
        ServiceConfig(nightly_cron="61 * * *")


def test_a_campaign_that_cannot_run_is_refused_before_its_workspace_exists(tmp_path, capsys, monkeypatch):
    """Each of these made the workspace, started Prefect and generated tasks first, then failed with tracebacks
    (an hour in, for the empty dataset), leaving a catalog, an MLflow store, a Prefect database and the lock."""
    workspace = tmp_path / "ws"
    run = ["run", "--preset", "smoke", "--workspace", str(workspace)]
    assert "tasks: expected at least one seen task to explore, got none of 3" in _refused(
        capsys, [*run, "--set", "tasks.unseen_colours=[red, green, blue]"])
    monkeypatch.setenv("SIM2ACT_SCENES_PER_WORKER", "abc")
    assert "SIM2ACT_SCENES_PER_WORKER: expected a whole number of scenes, at least 1, got 'abc'" in _refused(capsys, run)
    monkeypatch.delenv("SIM2ACT_SCENES_PER_WORKER")
    assert ("iterations: expected at least 1, or 0 with baselines.agents set (the baselines alone), got 0 and no "
            "baselines") in _refused(capsys, [*run, "--iterations", "0"])
    assert "argument --iterations: expected 1 or more, got -1" in _refused(
        capsys, ["bench", "soak", "--preset", "smoke", "--workspace", str(workspace), "--iterations", "-1"])
    assert not workspace.exists()


def test_a_shard_store_that_does_not_answer_is_one_line_before_the_workspace_exists(tmp_path, capsys, monkeypatch):
    """The campaign made its workspace and started Prefect, then waited on the store inside the flow."""
    from tests.chat_server import closed_port
    from warehouse import store

    monkeypatch.setattr(store, "STORE_WAIT_S", 1.0)
    for name, value in {"SIM2ACT_SHARD_STORE": "s3://shards/lab", "AWS_ENDPOINT_URL": f"http://127.0.0.1:{closed_port()}",
                        "AWS_ACCESS_KEY_ID": "k", "AWS_SECRET_ACCESS_KEY": "s"}.items():
        monkeypatch.setenv(name, value)
    workspace = tmp_path / "ws"
    line = _refused(capsys, ["run", "--preset", "smoke", "--workspace", str(workspace)])
    assert line.startswith("sim2act: the shard store s3://shards/lab (127.0.0.1:") and "did not answer for 1 s" in line, line
    assert not workspace.exists()


def test_a_folder_given_as_a_task_file_is_called_a_folder(tmp_path, capsys):
    """It was called missing ("no such file"), which sends one looking for a typo."""
    assert f"tasks.spec_files: expected a YAML spec file, got the folder {tmp_path}" in _refused(
        capsys, ["tasks", "list", "--spec-file", str(tmp_path)])


def test_a_yaml_file_that_does_not_parse_says_where(tmp_path, capsys):
    """It said "not valid YAML (ParserError)": no line, no column, nothing to look for."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  steps: [1, 2\nseed: 3\n")
    assert f"{bad}: not valid YAML (expected ',' or ']', but got ':', line 3 column 5)" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--config", str(bad)])
    assert "not valid YAML (expected ',' or ']', but got ':', line 3 column 5)" in _refused(
        capsys, ["tasks", "validate", str(bad)])


def test_train_refuses_a_negative_iteration_as_one(tmp_path, capsys):
    """It looked the dataset up and said "no dataset for iteration -1"."""
    assert "argument --iteration: expected 0 or more, got -1" in _refused(
        capsys, ["train", "--preset", "smoke", "--workspace", str(tmp_path / "ws"), "--iteration", "-1"])


def test_sql_as_of_an_iteration_a_fresh_warehouse_has_not_reached_is_refused(tmp_path, capsys):
    from warehouse.catalog import Catalog

    workspace = Workspace.at(tmp_path / "ws").create()
    Catalog(workspace.catalog).initialise()
    assert "sql: --as-of-iteration 5: the warehouse holds no iteration yet" in _refused(
        capsys, ["sql", "SELECT 1", "--workspace", str(workspace.root), "--as-of-iteration", "5"])


def test_a_key_given_twice_in_a_config_file_is_refused(tmp_path, capsys):
    """PyYAML keeps the last: a config with two `train:` blocks ran with the second alone, silently."""
    twice = tmp_path / "twice.yaml"
    twice.write_text("train:\n  steps: 5\nseed: 1\ntrain:\n  epochs: 2\n")
    assert f"{twice}: not valid YAML (the key 'train' is given twice, line 4 column 1)" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--config", str(twice)])
    from schemas.config import load_yaml

    # a merge (`<<: *defaults`) is YAML's way to override: its keys are not given twice
    assert load_yaml("x: &d\n  steps: 5\n  epochs: 1\ntrain:\n  <<: *d\n  steps: 7\n")["train"] == {"steps": 7, "epochs": 1}
    listed = tmp_path / "listed.yaml"
    listed.write_text("? [a, b]\n: 1\n")  # was a TypeError traceback
    assert f"{listed}: not valid YAML (a key that is a list or a mapping, line 1 column 3)" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--config", str(listed)])


def test_a_model_reference_that_cannot_be_one_is_said_first(tmp_path, capsys):
    """`shadow --model 'nope!'` on a fresh workspace said the tasks were never generated, not what was wrong."""
    for command in ("shadow", "eval"):
        assert "--model: 'nope!' is neither a model key (train-...) nor a registry reference" in _refused(
            capsys, [command, "--preset", "smoke", "--workspace", str(tmp_path / "ws"), "--model", "nope!"])


def test_a_flag_no_command_takes_is_refused_by_the_command_it_was_given_to(tmp_path, capsys):
    """argparse refused it from the top parser: `sim2act: error: ... (usage: sim2act --help)`, whose usage does
    not list the command's flags."""
    assert _refused(capsys, ["run", "--workspace", str(tmp_path / "ws"), "--bogus"]) == (
        "sim2act run: error: unrecognized arguments: --bogus (usage: sim2act run --help)")
    assert _refused(capsys, ["tasks", "validate", "x.yaml", "--bogus"]).startswith("sim2act tasks validate: error:")


def test_a_registry_lookup_in_a_sqlite_store_that_does_not_exist_makes_none(tmp_path, monkeypatch):
    """MLflow made the named SQLite file (two INFO lines of migrations), then found no model in it."""
    from flows.model_eval import resolve_model
    from warehouse.catalog import Catalog

    workspace = Workspace.at(tmp_path / "ws").create()
    Catalog(workspace.catalog).initialise()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'typo.db'}")
    with pytest.raises(ConfigError, match=r"--model: 'champion' is a registry reference, but sqlite:///.*typo.db does not exist"):
        resolve_model(workspace, CampaignConfig(), "champion")
    assert not (tmp_path / "typo.db").exists()


def test_a_mapping_given_where_a_value_goes_is_shown(tmp_path, capsys):
    """It said "seed: Input should be a valid integer" and nothing of what was given."""
    assert "seed: Input should be a valid integer (got {'a': 1})" in _refused(
        capsys, ["report", "--workspace", str(tmp_path / "ws"), "--set", "seed={a: 1}"])


def test_a_campaign_whose_randomisation_fails_every_expert_is_refused_once_they_are_measured(tmp_path, capsys,
                                                                                             monkeypatch):
    """Lift's expert cannot lift a block 100x its mass: the three tasks measured (10 episodes each, cached in the
    workspace), then one line naming them, before the flow starts."""
    from envs import expert_check
    from flows.cli import campaign

    # the refusal comes before the flow: no Prefect home, watchdog or stage log handler for the tests after this one
    monkeypatch.setattr(campaign, "configure_environment", lambda workspace: None)
    monkeypatch.setattr(campaign, "watch", lambda: None)
    monkeypatch.setattr(logging.getLogger("sim2act"), "handlers", [])  # an earlier test's holds a closed capture
    argv = ["run", "--preset", "smoke", "--set", "randomise.mass=[100,100]", "--workspace", str(tmp_path / "ws")]
    line = _refused(capsys, argv)
    assert re.fullmatch(r"sim2act: config error: tasks: expected at least one seen task to explore, got none: 3 task\(s\) "
                        r"left out, their scripted expert below 90% under this campaign's randomisation "
                        r"\(randomise.mass=\[100.0, 100.0\]; tasks.weak_experts: keep uses them\): "
                        r"robosuite: lift-red \d/10, lift-green \d/10, lift-blue \d/10; family robosuite left out whole",
                        line), line
    monkeypatch.setattr(expert_check, "measure_experts", lambda *args: pytest.fail("measured again"))
    assert _refused(capsys, argv) == line  # measured once: a rerun reads the workspace's rows


def test_a_campaign_of_no_iteration_without_a_budget_for_one_of_its_agents_is_refused_before_any_work(tmp_path, capsys):
    """iterations 0 explores nothing: a budget mapping that leaves out a family an RL agent would train on once
    dropped that agent without a word."""
    workspace = tmp_path / "ws"
    said = _refused(capsys, ["run", "--preset", "smoke", "--workspace", str(workspace), "--iterations", "0",
                             "--set", "baselines.agents=[ppo]", "--set", "baselines.env_steps={metaworld: 500}"])
    assert said.endswith("baselines.env_steps: expected a budget for every RL agent where iterations is 0, got "
                         "{'metaworld': 500} and none for ppo on robosuite"), said
    assert not workspace.exists()


def test_rl_agents_on_a_family_the_campaign_gives_them_nothing_in_are_refused_before_any_work(tmp_path, capsys):
    """baselines.families names where the RL agents train: a family without seen tasks they act in would train
    nothing without a word; one that has them takes the budget of the campaign of no iteration for itself alone."""
    from envs.suite import generate_tasks
    from flows.cli.campaign import check_budgets
    from schemas.config import load_config

    workspace = tmp_path / "ws"
    said = _refused(capsys, ["run", "--preset", "smoke", "--workspace", str(workspace), "--iterations", "0",
                             "--set", "baselines.agents=[sac]", "--set", "baselines.env_steps=500",
                             "--set", "baselines.families=[metaworld, robosuite]"])
    assert said.endswith("baselines.families: expected families an RL agent of baselines.agents trains on (seen "
                         "tasks it acts in: robosuite), got metaworld"), said
    assert not workspace.exists()
    config = load_config("smoke", None, {"iterations": 0, "tasks": {"specs": ["lift", "mw-reach"]},
                                         "baselines": {"agents": ["sac"], "families": ["robosuite"],
                                                       "env_steps": {"robosuite": 500}}})
    check_budgets(config, generate_tasks(config.tasks, config.seed))  # metaworld's SAC is not asked for
