"""A campaign whose randomisation an expert feels (masses, sizes, frictions away from the shipped table's)
measures its tasks' experts under it once per workspace, and leaves out those below 90% in one line, before
exploring; every call site that keys its tasks agrees with the flow."""

import json
import logging
import re
import shutil

import pytest

from envs import expert_check
from flows.model_eval import registered_tasks
from schemas.config import ConfigError, ProposerConfig, RandomiseConfig, TasksConfig, load_config
from schemas.experts import ExpertRow
from schemas.workspace import Workspace
from stages import StageUnits, UnitOutput
from stages.generate_tasks import campaign_tasks, left_out_line, run_generate_tasks
from warehouse.catalog import Catalog

HEAVY = {"mass": [100.0, 100.0]}  # measured: mw-push 0/10, mw-reach 10/10 (a reach moves no object)


def _config(randomise: dict, specs: tuple[str, ...] = ("mw-reach", "mw-push"), **tasks):
    config = load_config("smoke", overrides={"randomise": randomise})
    return config.model_copy(update={"tasks": TasksConfig(specs=list(specs), **tasks)})


def _no_measuring(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("measured again")

    monkeypatch.setattr(expert_check, "measure_experts", refuse)


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> tuple[Workspace, list, list]:
    """mw-reach and mw-push measured under HEAVY once (20 episodes): the tests read the workspace's rows."""
    workspace = Workspace.at(tmp_path_factory.mktemp("measured"))
    kept, weak = campaign_tasks(workspace, _config(HEAVY), measure=True)
    return workspace, kept, weak


def _copy(workspace: Workspace, tmp_path) -> Workspace:
    """A workspace of its own holding the measured rows (a test that registers must not share its catalog)."""
    shutil.copytree(workspace.root / "experts", tmp_path / "experts")
    return Workspace.at(tmp_path)


def test_a_task_whose_expert_fails_under_the_campaigns_masses_is_left_out_once_measured(measured, monkeypatch):
    workspace, kept, weak = measured
    config = _config(HEAVY)
    assert [t.task_id for t in kept] == ["mw-reach"] and [r.task_id for r in weak] == ["mw-push"]
    assert weak[0].episodes == expert_check.EPISODES
    assert re.fullmatch(r"1 task\(s\) left out, their scripted expert below 90% under this campaign's randomisation "
                        r"\(randomise.mass=\[100.0, 100.0\]; tasks.weak_experts: keep uses them\): "
                        r"metaworld: mw-push \d/10", left_out_line(weak, config, kept))
    assert len(list(workspace.root.joinpath("experts").glob("*.json"))) == 2  # one row per task, kept

    _no_measuring(monkeypatch)  # the rows are the workspace's now: read, not measured again
    assert [t.task_id for t in campaign_tasks(workspace, config, measure=True)[0]] == ["mw-reach"]
    # light and tint an expert cannot see, another seed's wordings it does not read: the same rows
    lit = _config({**HEAVY, "light": [0.2, 2.0], "tint": 0.5}).model_copy(update={"seed": 7})
    assert [t.task_id for t in campaign_tasks(workspace, lit, measure=True)[0]] == ["mw-reach"]
    with pytest.raises(ConfigError, match=r"^tasks.include: expected tasks whose scripted expert reaches 90% under this "
                                          r"campaign's randomisation \(randomise.mass=\[100.0, 100.0\]\), got 'mw-push' "
                                          r"at \d/10; set tasks.weak_experts: keep to use them$"):
        campaign_tasks(workspace, _config(HEAVY, include=["mw-push"]))
    with pytest.raises(ConfigError, match=r"^tasks: expected at least one seen task to explore, got none: 1 task\(s\) "
                                          r".*; family metaworld left out whole$"):
        campaign_tasks(workspace, _config(HEAVY, specs=("mw-push",)))
    assert [t.task_id for t in campaign_tasks(workspace, _config(HEAVY, weak_experts="keep"))[0]] == ["mw-reach", "mw-push"]


@pytest.mark.parametrize("randomise", [{}, {"light": [0.2, 2.0], "tint": 0.5}])
def test_what_an_expert_cannot_feel_measures_nothing(tmp_path, monkeypatch, randomise):
    _no_measuring(monkeypatch)
    kept, weak = campaign_tasks(Workspace.at(tmp_path), _config(randomise), measure=True)
    assert [t.task_id for t in kept] == ["mw-reach", "mw-push"] and weak == []
    assert not tmp_path.joinpath("experts").exists()


def test_a_measurement_killed_midway_keeps_the_rows_it_finished(tmp_path, monkeypatch):
    def first_then_killed(tasks, episodes, noise, randomise, workers, command, progress):
        progress(ExpertRow(task_id=tasks[0].task_id, family=tasks[0].family, split=tasks[0].split, episodes=episodes,
                           successes=episodes, mean_length=50, noise=noise, randomised=True, command=command,
                           measured_on="2026-12-06"))
        raise KeyboardInterrupt

    monkeypatch.setattr(expert_check, "measure_experts", first_then_killed)
    workspace = Workspace.at(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        campaign_tasks(workspace, _config({"friction": [0.5, 0.6]}), measure=True)
    assert [p.suffix for p in (tmp_path / "experts").iterdir()] == [".json"]  # the finished one, whole
    rows = expert_check.experts_under(workspace, campaign_tasks(workspace, _config({}))[0],
                                      RandomiseConfig(friction=(0.5, 0.6)), 1, measure=False)
    assert list(rows) == ["mw-reach"]  # a resumed run measures only mw-push


def test_the_flows_stage_registers_the_kept_tasks_and_an_evaluation_finds_them(measured, tmp_path, caplog):
    workspace, config = _copy(measured[0], tmp_path), _config(HEAVY)
    workspace.create()
    Catalog(workspace.catalog).initialise()
    with caplog.at_level(logging.WARNING, logger="sim2act.stages.generate_tasks"):
        result = run_generate_tasks(workspace, config)
    assert result.task_ids == ["mw-reach"] and result.experts_left_out == ["mw-push"]
    assert result.metrics()["tasks.experts_left_out"] == 1
    assert "1 task(s) left out, their scripted expert below 90% under this campaign's randomisation" in caplog.text
    assert [t.task_id for t in registered_tasks(workspace, config)] == ["mw-reach"]  # `sim2act eval`'s look-up

    # an evaluation under the default masses finds the tasks by the randomisation the campaign explored with
    elsewhere = config.model_copy(update={"randomise": RandomiseConfig()})
    with pytest.raises(ConfigError, match="this config's tasks were never generated"):
        registered_tasks(workspace, elsewhere)  # nothing explored yet: no record of the campaign's randomisation
    StageUnits(Catalog(workspace.catalog), "explore", config.name, 0).register(
        "explore-recorded", UnitOutput({"randomise": config.randomise.model_dump(mode="json")}, [], {}), 1.0)
    assert [t.task_id for t in registered_tasks(workspace, elsewhere)] == ["mw-reach"]


def test_a_task_the_proposer_brings_back_is_measured_and_dropped_again(measured, tmp_path, serve_chat):
    """The proposer checks new bindings against the shipped table alone: mw-push, left out under HEAVY, proposed
    anew (twice), is dropped by its measured row, each proposal of it a rejection; a rerun says the same."""
    push = {"spec": "mw-push", "colours": {}, "instructions": [
        "nudge the hockey puck toward the goal", "move the puck along the table to the goal spot",
        "get the puck over to the goal region"]}
    again = {**push, "instructions": ["shove the puck until it reaches the goal", "send the puck to the goal area",
                                      "slide that puck across to where the goal is"]}
    server = serve_chat(json.dumps({"tasks": [push, again]}))
    proposer = ProposerConfig(url=f"http://127.0.0.1:{server.server_port}/v1", model="tiny-llm", retries=1, timeout_s=5)
    workspace, config = _copy(measured[0], tmp_path), _config(HEAVY, proposer=proposer)
    workspace.create()
    Catalog(workspace.catalog).initialise()
    result = run_generate_tasks(workspace, config)
    assert result.task_ids == ["mw-reach"] and result.experts_left_out == ["mw-push"]
    assert result.proposals_valid == 0 and result.proposals_rejected == {"weak_expert": 2}
    rerun = run_generate_tasks(workspace, config)
    assert rerun.skipped and rerun.task_ids == ["mw-reach"] and rerun.experts_left_out == ["mw-push"]
