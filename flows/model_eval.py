"""`sim2act eval`: any model on any tasks. The model by registry reference or model key; the tasks
the campaign's (all, or one split), or a task spec file's, tasks the model may never have trained
on. Rolled out with the campaign's render, randomisation and evaluation seeds (stages.evaluate),
recorded in the warehouse `evaluations` under the task set's suite name."""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from mlflow import MlflowClient
from mlflow.exceptions import MlflowException

from envs.suite import generate_tasks
from policies.model import ModelDims
from schemas.config import CampaignConfig, ConfigError, RandomiseConfig, read_text_file, recorded_render
from schemas.tasks import CAMPAIGN_SUITE, TaskRecord
from schemas.settings import REGISTRY_URI_ENV, TRACKING_URI_ENV, registry_uri, tracking_uri
from schemas.wordings import HELD_OUT_WORDING
from schemas.workspace import Workspace
from stages.evaluate import EvalUnit, evaluation_cases
from stages.generate_tasks import campaign_tasks, tasks_unit_key
from stages.redeploy import MODEL_KEY_TAG, champion_explorer
from stages.train import model_dims
from warehouse.catalog import Catalog
from warehouse.shard_writer import ShardUnreadable
from warehouse.store import ShardStoreUnreachable
from warehouse.tasks import load_tasks

_NAME, _ALIAS, _VERSION = re.compile(r"^[A-Za-z0-9_.-]+$"), re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$"), re.compile(r"^v?(\d+)$")


@dataclass(frozen=True)
class ModelRef:
    model_key: str
    checkpoint: str
    iteration: int  # the iteration whose dataset it trained on
    label: str  # as people named it: name/version, or the model key


def resolve_model(workspace: Workspace, config: CampaignConfig, ref: str) -> ModelRef:
    """A model key of the catalog's `models`, or a registry reference (`champion`, `@alias`, `3`,
    `v3`, `name/3`, `name@alias`, with or without `models:/`; the name defaults to the campaign's
    registered model). Unknown: ConfigError naming it."""
    catalog = Catalog(workspace.catalog)
    if ref.startswith("train-"):
        found = catalog.query("SELECT checkpoint_path, iteration FROM models WHERE model_key = ?", [ref])
        if not found:
            raise ConfigError(f"--model: no model {ref!r} in {workspace.root}")
        checkpoint = workspace.root / found[0][0]  # stored relative to the workspace
        if not checkpoint.is_file():
            raise ConfigError(f"--model: {ref} is in the catalog of {workspace.root}, but its checkpoint {checkpoint} "
                              "is missing (its models/ folder moved or deleted?)")
        return ModelRef(ref, str(checkpoint), found[0][1], ref)
    name, version_number, alias = parse_registry_ref(ref, config.registered_model_name)
    if not (os.environ.get(TRACKING_URI_ENV) or os.environ.get(REGISTRY_URI_ENV)) and not workspace.tracking_db.exists():
        raise ConfigError(f"--model: {ref!r} is a registry reference, but {workspace.root} has no model registry "
                          f"({workspace.tracking_db} is missing: no campaign ran there); name a model key "
                          "(train-...) or the workspace of a campaign that ran")  # not made here: a lookup writes nothing
    for uri in {os.environ.get(TRACKING_URI_ENV), os.environ.get(REGISTRY_URI_ENV)} - {None, ""}:
        if uri.startswith("sqlite:///") and not Path(uri.removeprefix("sqlite:///")).is_file():  # MLflow would make it
            raise ConfigError(f"--model: {ref!r} is a registry reference, but {uri} does not exist (no registry "
                              "there); name a model key (train-...) or the store a campaign registered in")
    client = MlflowClient(tracking_uri=tracking_uri(workspace), registry_uri=registry_uri(workspace))
    try:
        version = (client.get_model_version(name, version_number) if version_number
                   else client.get_model_version_by_alias(name, alias))
    except MlflowException:
        raise ConfigError(f"--model: the registry of {workspace.root} has no {ref!r} (model {name!r})") from None
    model_key = version.tags[MODEL_KEY_TAG]
    found = catalog.query("SELECT iteration FROM models WHERE model_key = ?", [model_key])
    if not found:
        raise ConfigError(f"--model: {name}/{version.version} was trained in another workspace than {workspace.root}")
    explorer = champion_explorer(workspace, client, name, int(version.version))
    return ModelRef(model_key, explorer.checkpoint, found[0][0], f"{name}/{version.version}")


def check_model_ref(ref: str, config: CampaignConfig) -> None:
    """`ref` is a model key or reads as a registry reference (ConfigError otherwise); whether it names a
    model is `resolve_model`'s to say."""
    if not ref.startswith("train-"):
        parse_registry_ref(ref, config.registered_model_name)


def parse_registry_ref(ref: str, default_name: str) -> tuple[str, str | None, str | None]:
    """(name, version, alias), one of the last two None, from champion, @alias, 3, v3, name/3,
    name@alias (each with or without models:/)."""
    body = ref.removeprefix("models:/")
    if "@" in body:
        name, alias, version = *body.split("@", 1), None
    elif "/" in body:
        (name, token), alias = body.rsplit("/", 1), None
        version = _VERSION.match(token)[1] if _VERSION.match(token) else ""
    else:
        name, version, alias = default_name, None, None
        if _VERSION.match(body):
            version = _VERSION.match(body)[1]
        else:
            alias = body
    name = name or default_name
    if not _NAME.match(name) or (version is None and not _ALIAS.match(alias or "")) or version == "":
        raise ConfigError(f"--model: {ref!r} is neither a model key (train-...) nor a registry reference "
                          "(champion, @alias, 3, v3, name/3, name@alias)")
    return name, version, alias


def check_model_fits(config: CampaignConfig, model: ModelRef) -> None:
    """The campaign must render what the model reads (image size, RGB or RGB-D, its views): refused before any rollout."""
    reads = ModelDims(**torch.load(model.checkpoint, map_location="cpu", weights_only=False)["dims"])
    rendered = model_dims(config)
    if reads.image_size != rendered.image_size:
        raise ConfigError(f"render.image_size: {model.label} reads {reads.image_size} px frames, "
                          f"the config renders {rendered.image_size}")
    if reads.channels != rendered.channels:
        depth = reads.channels == 4
        raise ConfigError(f"render.depth: {model.label} reads {'RGB-D' if depth else 'RGB'} frames; "
                          f"set render.depth={str(depth).lower()}")
    if reads.views != rendered.views:
        wrist = reads.views == 2
        raise ConfigError(f"render.wrist_camera: {model.label} reads {reads.views} camera view(s); "
                          f"set render.wrist_camera={str(wrist).lower()}")


def registered_tasks(workspace: Workspace, config: CampaignConfig) -> list[TaskRecord]:
    """The campaign's tasks as its flow registered them: those its experts did not fail under the randomisation it
    explored with (an evaluation under another randomisation evaluates the same tasks); the config's own where the
    campaign explored nothing yet."""
    catalog = Catalog(workspace.catalog)
    explored = explored_randomise(latest_explore_summary(catalog, config.name))
    as_explored = config if explored is None else config.model_copy(update={"randomise": explored})
    key = tasks_unit_key(as_explored, campaign_tasks(workspace, as_explored)[0])
    if not catalog.is_registered(key):
        raise ConfigError(f"tasks: this config's tasks were never generated in {workspace.root} "
                          "(run `sim2act run` with it first, or give --tasks FILE)")
    return load_tasks(workspace, key)


def latest_explore_summary(catalog: Catalog, campaign: str) -> tuple[str, dict] | None:
    """(unit key, stage_runs summary) of the campaign's latest explore unit; None: it explored nothing here."""
    if not catalog.path.exists():
        return None
    latest = catalog.query("SELECT unit_key, summary FROM stage_runs WHERE stage = 'explore' AND campaign = ? "
                           "ORDER BY finished_at DESC NULLS LAST, unit_key DESC LIMIT 1", [campaign])
    return (latest[0][0], json.loads(latest[0][1] or "{}")) if latest else None


def explored_randomise(latest: tuple[str, dict] | None) -> RandomiseConfig | None:
    """The randomisation a latest explore unit drew from (None: none, or one explored before its summary
    recorded it); a field a later version dropped is ignored."""
    recorded = latest[1].get("randomise") if latest else None
    if recorded is None:
        return None
    return RandomiseConfig.model_validate({k: v for k, v in recorded.items() if k in RandomiseConfig.model_fields})


def file_tasks(path: Path, config: CampaignConfig, seen_ids: set[str]) -> list[TaskRecord]:
    """Every task a spec file declares, all colours bound; `seen` where the campaign explored the
    same task id, `unseen` otherwise (whatever the file holds out)."""
    from schemas.config import TasksConfig
    from schemas.task_spec import parse_spec_file

    if not path.is_file():
        raise ConfigError(f"--tasks: expected a YAML task file, got {'the folder ' if path.is_dir() else 'no such file '}{path}")
    names = [spec.name for spec in parse_spec_file(read_text_file(path, "--tasks"), str(path))]
    tasks = generate_tasks(TasksConfig(specs=names, spec_files=[path], weak_experts="keep"), config.seed)
    return [t.model_copy(update={"split": "seen" if t.task_id in seen_ids else "unseen"}) for t in tasks]


def _flat(settings: dict, prefix: str) -> dict[str, str]:
    """`{"mesh_detail": 0.1}` -> `{"render.mesh_detail": "0.1"}`: values as JSON, so a tuple and a list compare."""
    return {f"{prefix}.{name}": json.dumps(value, sort_keys=True) for name, value in settings.items()}


def explored_conditions(catalog: Catalog, campaign: str) -> dict[str, str]:
    """The render and randomisation settings the campaign's latest explore unit ran under, flat as
    `render.mesh_detail` -> its value as JSON: its episodes' render record, with the fields added since from the
    unit's summary (absent there: at their legacy values), and the randomisation ranges its summary records
    (a unit explored before they were recorded: whether randomisation was on, from its episodes' draws).
    {}: the campaign explored nothing here."""
    latest = latest_explore_summary(catalog, campaign)
    if latest is None:
        return {}
    unit_key, summary = latest
    try:
        episode = catalog.read_unit_shard("episodes", unit_key, ["render", "randomisation"]).slice(0, 1).to_pylist()
    except (KeyError, ShardUnreadable, ShardStoreUnreachable):  # no record to read: the summary's alone
        episode = []
    render = recorded_render(episode[0]["render"] or {} if episode else {}, summary)
    if "randomise" in summary:
        randomise = summary["randomise"]
    else:  # the whole draw is null where the campaign turned randomisation off
        randomise = {"enabled": episode[0]["randomisation"] is not None} if episode else {}
    return {**_flat(render, "render"), **_flat(randomise, "randomise")}


def conditions_apart(workspace: Workspace, config: CampaignConfig) -> list[str]:
    """The render and randomisation settings in which `config` differs from what its campaign explored under
    (explored_conditions), as `render.mesh_detail=1.0`: frames the campaign's model never met, whose evaluation
    is not the campaign's figure. Empty where they agree or nothing was explored."""
    explored = explored_conditions(Catalog(workspace.catalog), config.name)
    mine = {**_flat(config.render.model_dump(mode="json"), "render"),
            **_flat(config.randomise.model_dump(mode="json"), "randomise")}
    if mine["randomise.enabled"] == explored.get("randomise.enabled") == "false":  # ranges nothing draws from
        explored = {name: value for name, value in explored.items() if not name.startswith("randomise.")}
    return [f"{name}={mine[name]}" for name in sorted(explored) if name in mine and mine[name] != explored[name]]


def _suite(name: str, apart: list[str], config: CampaignConfig, cases: list[tuple[TaskRecord, str, str]]) -> str:
    """The suite's name: `name`, then what differs from the campaign's exploration (`conditions_apart`), and
    MetaWorld's placements where its cases are on other ones than MT1's (exploration always takes MT1's), and
    episodes cut short of their horizons."""
    placements = config.evaluate.metaworld_placements
    if placements != "benchmark" and any(task.family == "metaworld" for task, _, _ in cases):
        apart = [*apart, f"evaluate.metaworld_placements={placements}"]
    if config.evaluate.max_steps is not None:
        apart = [*apart, f"evaluate.max_steps={config.evaluate.max_steps}"]
    return f"{name} @ {', '.join(apart)}" if apart else name


def eval_cases(workspace: Workspace, config: CampaignConfig, tasks_file: Path | None,
               split: str | None, family: str | None = None) -> tuple[str, list[tuple[TaskRecord, str, str]]]:
    """(suite, cases): a file's tasks (seen: the task ids the campaign explored), or the
    campaign's own evaluation cases, all or one split: the same units as the flow's, so a model
    the flow evaluated is not rolled out again. Under render or randomisation settings other than the
    campaign explored under, the suite names them (`campaign @ render.mesh_detail=1.0`): such an evaluation
    keeps its own rows beside the campaign's, which the report and the dashboard read."""
    apart = conditions_apart(workspace, config)
    if tasks_file is not None:
        explored = {task_id for (task_id,) in Catalog(workspace.catalog).query(
            "SELECT DISTINCT task_id FROM episodes WHERE campaign = ?", [config.name])}
        cases = evaluation_cases(file_tasks(tasks_file, config, explored))
        return _suite(f"file:{tasks_file.name}", apart, config, _of(cases, family)), cases
    # --split held_out_wording asks for that split whether or not the campaign evaluates it
    cases = evaluation_cases(registered_tasks(workspace, config),
                             config.evaluate.held_out_wordings or split == HELD_OUT_WORDING)
    if split:
        cases = [case for case in cases if case[1] == split]
        if not cases:
            raise ConfigError(f"--split: campaign {config.name!r} has no {split} evaluation case")
    return _suite(CAMPAIGN_SUITE, apart, config, _of(cases, family)), cases


def _of(cases: list[tuple[TaskRecord, str, str]], family: str | None) -> list[tuple[TaskRecord, str, str]]:
    return cases if family is None else [case for case in cases if case[0].family == family]


def instruction_embeddings(workspace: Workspace, config: CampaignConfig,
                           cases: list[tuple[TaskRecord, str, str]]) -> dict[str, np.ndarray]:
    """The frozen encoder's embeddings of the instructions the cases say that the warehouse caches
    (evaluate_model encodes the others)."""
    encoder = config.train.model.language_encoder
    texts = sorted({instruction for _, _, instruction in cases})
    table = Catalog(workspace.catalog).query_arrow(
        "SELECT DISTINCT instruction, embedding FROM instructions WHERE encoder = ? AND list_contains(?, instruction)",
        [encoder, texts])
    return {text: np.asarray(vector, dtype=np.float32)
            for text, vector in zip(table["instruction"].to_pylist(), table["embedding"].to_pylist())}


def trained_seeds(workspace: Workspace, config: CampaignConfig, model: ModelRef, task_ids: list[str]) -> dict[str, list[int]]:
    """Per task, the seeds of the campaign's episodes kept up to the model's iteration, iteration by iteration
    (within one, by episode id), each once: an environment reset with one of them starts where a training
    episode started (the placement the model was shown, with its expert label), as explore drew it (`sim2act
    shadow --placements trained`). A seed explored twice (a unit redone under a new key) is one placement.
    `train.where` is not applied: these are the campaign's kept episodes, a narrowed training saw fewer.
    Relabelled episodes are left out: their seed under the task they were filed as colours the objects the
    other way."""
    rows = Catalog(workspace.catalog).query(
        "SELECT task_id, seed FROM episodes WHERE campaign = ? AND iteration <= ? AND error IS NULL "
        "AND list_contains(?, task_id) AND coalesce(explorer_stats, '') NOT LIKE '%relabelled_from%' "
        "AND episode_id IN (SELECT episode_id FROM filter_decisions WHERE kept) ORDER BY iteration, episode_id",
        [config.name, model.iteration, task_ids])
    seeds: dict[str, list[int]] = {}
    for task_id, seed in rows:
        if int(seed) not in (known := seeds.setdefault(task_id, [])):
            known.append(int(seed))
    return seeds


def started_as_trained(units: list[EvalUnit], seeds: dict[str, list[int]]) -> list[EvalUnit]:
    """The units of tasks with trained seeds (`trained_seeds`), each playing as many of them as it asked
    episodes, in `trained_seeds` order. Raises ConfigError where no unit's task was trained on."""
    started = [unit.model_copy(update={"seeds": seeds[unit.task.task_id][:len(unit.seeds)]})
               for unit in units if seeds.get(unit.task.task_id)]
    if not started:
        raise ConfigError(f"--placements trained: expected cases the model trained on, got only "
                          f"{', '.join(sorted({unit.task.task_id for unit in units}))} (held out: try --split seen)")
    return started
