"""The whole campaign through the real CLI: real Prefect flow runs, robosuite rollouts, Parquet
shards in a DuckDB catalog, torch training, MLflow tracking and registry.

One uninterrupted smoke campaign is the reference; a re-run must do no work; a campaign killed
with SIGKILL in each stage in turn must finish with exactly the same rows.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import imageio.v2 as iio
import pytest
from mlflow import MlflowClient

from schemas.config import load_config
from schemas.workspace import Workspace
from stages.baselines import exploration_steps, rl_units
from tests.campaign import NEW_TASKS, iteration_zero_snapshot, run_campaign, snapshot
from tests.conftest import SIM2ACT, sim2act_env
from warehouse.catalog import Catalog
from warehouse.priority import plan_priorities
from warehouse.tasks import load_embeddings, load_tasks

pytestmark = pytest.mark.timeout(900)


def test_the_run_ends_with_a_summary_a_person_reads(finished_campaign):
    workspace, output, _ = finished_campaign
    summary = output[output.index("campaign 'smoke': success per iteration"):]
    catalog = Catalog(Workspace.at(workspace).catalog)
    for iteration in (0, 1):  # each iteration's seen figure, as the warehouse has it
        [(successes, episodes)] = catalog.query(
            "SELECT sum(v.successes), sum(v.episodes) FROM evaluations v JOIN deployments d USING (campaign, iteration, "
            "model_key) WHERE v.iteration = ? AND v.split = 'seen' AND v.suite = 'campaign'", [iteration])
        assert re.search(rf"\n  {iteration} +{successes}/{episodes} ", summary), summary
    assert "unseen_paraphrase" in summary and "look further:" in summary
    assert f"sim2act report --preset smoke --workspace {workspace}" in summary


def test_campaign_fills_the_warehouse(finished_campaign):
    workspace, output, _ = finished_campaign
    catalog = Catalog(Workspace.at(workspace).catalog)
    tasks = catalog.query("SELECT task_id, len(instructions) FROM tasks ORDER BY 1")
    assert len(tasks) >= 3 and all(n >= 3 for _, n in tasks)
    [(episodes, steps, kept)] = catalog.query(
        "SELECT (SELECT count(*) FROM episodes), (SELECT count(*) FROM triplets WHERE next_obs IS NOT NULL),"
        " (SELECT count(*) FROM filter_decisions WHERE kept)"
    )
    assert episodes == 2 * 3 * load_config("smoke").explore.episodes_per_task and steps > episodes * 20 and 0 < kept <= episodes
    # the filter's reasons are counted, per iteration
    assert catalog.query("SELECT count(DISTINCT iteration) FROM filter_decisions WHERE reason IS NOT NULL") == [(2,)]
    # success per task per iteration is in the warehouse
    assert catalog.query("SELECT split, count(*), count(DISTINCT task_id), count(DISTINCT iteration) FROM evaluations "
                         "GROUP BY 1 ORDER BY 1") == [("seen", 6, 3, 2), ("unseen_paraphrase", 6, 3, 2)]
    # each case: a Wilson interval around its rate, the episodes' lengths, an MP4 of each outcome it had
    for successes, episodes, low, high, lengths, outcomes, success_video, failure_video in catalog.query(
            "SELECT successes, episodes, ci_low, ci_high, episode_lengths, episode_successes, success_video, "
            "failure_video FROM evaluations"):
        assert low <= successes / episodes <= high and high - low > 0.3 and len(lengths) == len(outcomes) == episodes
        assert sum(outcomes) == successes and all(0 < n <= 60 for n in lengths)
        assert (success_video is not None) == (successes > 0) and (failure_video is not None) == (successes < episodes)
        for video in filter(None, (success_video, failure_video)):
            with iio.get_reader(video, format="FFMPEG") as reader:  # every step's frame and the last
                assert reader.count_frames() == lengths[outcomes.index(video.endswith("-success.mp4"))] + 1
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
    # iteration 1 shared its episodes by iteration 0's evaluation (the least sure, least successful tasks most;
    # the smoke preset's 2 a task leave little to share: tests/warehouse/test_priority.py shows the skew)
    per_task = load_config("smoke").explore.episodes_per_task
    explored = dict(catalog.query("SELECT task_id, count(*) FROM episodes WHERE iteration = 1 GROUP BY 1"))
    tasks = [t for t in load_tasks(Workspace.at(workspace), catalog.query("SELECT min(unit_key) FROM tasks")[0][0])]
    planned = plan_priorities(catalog, "smoke", model_0, tasks, per_task=per_task, floor=0.25)
    assert explored == {p.task_id: p.episodes for p in planned} and sum(explored.values()) == 3 * per_task
    assert all(p.success is not None and p.episodes >= 1 for p in planned)


def test_mlflow_has_the_campaign_its_iterations_and_the_registered_model(finished_campaign):
    workspace, _, _ = finished_campaign
    ws = Workspace.at(workspace)
    client = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=ws.tracking_uri)
    experiment = client.get_experiment_by_name("sim2act")
    [campaign] = client.search_runs([experiment.experiment_id], "tags.`sim2act.kind` = 'campaign'")
    children = client.search_runs([experiment.experiment_id], f"tags.`mlflow.parentRunId` = '{campaign.info.run_id}'")
    # the success-vs-iteration plot, on the campaign run, points from the warehouse's evaluations
    [plot] = client.list_artifacts(campaign.info.run_id, "plots")
    assert plot.path == "plots/smoke-success-by-iteration.png" and plot.file_size > 5_000
    assert sorted(r.data.tags["sim2act.iteration"] for r in children) == ["0", "1"]
    for child in children:
        metrics = child.data.metrics
        assert metrics["explore.episodes"] == 6 and metrics["dataset.triplets"] > 0
        assert "filter.pass_rate" in metrics and "train.loss" in metrics
        lifts = {f"success.lift-{colour}" for colour in ("red", "green", "blue")}
        groups = {f"success.{g}" for g in ("seen", "unseen_paraphrase", "robosuite", "robosuite/seen",
                                           "robosuite/unseen_paraphrase")}
        success = {k for k in metrics if k.startswith("success.") and not k.endswith((".ci_low", ".ci_high"))}
        assert success == lifts | {f"{name}.paraphrase" for name in lifts} | groups
        assert all(metrics[f"{k}.ci_low"] <= metrics[k] <= metrics[f"{k}.ci_high"] for k in success)
        assert metrics["success.seen.ci_high"] - metrics["success.seen.ci_low"] > 0.2  # 3 episodes: a wide interval
        # a point every train.log_every steps as it trains, and one at its last step
        steps = [m.step for m in client.get_metric_history(child.info.run_id, "train.loss")]
        assert len(steps) >= 2 and steps == sorted(set(steps)) and all(s % load_config("smoke").train.log_every == 0 for s in steps[:-1])
        assert {"train.lr", "train.samples_per_s", "train.data_wait"} <= set(metrics)
        videos = [a.path for a in client.list_artifacts(child.info.run_id, "evaluation/lift-red/seen")]
        assert videos and all(path.endswith(("-success.mp4", "-failure.mp4")) for path in videos)
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
    from mlflow.models import get_model_info

    from stages.redeploy import _fluent_tracking  # models:/ URIs resolve through the fluent global

    with _fluent_tracking(ws):
        info = get_model_info("models:/sim2act-smoke/2")
    assert info.signature.inputs.input_names() == ["image", "proprio", "instruction", "family", "episode_id"]
    assert not info.signature.inputs.inputs[-1].required  # served rows may leave it out (acted on alone)
    assert info.signature.outputs.input_names() == ["action", "uncertainty"]


def _ran_on(run, workspace: str) -> bool:
    """Whether a flow run of the smoke campaign ran on `workspace` (its parameter; the top flow's too)."""
    return Path(run.parameters.get("workspace", "")).resolve() == Path(workspace).resolve()


def test_prefect_recorded_the_iterations_the_shards_and_the_explore_progress(finished_campaign, prefect_api):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterType, FlowRunFilter, FlowRunFilterId, FlowRunFilterName,
    )
    from prefect.settings import PREFECT_API_URL, temporary_settings

    names = ["smoke", "smoke-iteration-0", "smoke-iteration-1", "smoke-explore-0", "smoke-explore-1"]
    with temporary_settings({PREFECT_API_URL: prefect_api}), get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=names)))
        # this campaign's: the server is the session's, and another test's smoke campaign has the same run names
        runs = [run for run in runs if _ran_on(run, str(finished_campaign[0]))]
        explores = [run.id for run in runs if "explore" in run.name]
        shards = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=explores)))
        progress = client.read_artifacts(artifact_filter=ArtifactFilter(
            type=ArtifactFilterType(any_=["progress"]), flow_run_id=ArtifactFilterFlowRunId(any_=explores)))
    assert {run.name for run in runs if run.state.is_completed()} == set(names)
    # one task run per shard (of episodes_per_shard episodes: iteration 1 shares its episodes by priority),
    # and the progress artifact at 100%
    per_shard = load_config("smoke").explore.episodes_per_shard
    explored = Catalog(Workspace.at(finished_campaign[0]).catalog).query(
        "SELECT task_id, count(*) FROM episodes GROUP BY iteration, task_id")
    assert sorted(t.name for t in shards) == sorted(
        f"{task_id}-shard-{s}" for task_id, episodes in explored for s in range(-(-episodes // per_shard)))
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


def test_a_compacted_campaign_reruns_without_work(finished_campaign, tmp_path, prefect_api):
    """`sim2act warehouse compact` between runs: the rows, digests and shard rows are what they were, and
    the next run redoes no unit of the compacted iterations (the nightly test of tests/flows/test_service.py
    goes on from a compacted campaign: its next iteration explores, filters and trains on it)."""
    workspace = tmp_path / "workspace"  # a copy: the other tests compare the campaign's rows
    shutil.copytree(finished_campaign[0], workspace)
    before = snapshot(workspace)
    compacted = subprocess.run([SIM2ACT, "warehouse", "compact", "--workspace", str(workspace)],
                               env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)
    assert compacted.returncode == 0 and "compacted into" in compacted.stdout, compacted.stderr[-3000:]
    catalog = Catalog(Workspace.at(workspace).catalog)
    assert catalog.query("SELECT count(*) FROM shards WHERE stored_in IS NULL AND table_name <> 'instructions'") == [(0,)]
    assert snapshot(workspace) == before
    output, _ = run_campaign(workspace, prefect_api)
    assert output.count("stages that ran: 0/7") == 2, output[-3000:]
    assert catalog.query("SELECT count(*) FROM stage_runs WHERE finished_at > (SELECT max(compacted_at) "
                         "FROM compacted)") == [(0,)]
    assert snapshot(workspace) == before


# Where each kill lands: inside generate_tasks (before it registers), explore, train and evaluate,
# and at the seams where filter, index and redeploy start (those take a second or less).
KILL_POINTS = (
    r"generate_tasks: 3 tasks, \d+ instructions; embedding",
    r"explore it0: 3/6 episodes",
    r"filter it0: 6 shards",
    r"index it0: dataset",
    r"train it0: epoch 1/",
    r"evaluate it0: 2/6 cases",
    r"evaluate it0: promote",
)


def test_sigkill_in_every_stage_then_resume_gives_the_same_rows(finished_campaign, tmp_path, prefect_api):
    """One workspace, killed (SIGKILL, the whole process group) once in or at the start of each
    stage of iteration 0 in turn; each run resumes where the last was killed; iteration 0 ends with the
    reference's rows, shard bytes, dataset, model and evaluations (iteration 1 would only repeat it)."""
    reference, _, _ = finished_campaign
    workspace = tmp_path / "killed"
    outputs = []
    for kill_at in KILL_POINTS:
        output, _ = run_campaign(workspace, prefect_api, kill_at, "--set", "iterations=1")
        outputs.append(output)
        if kill_at.startswith("explore"):
            partial = Catalog(Workspace.at(workspace).catalog).query("SELECT count(*) FROM episodes")[0][0]
            assert 0 < partial < 6
    # the run after the explore kill kept the shards that were registered
    assert re.search(r"explore it0: 6 shards \([1-5] already registered\)", outputs[2]), outputs[2][-3000:]
    run_campaign(workspace, prefect_api, None, "--set", "iterations=1")
    assert iteration_zero_snapshot(workspace) == iteration_zero_snapshot(reference)
    assert Catalog(Workspace.at(workspace).catalog).query("SELECT iteration FROM deployments") == [(0,)]


def _on_a_copy(finished_campaign, tmp_path, prefect_api, command: str):
    """(workspace, its catalog, `sim2act <command> --preset smoke` on it) for a copy of the finished campaign's
    workspace: the other tests compare the campaign's rows."""
    workspace = tmp_path / "workspace"
    shutil.copytree(finished_campaign[0], workspace)

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([SIM2ACT, command, "--preset", "smoke", "--workspace", str(workspace), *args],
                              env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)

    return workspace, Catalog(Workspace.at(workspace).catalog), run


def test_eval_scores_a_registered_model_on_a_split_and_on_a_task_file(finished_campaign, tmp_path, prefect_api):
    workspace, catalog, evaluate = _on_a_copy(finished_campaign, tmp_path, prefect_api, "eval")
    before = catalog.query("SELECT count(*) FROM evaluations")

    # the flow already evaluated version 1 on these cases: the same units, nothing rolled out again
    seen = evaluate("--model", "1", "--split", "seen")
    assert seen.returncode == 0, seen.stderr[-3000:]
    assert "3 case(s) of campaign" in seen.stdout and "lift-red" in seen.stdout and "robosuite/seen" in seen.stdout
    [(first_key,)] = catalog.query("SELECT model_key FROM models ORDER BY iteration LIMIT 1")  # version 1's
    by_key = evaluate("--model", first_key, "--split", "seen")  # its checkpoint path is stored relative to the workspace
    assert by_key.returncode == 0 and f"evaluating {first_key}" in by_key.stdout, by_key.stderr[-3000:]
    one_family = evaluate("--model", "1", "--split", "seen", "--family", "robosuite")  # a family's cases: the same units
    assert one_family.returncode == 0 and "3 case(s) of campaign" in one_family.stdout, one_family.stderr[-3000:]
    assert catalog.query("SELECT count(*) FROM evaluations") == before

    spec = tmp_path / "elsewhere.yaml"
    spec.write_text(NEW_TASKS)
    new = evaluate("--model", "champion", "--tasks", str(spec), "--episodes", "2")
    assert new.returncode == 0, new.stderr[-3000:]
    assert "sim2act.stages.evaluate - evaluate it" in new.stderr  # progress lines, with no terminal for a bar
    rows = catalog.query("SELECT task_id, split, episodes, instruction, model_key FROM evaluations "
                         "WHERE suite = 'file:elsewhere.yaml' ORDER BY task_id")
    champion = catalog.query("SELECT champion_model_key FROM deployments ORDER BY iteration DESC LIMIT 1")[0][0]
    assert rows == [("lift-elsewhere-red", "unseen", 2, "elevate the red block", champion),
                    ("lift-elsewhere-yellow", "unseen", 2, "elevate the yellow block", champion)]
    assert re.search(r"^unseen\s+\d/4\s+\d+%\s+\[", new.stdout, re.MULTILINE), new.stdout
    client = MlflowClient(tracking_uri=Workspace.at(workspace).tracking_uri)
    [run] = client.search_runs([client.get_experiment_by_name("sim2act").experiment_id],
                               "tags.`sim2act.kind` = 'evaluation' and tags.`sim2act.suite` = 'file:elsewhere.yaml'")
    assert {"success.unseen", "success.unseen.ci_low", "success.lift-elsewhere-red"} <= set(run.data.metrics)

    for args, named in ((["--model", "v99"], "--model"), (["--model", "champion", "--tasks", "missing.yaml"], "--tasks"),
                        (["--model", "1", "--set", "render.depth=true"], "render.depth"),
                        (["--model", "1", "--set", "render.wrist_camera=true"], "render.wrist_camera"),
                        (["--model", "1", "--family", "navigation"], "--family: campaign has no navigation case")):
        refused = evaluate(*args)
        assert refused.returncode == 2 and named in refused.stderr and len(refused.stderr.splitlines()) == 1, refused.stderr
    assert catalog.query("SELECT count(*) FROM evaluations WHERE suite = 'campaign'") == before


def test_shadow_names_where_a_model_and_the_expert_part_and_registers_nothing(finished_campaign, tmp_path, prefect_api):
    _, catalog, shadow = _on_a_copy(finished_campaign, tmp_path, prefect_api, "shadow")
    before = catalog.query("SELECT count(*) FROM evaluations")

    done = shadow("--model", "champion", "--split", "seen", "--task", "lift-red", "--episodes", "2")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 1 case(s), 2 episodes each" in done.stdout
    [row] = [line for line in done.stdout.splitlines() if line.startswith("| lift-red | seen |")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert re.fullmatch(r"[0-2]/2", cells[2]) and int(cells[3].replace(",", "")) > 0  # success, steps
    assert all(re.fullmatch(r"cos -?[01]\.\d\d|-", cell) for cell in cells[4:6])  # agreement: all, before closing
    assert re.fullmatch(r"\d+\.\d\d", cells[6])  # speed against the expert's
    assert catalog.query("SELECT count(*) FROM evaluations") == before  # a diagnosis, not an evaluation
    assert "Does the first move follow the placement?" not in done.stdout  # 2 placements: nothing to correlate

    # the chunks executed receding one step at a time instead of ensembled, over 3 placements
    receding = shadow("--model", "champion", "--split", "seen", "--task", "lift-red", "--episodes", "3",
                      "--execution", "receding", "--execute-steps", "1")
    assert receding.returncode == 0, receding.stderr[-3000:]
    assert " weights, acting: execution receding, execute_steps 1)" in receding.stdout, receding.stdout
    [placements] = [line for line in receding.stdout.splitlines() if line.startswith("| lift | 3 |")]
    assert all(re.fullmatch(r"[+-][01]\.\d\d|-|policy constant", cell.strip())
               for cell in placements.strip("|").split("|")[2:5]), placements  # r per axis

    # the first step alone of 3 placements: the placement table in seconds
    first = shadow("--model", "champion", "--split", "seen", "--task", "lift-red", "--episodes", "3", "--steps", "1")
    assert first.returncode == 0, first.stderr[-3000:]
    assert "the first 1 step of each episode)" in first.stdout, first.stdout
    assert [line for line in first.stdout.splitlines() if line.startswith("| lift-red | seen |")][0].split("|")[4].strip() == "3"
    assert [line.split("|")[3:6] for line in first.stdout.splitlines() if line.startswith("| lift | 3 |")] == [
        placements.split("|")[3:6]]  # the same first moves as the whole episodes' (receding acts on its first chunk too)

    # the first step from 3 of the placements the champion's training episodes started from
    trained = shadow("--model", "champion", "--split", "seen", "--task", "lift-red", "--episodes", "3", "--steps", "1",
                     "--placements", "trained")
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert "from its training episodes' placements)" in trained.stdout, trained.stdout
    model_key = re.search(r"\((train-[0-9a-f]+)\)", trained.stdout).group(1)
    [(kept,)] = catalog.query(  # the kept lift-red episodes up to the champion's iteration: as many placements, at most 3
        "SELECT count(*) FROM episodes WHERE task_id = 'lift-red' AND iteration <= "
        "(SELECT iteration FROM models WHERE model_key = ?) AND episode_id IN "
        "(SELECT episode_id FROM filter_decisions WHERE kept)", [model_key])
    assert kept > 0 and f"on 1 case(s), {min(kept, 3)} episodes each" in trained.stdout, (kept, trained.stdout)

    for flags, says in ((["--task", "no-such-task"], "lift-red"), (["--steps", "0"], "--steps: expected at least 1, got 0"),
                        (["--execution", "receding", "--execute-steps", "9"], "--execute-steps: expected at most the model's chunk (8)")):
        refused = shadow("--model", "champion", *flags)
        assert refused.returncode == 2 and says in refused.stderr, refused.stderr
        assert len(refused.stderr.splitlines()) == 1, refused.stderr


RL_BUDGET = 128  # env steps per RL baseline: one PPO rollout, 116 SAC updates (SAC took 55 s at 300 here)


def test_baselines_and_the_results_table_beside_a_finished_campaign(finished_campaign, tmp_path, prefect_api):
    workspace = tmp_path / "workspace"  # a copy: the other tests compare the campaign's rows
    shutil.copytree(finished_campaign[0], workspace)
    ws, catalog = Workspace.at(workspace), Catalog(Workspace.at(workspace).catalog)
    with_baselines = [SIM2ACT, "run", "--preset", "smoke", "--workspace", str(workspace),
                      "--set", "baselines.agents=[expert,ppo,sac]", "--set", f"baselines.env_steps={RL_BUDGET}"]
    run = subprocess.run(with_baselines, env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    # the agent that trained first (two workers, two agents) is evaluated beside the other's training, its log
    # lines in the flow run's (a thread of its own that did not carry the run's context would be refused by
    # Prefect's API handler with a warning)
    assert "evaluated beside 1 training(s)" in run.stderr and "without a flow run id" not in run.stderr, run.stderr[-3000:]

    # by default RL from scratch gets the environment steps the campaign's exploration took, per family
    [(explored,)] = catalog.query("SELECT sum(num_steps) FROM episodes WHERE campaign = 'smoke'")
    config = load_config("smoke", None, {"baselines": {"agents": ["ppo", "sac"]}})
    [(tasks_key,)] = catalog.query("SELECT unit_key FROM stage_runs WHERE stage = 'generate_tasks'")
    tasks = load_tasks(ws, tasks_key)
    [(explore_units,)] = catalog.query("SELECT explore_units FROM iterations WHERE iteration = 1")
    planned = rl_units(ws, config, tasks_key, tasks, load_embeddings(ws, tasks_key, config.train.model.language_encoder),
                       exploration_steps(catalog, explore_units))
    assert [(u.algorithm, u.family, u.env_steps) for u in planned] == [("ppo", "robosuite", explored),
                                                                      ("sac", "robosuite", explored)]
    assert all(u.tasks == [t for t in tasks if t.split == "seen"] for u in planned)
    # (here RL_BUDGET steps, to keep the test short)
    trained = {json.loads(s)["algorithm"]: (key, json.loads(s)) for key, s in catalog.query(
        "SELECT unit_key, summary FROM stage_runs WHERE stage = 'baselines'")}
    assert set(trained) == {"ppo", "sac"}
    for key, summary in trained.values():
        assert summary["env_steps"] == RL_BUDGET and summary["family"] == "robosuite"
        assert RL_BUDGET <= summary["steps_taken"] <= RL_BUDGET + 2
        assert summary["episodes"] >= RL_BUDGET // 60  # episodes of at most the horizon, 60 steps
        assert (ws.models / key / "agent.zip").stat().st_size > 100_000
        assert json.loads((ws.models / key / "plan.json").read_text()) == {  # what a report read mid-training names
            "campaign": "smoke", "algorithm": summary["algorithm"], "family": "robosuite", "env_steps": RL_BUDGET}
        assert not (ws.models / key / "progress.json").exists()  # registered: spent, like its checkpoints
        assert not (ws.models / key / "checkpoint").exists()
    # the experts' ceiling is measured before the trainings' hours, not after
    [(expert_done,)] = catalog.query("SELECT max(s.finished_at) FROM stage_runs s JOIN evaluations v "
                                     "ON v.unit_key = s.unit_key WHERE v.model_key = 'expert'")
    [(first_trained,)] = catalog.query("SELECT min(finished_at) FROM stage_runs WHERE stage = 'baselines'")
    assert expert_done < first_trained
    # every baseline meets the campaign's own evaluation cases, with the same seeds
    cases = catalog.query("SELECT task_id, split, instruction, episodes FROM evaluations "
                          "WHERE model_key = (SELECT model_key FROM deployments WHERE iteration = 1) ORDER BY ALL")
    for model_key in ("expert", *(key for key, _ in trained.values())):
        assert catalog.query("SELECT task_id, split, instruction, episodes FROM evaluations "
                             "WHERE model_key = ? AND campaign = 'smoke' ORDER BY ALL", [model_key]) == cases
    [(expert_rate,)] = catalog.query("SELECT sum(successes) / sum(episodes) FROM evaluations WHERE model_key = 'expert'")
    assert expert_rate >= 0.5  # the ceiling: the noiseless expert lifts (100% in docs/experts.md)
    client = MlflowClient(tracking_uri=ws.tracking_uri)
    [campaign] = client.search_runs([client.get_experiment_by_name("sim2act").experiment_id],  # this run's
                                    "tags.`sim2act.kind` = 'campaign'", order_by=["attributes.start_time DESC"],
                                    max_results=1)
    assert {"baseline.expert.success.seen", "baseline.ppo.robosuite.success.seen",
            "baseline.sac.robosuite.success.unseen_paraphrase"} <= set(campaign.data.metrics)

    counts = catalog.query("SELECT stage, count(*) FROM stage_runs GROUP BY ALL ORDER BY ALL")
    again = subprocess.run(with_baselines, env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and catalog.query("SELECT stage, count(*) FROM stage_runs GROUP BY ALL ORDER BY ALL") == counts

    out = tmp_path / "results.md"
    report = subprocess.run([SIM2ACT, "report", "--preset", "smoke", "--workspace", str(workspace), "--out", str(out)],
                            env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=120)
    assert report.returncode == 0, report.stderr[-3000:]
    table = out.read_text()
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| ")}
    assert {"Sim2Act iteration 0 (BC on iteration-0 data)", "Sim2Act iteration 1", "scripted expert, noiseless (ceiling)",
            "PPO from scratch (robosuite)", "SAC from scratch (robosuite)"} <= set(rows)
    assert f"| {RL_BUDGET} |" in rows["PPO from scratch (robosuite)"] and f"| {explored:,} |" in rows["Sim2Act iteration 1"]
    [(successes, episodes)] = catalog.query("SELECT sum(successes), sum(episodes) FROM evaluations "
                                            "WHERE model_key = 'expert' AND split = 'seen'")
    assert f"| {successes}/{episodes} = " in rows["scripted expert, noiseless (ceiling)"]
    for iteration, triplets in catalog.query("SELECT iteration, triplets FROM iterations ORDER BY 1"):
        assert re.search(rf"^\| {iteration} \|.* \| {triplets:,} \|$", table, re.MULTILINE), table
    assert "sim2act report --preset smoke" in table and "| train | 0 |" in table
    assert "Baselines not in the table yet" not in table  # every agent trained and evaluated
    [(latest_triplets,)] = catalog.query("SELECT triplets FROM iterations ORDER BY iteration DESC LIMIT 1")
    [total] = [line for line in table.splitlines() if line.startswith("| all |")]  # the dataset per family and split
    assert total.split(" | ")[7] == f"{latest_triplets:,}", total

    other = subprocess.run([SIM2ACT, "report", "--preset", "smoke", "--set", "name=other", "--workspace", str(workspace)],
                           env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=120)
    held = ", ".join(repr(name) for (name,) in catalog.query(  # the campaigns it ran, of no iteration too
        "SELECT campaign FROM iterations UNION SELECT campaign FROM evaluations WHERE suite = 'campaign' ORDER BY 1"))
    assert "smoke" in held and "adapt" not in held
    assert other.returncode == 2 and other.stderr.strip().endswith(
        f"campaign 'other' has no evaluated iteration in this warehouse (it holds {held}: name it with --preset, "
        f"--config or --set name=...)"), other.stderr


def test_a_campaign_of_no_iteration_trains_and_reports_its_baselines_alone(tmp_path, prefect_api):
    """iterations: 0 on a fresh workspace: the tasks, then the baselines at baselines.env_steps, nothing explored,
    trained or deployed; the report holds their rows, the compute, and no dataset."""
    workspace = tmp_path / "workspace"
    alone = [SIM2ACT, "run", "--preset", "smoke", "--workspace", str(workspace), "--iterations", "0",
             "--set", "baselines.agents=[ppo]", "--set", f"baselines.env_steps={RL_BUDGET}"]
    run = subprocess.run(alone, env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "no iteration (the baselines alone)" in run.stdout and "sim2act eval --model champion" not in run.stdout
    assert "campaign 'smoke': no iteration was evaluated" in run.stdout
    catalog = Catalog(Workspace.at(workspace).catalog)
    assert [stage for (stage,) in catalog.query("SELECT DISTINCT stage FROM stage_runs ORDER BY 1")] == [
        "baselines", "evaluate", "generate_tasks"]
    assert catalog.query("SELECT count(*) FROM iterations") == [(0,)] and catalog.query(
        "SELECT count(*) FROM deployments") == [(0,)]
    [(summary,)] = catalog.query("SELECT summary FROM stage_runs WHERE stage = 'baselines'")
    assert json.loads(summary)["env_steps"] == RL_BUDGET and json.loads(summary)["family"] == "robosuite"
    [(agent_cases,)] = catalog.query("SELECT count(*) FROM evaluations")
    tasks = catalog.query("SELECT split, len(unseen_instructions) > 0 FROM tasks")
    assert agent_cases == len(tasks) + sum(split == "seen" and said for split, said in tasks)  # every planned case

    report = subprocess.run([SIM2ACT, "report", "--preset", "smoke", "--workspace", str(workspace)],
                            env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=120)
    assert report.returncode == 0, report.stderr[-3000:]
    rows = {line.split(" | ")[0].lstrip("| "): line for line in report.stdout.splitlines() if line.startswith("| ")}
    assert f"| {RL_BUDGET} |" in rows["PPO from scratch (robosuite)"] and "evaluating" not in rows["PPO from scratch (robosuite)"]
    assert not any(name.startswith("Sim2Act") for name in rows) and "| baselines | 0 |" in report.stdout
    assert "No iteration: the campaign measures its baselines alone" in report.stdout
    assert "## Dataset per iteration" not in report.stdout and "## Training seeds" not in report.stdout
    assert "## Compute" in report.stdout

    counts = catalog.query("SELECT stage, count(*) FROM stage_runs GROUP BY ALL ORDER BY ALL")
    again = subprocess.run(alone, env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and catalog.query("SELECT stage, count(*) FROM stage_runs GROUP BY ALL ORDER BY ALL") == counts


def test_training_seeds_measure_each_iteration_beside_its_own_model(finished_campaign, tmp_path, prefect_api):
    """evaluate.training_seeds=2 over a finished campaign: no stage redoes a unit (the field is in no unit's key);
    each iteration's dataset is trained again under seed 1 and met by the same evaluation cases, measured and never
    deployed; the summary and the iteration's MLflow run show the two seeds pooled."""
    workspace = tmp_path / "workspace"  # a copy: the other tests compare the campaign's rows
    shutil.copytree(finished_campaign[0], workspace)
    catalog = Catalog(Workspace.at(workspace).catalog)
    deployed = catalog.query("SELECT iteration, model_key, champion_model_key, promoted FROM deployments ORDER BY 1")
    output, _ = run_campaign(workspace, prefect_api, None, "--set", "evaluate.training_seeds=2")
    assert output.count("stages that ran: 0/7") == 2, output[-3000:]
    assert catalog.query("SELECT iteration, model_key, champion_model_key, promoted FROM deployments ORDER BY 1") == deployed
    summary = output[output.index("campaign 'smoke': success per iteration"):]
    from dashboards.protocol import protocol_success
    from stages.evaluate import read_evaluations

    for iteration, own_key, _, _ in deployed:
        trainings = catalog.query(
            "SELECT m.model_key, s.summary FROM models m JOIN stage_runs s ON s.unit_key = m.model_key "
            "WHERE m.iteration = ? ORDER BY m.model_key", [iteration])
        assert sorted(json.loads(summary_json).get("seed", 0) for _, summary_json in trainings) == [0, 1]
        [other_key] = [key for key, _ in trainings if key != own_key]
        by_model = {key: sorted(((t.task_id, t.split, t.instruction, t.episodes), t) for t in [
            evaluation for _, evaluation in read_evaluations(catalog, "v.model_key", "WHERE v.model_key = ?", [key])])
            for key in (own_key, other_key)}
        assert [case for case, _ in by_model[other_key]] == [case for case, _ in by_model[own_key]]  # the same cases
        seen = {f.group: f for f in protocol_success([[t for _, t in by_model[k]] for k in (own_key, other_key)])}["seen"]
        rows = summary.splitlines()
        own_row = next(i for i, line in enumerate(rows) if re.match(rf"  {iteration} +\d+/", line))
        assert re.match(rf"    2 seeds +{seen.mean:.0%} ± {100 * seen.spread:.0f} +\[{seen.ci_low:.0%}, ", rows[own_row + 1]), summary
        ws = Workspace.at(workspace)
        client = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=ws.tracking_uri)
        # the config differs from the first run's (its hash tags the runs): this run's iteration runs are new ones
        [run] = client.search_runs([client.get_experiment_by_name("sim2act").experiment_id],
                                   f"tags.`sim2act.kind` = 'iteration' AND tags.`sim2act.iteration` = '{iteration}'",
                                   order_by=["attributes.start_time DESC"], max_results=1)
        metrics = run.data.metrics
        assert metrics["seeds.success.seen"] == pytest.approx(seen.mean)
        assert metrics["seed1.success.seen"] == pytest.approx(seen.per_seed[1]) and "train.seed1.loss" in metrics


def test_registering_a_model_leaves_its_iteration_run_running(finished_campaign, tmp_path):
    """MLflow's fluent run ends FINISHED as its block closes; the iteration goes on after redeploy registers
    (evaluate.training_seeds' trainings, for hours), so its run stays RUNNING until the flow ends it."""
    from stages.redeploy import _register

    workspace = tmp_path / "workspace"  # a copy: the registry gains a version
    shutil.copytree(finished_campaign[0], workspace)
    ws = Workspace.at(workspace)
    catalog = Catalog(ws.catalog)
    [(model_key, checkpoint)] = catalog.query("SELECT model_key, checkpoint_path FROM models WHERE iteration = 0")
    client = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=ws.tracking_uri)
    run_id = client.create_run(client.get_experiment_by_name("sim2act").experiment_id).info.run_id
    version = _register(ws, catalog, load_config("smoke"), model_key, str(ws.root / checkpoint), run_id)
    assert version >= 2 and client.get_run(run_id).info.status == "RUNNING"


def test_a_registry_of_its_own_is_where_models_are_registered_and_looked_up(finished_campaign, tmp_path, monkeypatch):
    """MLFLOW_REGISTRY_URI (a lab's registry apart from its tracking store): redeploy registered there while
    `sim2act eval --model` looked the version up in the tracking store, and found none."""
    from flows.model_eval import resolve_model
    from stages.redeploy import _register

    workspace = tmp_path / "workspace"
    shutil.copytree(finished_campaign[0], workspace)
    ws = Workspace.at(workspace)
    catalog = Catalog(ws.catalog)
    [(model_key, checkpoint)] = catalog.query("SELECT model_key, checkpoint_path FROM models WHERE iteration = 1")
    tracking = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=ws.tracking_uri)
    versions_before = len(tracking.search_model_versions("name = 'sim2act-smoke'"))
    run_id = tracking.create_run(tracking.get_experiment_by_name("sim2act").experiment_id).info.run_id
    registry = f"sqlite:///{tmp_path / 'lab-registry.db'}"
    monkeypatch.setenv("MLFLOW_REGISTRY_URI", registry)
    assert _register(ws, catalog, load_config("smoke"), model_key, str(ws.root / checkpoint), run_id) == 1
    [version] = MlflowClient(tracking_uri=ws.tracking_uri, registry_uri=registry).search_model_versions("name = 'sim2act-smoke'")
    assert version.tags["sim2act.model_key"] == model_key
    assert len(tracking.search_model_versions("name = 'sim2act-smoke'")) == versions_before  # nothing in the tracking store
    assert resolve_model(ws, load_config("smoke"), "1").model_key == model_key  # version 1 of the lab's registry
    import os

    assert os.environ["MLFLOW_REGISTRY_URI"] == registry and "MLFLOW_TRACKING_URI" not in os.environ  # put back
