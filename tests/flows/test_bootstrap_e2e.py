"""The whole campaign through the real CLI: real Prefect flow runs, robosuite rollouts, Parquet
shards in a DuckDB catalog, torch training, MLflow tracking and registry.

One uninterrupted smoke campaign is the reference; a re-run must do no work; a campaign killed
with SIGKILL during explore and again during train must finish with exactly the same rows.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest
from mlflow import MlflowClient

from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, sim2act_env
from warehouse.catalog import Catalog

pytestmark = pytest.mark.timeout(900)

ROW_COUNTS = """
SELECT (SELECT count(*) FROM tasks), (SELECT count(*) FROM episodes), (SELECT count(*) FROM steps),
       (SELECT count(*) FROM filter_decisions), (SELECT count(*) FROM evaluations), (SELECT count(*) FROM models),
       (SELECT count(*) FROM deployments), (SELECT count(*) FROM stage_runs), (SELECT count(*) FROM shards),
       (SELECT count(DISTINCT episode_id) FROM steps)
"""


def run_campaign(workspace: Path, prefect_api: str, kill_at: str | None = None) -> tuple[str, float]:
    """Run `sim2act run --preset smoke`; with kill_at, SIGKILL the whole process group as soon
    as a log line matches it. Returns (output, seconds)."""
    started = time.monotonic()
    process = subprocess.Popen(
        [SIM2ACT, "run", "--preset", "smoke", "--workspace", str(workspace)],
        env=sim2act_env(prefect_api), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )
    lines = []
    for line in process.stdout:
        lines.append(line)
        if kill_at and re.search(kill_at, line):
            os.killpg(process.pid, signal.SIGKILL)
            break
    process.wait(timeout=600)
    output = "".join(lines)
    if kill_at:
        assert process.returncode == -signal.SIGKILL, output[-3000:]
    else:
        assert process.returncode == 0, output[-5000:]
    return output, time.monotonic() - started


def snapshot(workspace: Path) -> dict:
    catalog = Catalog(Workspace.at(workspace).catalog)
    return {
        "counts": catalog.query(ROW_COUNTS)[0],
        "episodes": catalog.query("SELECT episode_id, explorer, num_steps, episode_return FROM episodes ORDER BY 1"),
        "digests": catalog.query("SELECT iteration, dataset_digest, triplets FROM iterations ORDER BY 1"),
        "shards": catalog.query("SELECT path, sha256 FROM shards WHERE table_name <> 'instructions' ORDER BY 1"),
    }


@pytest.fixture(scope="module")
def finished_campaign(tmp_path_factory, prefect_api):
    workspace = tmp_path_factory.mktemp("campaign")
    output, seconds = run_campaign(workspace, prefect_api)
    return workspace, output, seconds


def test_campaign_fills_the_warehouse(finished_campaign):
    workspace, output, _ = finished_campaign
    catalog = Catalog(Workspace.at(workspace).catalog)
    tasks = catalog.query("SELECT task_id, len(instructions) FROM tasks ORDER BY 1")
    assert len(tasks) >= 3 and all(n >= 3 for _, n in tasks)
    [(episodes, steps, kept)] = catalog.query(
        "SELECT (SELECT count(*) FROM episodes), (SELECT count(*) FROM triplets WHERE next_obs IS NOT NULL),"
        " (SELECT count(*) FROM filter_decisions WHERE kept)"
    )
    assert episodes == 2 * 3 * 4 and steps > episodes * 20 and 0 < kept <= episodes
    # the filter's reasons are counted, per iteration
    assert catalog.query("SELECT count(DISTINCT iteration) FROM filter_decisions WHERE reason IS NOT NULL") == [(2,)]
    # success per task per iteration is in the warehouse
    assert catalog.query("SELECT split, count(*), count(DISTINCT task_id), count(DISTINCT iteration) FROM evaluations "
                         "GROUP BY 1 ORDER BY 1") == [("seen", 6, 3, 2), ("unseen_paraphrase", 6, 3, 2)]
    # held-out paraphrases are evaluated, never explored (so never trained on)
    assert catalog.query(
        "SELECT count(*) FROM episodes e JOIN (SELECT unnest(unseen_instructions) AS said FROM tasks) u "
        "ON e.instruction = u.said") == [(0,)]
    assert catalog.query("SELECT count(*) FROM evaluations v JOIN tasks t ON v.task_id = t.task_id "
                         "WHERE v.split = 'unseen_paraphrase' AND list_contains(t.unseen_instructions, v.instruction)"
                         ) == [(6,)]
    # every episode carries its domain randomisation draw
    assert catalog.query("SELECT count(*) FROM episodes WHERE randomisation.light IS NULL") == [(0,)]
    for stage in ("explore", "filter", "index", "train", "evaluate", "redeploy"):
        assert f"sim2act.stages.{stage}" in output


def test_iteration_one_explores_with_iteration_zero_model(finished_campaign):
    workspace, _, _ = finished_campaign
    catalog = Catalog(Workspace.at(workspace).catalog)
    explorers = dict(catalog.query("SELECT iteration, list(DISTINCT explorer ORDER BY explorer) FROM episodes GROUP BY 1"))
    assert explorers[0] == ["expert"]
    assert explorers[1] == ["expert", "policy:sim2act-smoke/1"]
    [(model_0,)] = catalog.query("SELECT model_key FROM deployments WHERE iteration = 0 AND version = 1")
    assert catalog.query("SELECT count(*) FROM models WHERE model_key = ? AND iteration = 0", [model_0]) == [(1,)]


def test_mlflow_has_the_campaign_its_iterations_and_the_registered_model(finished_campaign):
    workspace, _, _ = finished_campaign
    ws = Workspace.at(workspace)
    client = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=ws.tracking_uri)
    experiment = client.get_experiment_by_name("sim2act")
    [campaign] = client.search_runs([experiment.experiment_id], "tags.`sim2act.kind` = 'campaign'")
    children = client.search_runs([experiment.experiment_id], f"tags.`mlflow.parentRunId` = '{campaign.info.run_id}'")
    assert sorted(r.data.tags["sim2act.iteration"] for r in children) == ["0", "1"]
    for child in children:
        metrics = child.data.metrics
        assert metrics["explore.episodes"] == 12 and metrics["dataset.triplets"] > 0
        assert "filter.pass_rate" in metrics and "train.loss" in metrics
        lifts = {f"success.lift-{colour}" for colour in ("red", "green", "blue")}
        assert {k for k in metrics if k.startswith("success.")} == lifts | {f"{name}.paraphrase" for name in lifts}
        # a point every train.log_every steps as it trains, and one at its last step
        steps = [m.step for m in client.get_metric_history(child.info.run_id, "train.loss")]
        assert len(steps) >= 4 and steps == sorted(set(steps)) and all(s % 20 == 0 for s in steps[:-1])
        assert {"train.lr", "train.samples_per_s", "train.data_wait"} <= set(metrics)
        artifacts = [a.path for a in client.list_artifacts(child.info.run_id, "evaluation/lift-red")]
        assert any(path.endswith(".gif") for path in artifacts)
        # the training run's dataset input: the digest and the exact shard set it read
        [dataset_input] = client.get_run(child.info.run_id).inputs.dataset_inputs
        iteration = int(child.data.tags["sim2act.iteration"])
        [(digest, shards)] = Catalog(ws.catalog).query(
            "SELECT m.dataset_digest, m.dataset_shards FROM models m JOIN iterations i USING (dataset_digest) "
            "WHERE i.iteration = ?", [iteration])
        assert dataset_input.dataset.digest == digest == child.data.tags["sim2act.dataset_digest"]
        assert json.loads(dataset_input.dataset.source)["shards"] == shards
        registered = Catalog(ws.catalog).query(
            "SELECT path FROM shards WHERE table_name = 'steps' AND iteration <= ? ORDER BY path", [iteration])
        assert shards and set(shards) <= {path for (path,) in registered}
    # the alias moved to iteration 1's model only if its evaluation beat iteration 0's
    [(promoted, decision)] = Catalog(ws.catalog).query("SELECT promoted, decision FROM deployments WHERE iteration = 1")
    champion = int(client.get_model_version_by_alias("sim2act-smoke", "champion").version)
    assert champion == (2 if promoted else 1) and "champion" in decision
    import mlflow
    from mlflow.models import get_model_info

    mlflow.set_tracking_uri(ws.tracking_uri)
    info = get_model_info("models:/sim2act-smoke/2")
    assert info.signature.inputs.input_names() == ["image", "proprio", "instruction", "family"]
    assert info.signature.outputs.input_names() == ["action", "uncertainty"]


def test_prefect_recorded_the_iterations_the_shards_and_the_explore_progress(finished_campaign, prefect_api):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterType, FlowRunFilter, FlowRunFilterId, FlowRunFilterName,
    )
    from prefect.settings import PREFECT_API_URL, temporary_settings

    names = ["smoke", "smoke-iteration-0", "smoke-iteration-1", "smoke-explore-0", "smoke-explore-1"]
    with temporary_settings({PREFECT_API_URL: prefect_api}), get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=names)))
        explores = [run.id for run in runs if "explore" in run.name]
        shards = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=explores)))
        progress = client.read_artifacts(artifact_filter=ArtifactFilter(
            type=ArtifactFilterType(any_=["progress"]), flow_run_id=ArtifactFilterFlowRunId(any_=explores)))
    assert {run.name for run in runs if run.state.is_completed()} == set(names)
    # one task run per shard (3 tasks x 2 shards per iteration), and the progress artifact at 100%
    assert sorted(t.name for t in shards) == sorted(
        [f"lift-{c}-shard-{s}" for c in ("blue", "green", "red") for s in (0, 1)] * 2)
    assert all(t.state.is_completed() for t in shards)
    assert [a.data for a in progress] == [100.0, 100.0]


def test_a_finished_campaign_reruns_without_work(finished_campaign, prefect_api):
    workspace, _, first_seconds = finished_campaign
    before = snapshot(workspace)
    output, seconds = run_campaign(workspace, prefect_api)
    assert output.count("stages that ran: 0/7") == 2, output[-3000:]
    assert "already registered" in output
    assert snapshot(workspace) == before
    assert seconds < 0.5 * first_seconds, (seconds, first_seconds)


def test_sigkill_during_explore_and_train_then_resume_gives_the_same_rows(finished_campaign, tmp_path, prefect_api):
    reference, _, _ = finished_campaign
    workspace = tmp_path / "killed"
    run_campaign(workspace, prefect_api, kill_at=r"explore it0: 4/12 episodes")
    partial = Catalog(Workspace.at(workspace).catalog).query("SELECT count(*) FROM episodes")[0][0]
    assert 0 < partial < 12
    output, _ = run_campaign(workspace, prefect_api, kill_at=r"train it0: epoch 2/")
    assert re.search(r"explore it0: 6 shards \([1-5] already registered\)", output), output[-3000:]
    run_campaign(workspace, prefect_api)
    assert snapshot(workspace) == snapshot(reference)
