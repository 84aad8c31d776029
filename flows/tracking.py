"""MLflow bookkeeping: one campaign run, one child run per iteration, found again on resume."""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import urlsplit

from mlflow import MlflowClient
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param, RunTag
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID, MLFLOW_RUN_NAME

from schemas.config import RENDER_LEGACY_VALUES, CampaignConfig
from schemas.keys import key_fields
from schemas.settings import registry_uri, tracking_uri
from schemas.workspace import Workspace
from stages.evaluate import TaskEvaluation, evaluation_metrics, evaluation_videos
from stages.train import EXECUTION_FIELDS as TRAIN_EXECUTION_FIELDS

EXPERIMENT = "sim2act"


def _flatten(data: Mapping, prefix: str = "") -> dict[str, str]:
    flat = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f"{name}."))
        else:
            flat[name] = str(value)
    return flat


MLFLOW_SOURCE_CHARACTERS = 65_535  # the longest dataset source MLflow accepts (mlflow.utils.validation)

# How a campaign runs, not what it makes (the unit keys leave them out): per config section.
# baselines.families too: which families' agents a run trains, each under the key it has beside the others
EXECUTION_FIELDS = {"explore": {"workers", "dask_address"}, "evaluate": {"workers"},
                    "baselines": {"workers", "threads", "families"}, "train": TRAIN_EXECUTION_FIELDS}


def campaign_settings(config: CampaignConfig) -> dict:
    """What tells one campaign's MLflow run from another's: its name plus everything but the iteration count
    and the adaptation after its iterations (asking for more iterations, or for an adaptation, continues the
    same run), without the fields added since that hold their legacy values, as unit keys leave them out — so
    a campaign resumed by newer code continues its run instead of opening another."""
    from stages.baselines import LEGACY_VALUES as BASELINES_LEGACY_VALUES
    from stages.explore import LEGACY_VALUES as EXPLORE_LEGACY_VALUES
    from stages.train import LEGACY_VALUES as TRAIN_LEGACY_VALUES

    # the baselines' fields whose default changed as they were added count as absent at that default: a campaign
    # keeps its run, while the unit keys (stages.baselines.LEGACY_VALUES) tell the new agents from the old
    baselines = {**BASELINES_LEGACY_VALUES, "end_on_success": False, "sac_target_entropy": "acting", "families": None}
    legacy = {"render": RENDER_LEGACY_VALUES, "explore": EXPLORE_LEGACY_VALUES, "train": TRAIN_LEGACY_VALUES,
              "baselines": baselines}
    return key_fields(config, {"iterations", "adapt"}, legacy)


def campaign_hash(config: CampaignConfig) -> str:
    """The `sim2act.config` tag: every setting, how the campaign runs included (runs made before
    `sim2act.settings` existed are found by it)."""
    return _digest(campaign_settings(config))


def settings_hash(config: CampaignConfig) -> str:
    """The `sim2act.settings` tag: campaign_settings less how the campaign runs, as the unit keys leave it
    out (EXECUTION_FIELDS), so a campaign resumed with fewer workers continues its run."""
    settings = campaign_settings(config)
    for section, fields in EXECUTION_FIELDS.items():
        for name in fields:
            settings.get(section, {}).pop(name, None)
    return _digest(settings)


def _digest(settings: dict) -> str:
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode(), digest_size=6).hexdigest()


class StepLogger:
    """A training's metrics into its run under `prefix`, each step once: told where a resumed training goes on
    from (`resumed_at`, stages.train), it skips the steps after it that the run holds already: the kill cut them
    after the checkpoint, and they come again with the same values. A fresh training logs every step."""

    def __init__(self, tracking: Tracking, run_id: str, prefix: str):
        self.tracking, self.run_id, self.prefix = tracking, run_id, prefix
        self.replayed = range(0)  # the steps the run holds that a resumed training goes through again

    def resumed_at(self, step: int) -> None:
        history = self.tracking.client.get_metric_history(self.run_id, f"{self.prefix}loss")
        self.replayed = range(step + 1, max((m.step for m in history), default=step) + 1)

    def __call__(self, step: int, metrics: Mapping[str, float]) -> None:
        if step not in self.replayed:
            self.tracking.log_metrics(self.run_id, {f"{self.prefix}{k}": v for k, v in metrics.items()}, step)


class Tracking:
    def __init__(self, workspace: Workspace, config: CampaignConfig):
        uri = tracking_uri(workspace)
        self.client = MlflowClient(tracking_uri=uri, registry_uri=registry_uri(workspace))
        self.config = config
        self.warehouse = workspace.warehouse
        experiment = self.client.get_experiment_by_name(EXPERIMENT)
        # An MLflow server keeps artifacts where it was told (its proxied store): the experiment takes the
        # server's default. Any store opened directly (the workspace's SQLite file, a database URL) would
        # put them in ./mlruns of whatever folder the command ran in: the workspace's folder instead.
        location = None if urlsplit(uri).scheme in ("http", "https") else workspace.artifact_root.as_uri()
        self.experiment_id = (
            experiment.experiment_id if experiment else self.client.create_experiment(EXPERIMENT, artifact_location=location)
        )
        self.config_hash, self.settings_hash = campaign_hash(config), settings_hash(config)
        self.created: list[str] = []  # runs this Tracking made (a command ends those it opened)

    def _find_or_create(self, tags: dict[str, str], name: str, params: dict[str, str] | None = None) -> str:
        """The run with `tags`; where they name the campaign's settings, one made before its `sim2act.settings`
        tag existed (found by `sim2act.config`, and tagged now); else a new one."""
        def search(wanted: dict[str, str]):
            query = " and ".join(f"tags.`{k}` = '{v}'" for k, v in wanted.items())
            return self.client.search_runs([self.experiment_id], query, max_results=1)

        found = search(tags)
        if not found and "sim2act.settings" in tags:
            earlier = {k: v for k, v in tags.items() if k != "sim2act.settings"}
            found = search({**earlier, "sim2act.config": self.config_hash})
            if found:
                self.client.set_tag(found[0].info.run_id, "sim2act.settings", tags["sim2act.settings"])
        if found:
            return found[0].info.run_id
        if "sim2act.settings" in tags:
            tags = {**tags, "sim2act.config": self.config_hash}
        run = self.client.create_run(self.experiment_id, tags={**tags, MLFLOW_RUN_NAME: name}, run_name=name)
        self.created.append(run.info.run_id)
        if params:
            self.client.log_batch(run.info.run_id, params=[Param(k, v[:6000]) for k, v in params.items()])
        return run.info.run_id

    def campaign_run(self) -> str:
        tags = {"sim2act.campaign": self.config.name, "sim2act.settings": self.settings_hash, "sim2act.kind": "campaign"}
        return self._find_or_create(tags, f"{self.config.name}", _flatten(self.config.model_dump(mode="json")))

    def iteration_run(self, campaign_run_id: str, iteration: int) -> str:
        tags = {
            "sim2act.campaign": self.config.name, "sim2act.settings": self.settings_hash,
            "sim2act.kind": "iteration", "sim2act.iteration": str(iteration), MLFLOW_PARENT_RUN_ID: campaign_run_id,
        }
        return self._find_or_create(tags, f"{self.config.name}-iteration-{iteration}", {"iteration": str(iteration)})

    def evaluation_run(self, model_key: str, suite: str, label: str) -> str:
        """A run of its own for `sim2act eval` of one model on one task set (found again on a re-run)."""
        tags = {"sim2act.campaign": self.config.name, "sim2act.kind": "evaluation", "sim2act.model_key": model_key,
                "sim2act.suite": suite, "sim2act.episodes": str(self.config.evaluate.episodes_per_task)}
        return self._find_or_create(tags, f"eval {label} on {suite}")

    def log_evaluation(self, run_id: str, evaluations: list[TaskEvaluation]) -> None:
        """Success per case and per group (split, family, split within family) with their Wilson
        intervals, mean episode lengths, and the cases' videos."""
        self.log_metrics(run_id, evaluation_metrics(evaluations))
        for video, folder in evaluation_videos(evaluations):
            self.log_artifact(run_id, video, folder)

    def log_metrics(self, run_id: str, metrics: Mapping[str, float], step: int = 0) -> None:
        import time

        now = int(time.time() * 1000)
        self.client.log_batch(run_id, metrics=[Metric(k, float(v), now, step) for k, v in metrics.items()])

    def log_artifact(self, run_id: str, path: str, folder: str) -> None:
        self.client.log_artifact(run_id, path, folder)

    def step_logger(self, run_id: str, prefix: str) -> StepLogger:
        """(step, metrics) -> logged to the run under `prefix`: a stage's live metrics."""
        return StepLogger(self, run_id, prefix)

    def set_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        self.client.log_batch(run_id, tags=[RunTag(k, v) for k, v in tags.items()])

    def log_training_dataset(self, run_id: str, digest: str, shards: list[str], triplets: int) -> None:
        """The exact data a training run read (its steps shards; the kept steps, narrowed by
        train.where), as the run's MLflow dataset input. A shard list longer than MLflow takes in a
        source (the million's 5,040 shards: ~260k characters) goes to the run's artifact
        `training/shards-<digest>.json`, which the source names."""
        source = {"warehouse": str(self.warehouse), "selection": "kept steps", "where": self.config.train.where,
                  "shards": shards}
        if len(json.dumps(source)) > MLFLOW_SOURCE_CHARACTERS:
            with tempfile.TemporaryDirectory() as folder:
                listing = Path(folder) / f"shards-{digest[:12]}.json"
                listing.write_text(json.dumps(shards))
                self.log_artifact(run_id, str(listing), "training")
            source["shards"] = f"{len(shards)} shards: the run's artifact training/{listing.name}"
        dataset = Dataset(
            name=f"{self.config.name}-warehouse", digest=digest, source_type="sim2act-warehouse",
            source=json.dumps(source), schema=None,
            profile=json.dumps({"triplets": triplets, "shards": len(shards)}),
        )
        self.client.log_inputs(run_id, [DatasetInput(dataset, [InputTag("mlflow.data.context", "training")])])

    def finish(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status)

    def finish_created(self, status: str = "FINISHED") -> None:
        """End the runs this Tracking opened, newest first (a command's own campaign and iteration runs;
        those it found belong to whatever made them)."""
        for run_id in reversed(self.created):
            self.finish(run_id, status)
