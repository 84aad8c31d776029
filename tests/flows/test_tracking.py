"""What a training logs to MLflow about its data at the generalist's scale: MLflow takes a dataset
source of at most 65,535 characters, and the million's training read 5,040 shards."""

from __future__ import annotations

import json

from mlflow import MlflowClient

from flows.tracking import MLFLOW_SOURCE_CHARACTERS, Tracking, campaign_hash, campaign_settings, settings_hash
from schemas.config import load_config
from schemas.workspace import Workspace


def test_a_training_dataset_of_thousands_of_shards_names_them_in_an_artifact(tmp_path):
    workspace = Workspace.at(tmp_path / "workspace").create()
    tracking = Tracking(workspace, load_config("smoke"))
    run_id = tracking.campaign_run()
    few = [f"steps/iteration=0/explore-{i:04d}.parquet" for i in range(3)]
    many = [f"steps/iteration=0/explore-lift-red-shard-{i:04d}-0123456789abcdef.parquet" for i in range(5040)]
    assert len(json.dumps(many)) > MLFLOW_SOURCE_CHARACTERS
    tracking.log_training_dataset(run_id, "a" * 32, few, 300)
    tracking.log_training_dataset(run_id, "b" * 32, many, 1_051_301)

    client = MlflowClient(tracking_uri=workspace.tracking_uri)
    inputs = {d.dataset.digest: d.dataset for d in client.get_run(run_id).inputs.dataset_inputs}
    assert json.loads(inputs["a" * 32].source)["shards"] == few  # a list that fits stays in the source
    source = json.loads(inputs["b" * 32].source)
    assert source["shards"] == "5040 shards: the run's artifact training/shards-bbbbbbbbbbbb.json"
    assert json.loads(inputs["b" * 32].profile) == {"triplets": 1_051_301, "shards": 5040}
    listed = client.download_artifacts(run_id, "training/shards-bbbbbbbbbbbb.json", str(tmp_path))
    assert json.loads(open(listed).read()) == many


def test_a_campaign_keeps_its_mlflow_run_when_newer_code_adds_config_fields():
    """Fields added since (a render, explore or train field at its legacy value) leave the campaign's hash
    as it was without them; a field that changes what is made, or the name, makes another campaign; more
    iterations or an adaptation continue the same one."""
    config = load_config("hard-mix")
    assert campaign_hash(config) == campaign_hash(config.model_copy(update={"iterations": 9}))
    settings = campaign_settings(config)
    for section, added in (("render", "wrist_camera"), ("render", "mesh_detail"), ("render", "decimate_colliding"),
                           ("explore", "expert_takeover"), ("train", "language_augment"),
                           ("train", "proprio_dropout"), ("explore", "policy_steps"),
                           ("explore", "first_episodes_per_task"), ("baselines", "sac_encoder"),
                           ("baselines", "end_on_success"), ("baselines", "sac_target_entropy"),
                           ("baselines", "families")):
        assert added not in settings[section]  # as code from before the field existed hashed the campaign
    assert campaign_settings(load_config("hard-mix", None, {"render": {"wrist_camera": True}}))["render"]["wrist_camera"]
    assert campaign_hash(config) != campaign_hash(load_config("hard-mix", None, {"render": {"wrist_camera": True}}))
    assert campaign_hash(config) != campaign_hash(load_config("hard-mix", None, {"explore": {"expert_takeover": 0.5}}))
    assert campaign_hash(config) != campaign_hash(config.model_copy(update={"name": "other"}))
    assert campaign_hash(config) != campaign_hash(load_config("hard-mix", None, {"baselines": {"sac_encoder": "critic"}}))


def test_a_campaign_resumed_with_other_workers_continues_its_mlflow_runs(tmp_path):
    """How a campaign runs (workers, threads, a device) is not what it makes: the same campaign run and
    iteration run; a run made before the `sim2act.settings` tag is found by its `sim2act.config` one."""
    workspace = Workspace.at(tmp_path).create()
    config = load_config("smoke")
    fewer = load_config("smoke", None, {"evaluate": {"workers": 1}, "explore": {"workers": 1},
                                        "train": {"threads": 1, "checkpoint_every": 7},
                                        "baselines": {"threads": 2, "families": ["robosuite"]}})
    assert campaign_hash(config) != campaign_hash(fewer) and settings_hash(config) == settings_hash(fewer)
    assert settings_hash(config) != settings_hash(load_config("smoke", None, {"train": {"steps": 11}}))
    first = Tracking(workspace, config)
    campaign = first.campaign_run()
    iteration = first.iteration_run(campaign, 0)
    again = Tracking(workspace, fewer)
    assert again.campaign_run() == campaign and again.iteration_run(campaign, 0) == iteration

    # as older code made it: no settings tag
    client = MlflowClient(tracking_uri=workspace.tracking_uri)
    older = client.create_run(first.experiment_id, tags={"sim2act.campaign": "older", "sim2act.kind": "campaign",
                                                         "sim2act.config": campaign_hash(config.model_copy(
                                                             update={"name": "older"}))}).info.run_id
    found = Tracking(workspace, config.model_copy(update={"name": "older"})).campaign_run()
    assert found == older and client.get_run(older).data.tags["sim2act.settings"] == settings_hash(
        config.model_copy(update={"name": "older"}))


def test_a_resumed_training_logs_each_step_once_and_a_fresh_one_every_step(tmp_path):
    """A training killed after logging steps 2-8 with its checkpoint at 4 goes on from 4: steps 6 and 8 come again
    and are not logged twice. A fresh training into the same run (no resume) logs all of its own."""
    workspace = Workspace.at(tmp_path).create()
    tracking = Tracking(workspace, load_config("smoke"))
    run_id = tracking.iteration_run(tracking.campaign_run(), 0)
    killed = tracking.step_logger(run_id, "train.")
    for step in (2, 4, 6, 8):
        killed(step, {"loss": 1.0 / step})
    resumed = tracking.step_logger(run_id, "train.")
    resumed.resumed_at(4)
    for step in (6, 8, 10):
        resumed(step, {"loss": 1.0 / step})
    history = MlflowClient(tracking_uri=workspace.tracking_uri).get_metric_history(run_id, "train.loss")
    assert sorted(m.step for m in history) == [2, 4, 6, 8, 10]
    fresh = tracking.step_logger(run_id, "train.")
    fresh(2, {"loss": 0.5})
    assert len(MlflowClient(tracking_uri=workspace.tracking_uri).get_metric_history(run_id, "train.loss")) == 6
