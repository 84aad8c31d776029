"""Training on a real warehouse (lift and navigation rollouts by the scripted experts): mixed
discrete and continuous actions, `sim2act train` alone with MLflow metrics, a real SIGKILL and
resume to the same weights, bad selections refused before any work."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from mlflow import MlflowClient

from envs.observation import Observation
from policies.policy import Normaliser, Policy, checkpoint_members
from policies.precision import uses_bf16
from schemas.config import load_config
from schemas.frames import encode_frame
from schemas.keys import unit_key
from schemas.workspace import Workspace
from stages.explore import run_explore
from stages.filter import run_filter
from stages.generate_tasks import run_generate_tasks
from stages.index import IndexResult, latest_index, run_index
from warehouse.tasks import load_embeddings, load_tasks
from stages.train import (EXECUTION_FIELDS, STAGE, VERSION, TrainingCollate, action_targets, drop_proprio, random_shift,
                          run_train, train_unit_key, training_device)
from tests.conftest import SIM2ACT
from warehouse.catalog import Catalog

CAMPAIGN = {
    "name": "train-test",
    "tasks": {"specs": ["lift", "nav-room"], "colours": ["red", "green"], "horizon": {"lift": 40, "nav-room": 12}},
    "explore": {"episodes_per_task": 2, "episodes_per_shard": 2, "workers": 2},
    "filter": {"min_return": 0.0},
    "train": {"epochs": 3, "batch_size": 16, "checkpoint_every": 4, "log_every": 2, "loader_workers": 1,
              "model": {"dim": 32, "heads": 4, "vision_depth": 1, "fusion_depth": 1}},
}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> tuple[Path, Path]:
    """(config file, workspace holding iteration 0's dataset, nothing trained)."""
    root = tmp_path_factory.mktemp("train")
    config_file = root / "campaign.yaml"
    config_file.write_text(yaml.safe_dump(CAMPAIGN))
    workspace = Workspace.at(root / "workspace")
    _iteration_zero_dataset(workspace, load_config("smoke", config_file))
    return config_file, workspace.root


def _iteration_zero_dataset(workspace: Workspace, config) -> tuple[str, dict, IndexResult]:
    """Generate, explore, filter and index iteration 0 in a new workspace: (tasks key, embeddings, dataset)."""
    workspace.create()
    Catalog(workspace.catalog).initialise()
    tasks = run_generate_tasks(workspace, config)
    embeddings = load_embeddings(workspace, tasks.unit_key, config.train.model.language_encoder)
    explored = run_explore(workspace, config, 0, load_tasks(workspace, tasks.unit_key), None, embeddings)
    filtered = run_filter(workspace, config, 0, explored.unit_keys)
    return tasks.unit_key, embeddings, run_index(workspace, config, 0, explored.unit_keys, filtered.unit_keys, None)


def _copy(campaign, tmp_path: Path, name: str) -> Path:
    target = tmp_path / name
    shutil.copytree(campaign[1], target)
    return target


def _train(config_file: Path, workspace: Path, *extra: str, **popen) -> subprocess.Popen:
    return subprocess.Popen([SIM2ACT, "train", "--preset", "smoke", "--config", str(config_file),
                             "--workspace", str(workspace), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)


def _weights(workspace: Path) -> list[dict[str, torch.Tensor]]:
    [checkpoint] = (workspace / "models").glob("*/policy.pt")
    return checkpoint_members(torch.load(checkpoint, weights_only=False))


def test_a_sigkilled_ensemble_training_resumes_to_the_same_weights(campaign, tmp_path):
    """Killed in its second member: the first member's finished state survives, the second resumes
    from its last checkpoint, and both end as a straight run's."""
    config_file, ensemble = campaign[0], ("--set", "train.ensemble=2")
    straight, killed = _copy(campaign, tmp_path, "straight"), _copy(campaign, tmp_path, "killed")
    run = _train(config_file, straight, *ensemble)
    output = run.communicate(timeout=600)[0]
    assert run.returncode == 0, output

    victim = _train(config_file, killed, *ensemble, start_new_session=True)
    deadline = time.monotonic() + 300
    states = []
    while not states and victim.poll() is None and time.monotonic() < deadline:
        states = list((killed / "models").glob("*/train-state-1.pt"))
        time.sleep(0.05)
    assert states, victim.communicate()[0]
    time.sleep(0.3)  # a few more steps past the checkpoint, lost with the kill
    os.killpg(victim.pid, signal.SIGKILL)  # the trainer and its loader worker
    victim.wait()
    assert victim.returncode == -signal.SIGKILL
    saved = [torch.load(states[0].with_name(f"train-state-{m}.pt"), weights_only=False) for m in (0, 1)]
    killed_at = saved[0]["step"] + saved[1]["step"]  # the first member finished: its steps, then the second's
    # as if the killed part had run in the other precision (another host, train.amp changed): the resume says
    # so; the flag is all that differs, so the weights below still end as the straight run's
    torch.save({**saved[1], "bf16": not saved[1]["bf16"]}, states[0].with_name("train-state-1.pt"))

    resumed = _train(config_file, killed, *ensemble)
    output = resumed.communicate(timeout=600)[0]
    assert resumed.returncode == 0 and f"resumed at step {killed_at}" in output, output
    assert "the training mixes precisions" in output and output.count("mixes precisions") == 1, output
    # the compute it took counts the killed run's training too, not only the resumed part
    [(wall_s,)] = Catalog(Workspace.at(killed).catalog).query("SELECT wall_s FROM stage_runs WHERE stage = 'train'")
    assert wall_s > saved[0]["wall_s"] + saved[1]["wall_s"] > 0
    a, b = _weights(straight), _weights(killed)
    assert len(a) == len(b) == 2 and any(not torch.equal(a[0][k], a[1][k]) for k in a[0])  # two different models
    assert all(x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x) for x, y in zip(a, b))
    assert not list((killed / "models").glob("*/train-state-*.pt"))  # removed once the model is registered

    again = _train(config_file, killed, *ensemble)
    assert "already trained" in again.communicate(timeout=300)[0] and again.returncode == 0


def test_a_chunked_training_on_mixed_actions_registers_its_average_and_acts_per_episode(campaign, tmp_path):
    """Chunks over lift (continuous) and navigation (discrete) episodes: the reader's look-ahead, the
    chunk targets and their mask, both heads; the checkpoint holds the average and the last weights."""
    workspace = _copy(campaign, tmp_path, "chunked")
    run = _train(campaign[0], workspace, "--set", "train.model.chunk=3")
    output = run.communicate(timeout=600)[0]
    assert run.returncode == 0 and "action_mse_chunk" in output, output
    [path] = (workspace / "models").glob("*/policy.pt")
    state = torch.load(path, weights_only=False)
    assert state["weights"] == "ema 0.999" and state["model_config"]["chunk"] == 3
    assert any(not torch.equal(state["members"][0][k], state["final_members"][0][k]) for k in state["members"][0])
    [(summary,)] = Catalog(Workspace.at(workspace).catalog).query("SELECT summary FROM stage_runs WHERE stage = 'train'")
    assert json.loads(summary)["chunk"] == 3 and json.loads(summary)["weights"] == "ema 0.999"
    recipe = json.loads(summary)["recipe"]  # what the protocol pools seeds by: every setting but the seed
    assert recipe["model"]["chunk"] == 3 and recipe["targets"] == "expert" and "seed" not in recipe
    assert json.loads(summary)["precision"] == ("bf16" if uses_bf16(training_device("auto"), True) else "fp32")
    embeddings = load_embeddings(Workspace.at(workspace), *Catalog(Workspace.at(workspace).catalog).query(
        "SELECT DISTINCT unit_key FROM tasks")[0], "all-MiniLM-L6-v2")
    policy = Policy.load(path, embeddings)
    obs = Observation(np.zeros((84, 84, 3), np.uint8), np.zeros(9, np.float32), {})
    instruction = next(iter(embeddings))
    for family, shape in (("robosuite", (7,)), ("navigation", (1,))):
        actor = policy.episode(family)
        actions = [actor(obs, instruction).action for _ in range(4)]
        assert all(a.shape == shape and np.isfinite(a).all() for a in actions)


def test_train_alone_logs_losses_lr_throughput_and_the_dataset_to_mlflow(campaign, tmp_path):
    workspace = _copy(campaign, tmp_path, "logged")
    run = _train(campaign[0], workspace)
    output = run.communicate(timeout=600)[0]
    assert run.returncode == 0, output
    assert "sim2act.stages.train - train it0: epoch 1/" in output  # progress lines, with no terminal to draw a bar on
    client = MlflowClient(tracking_uri=Workspace.at(workspace).tracking_uri)
    [iteration_run] = client.search_runs(
        [client.get_experiment_by_name("sim2act").experiment_id], "tags.`sim2act.kind` = 'iteration'")
    metrics = iteration_run.data.metrics
    for name in ("train.loss", "train.infonce", "train.bc", "train.action_mse", "train.action_mse_dy", "train.discrete_ce",
                 "train.discrete_accuracy", "train.lr", "train.samples_per_s", "train.data_wait"):
        assert name in metrics, name
    history = client.get_metric_history(iteration_run.info.run_id, "train.loss")
    assert [m.step for m in history] == sorted(m.step for m in history) and len(history) >= 3
    lr = [m.value for m in client.get_metric_history(iteration_run.info.run_id, "train.lr")]
    peak = lr.index(max(lr))
    assert lr[peak:] == sorted(lr[peak:], reverse=True) and lr[-1] < 0.05 * lr[peak]  # cosine decay to ~0
    [dataset] = iteration_run.inputs.dataset_inputs
    [(digest,)] = Catalog(Workspace.at(workspace).catalog).query("SELECT dataset_digest FROM models")
    assert dataset.dataset.digest == digest
    # the campaign and iteration runs this command opened (no campaign had run here) end with it
    runs = client.search_runs([client.get_experiment_by_name("sim2act").experiment_id])
    assert sorted(r.data.tags["sim2act.kind"] for r in runs) == ["campaign", "iteration"]
    assert {r.info.status for r in runs} == {"FINISHED"}


def test_the_policy_acts_on_both_kinds_of_action_with_an_uncertainty(campaign, tmp_path):
    workspace = Workspace.at(_copy(campaign, tmp_path, "inproc"))
    # with the auxiliary state head (the default): trained, then unread when acting; a budget in steps
    config = load_config("smoke", campaign[0], {"train": {"loader_workers": 0, "steps": 20}})
    catalog = Catalog(workspace.catalog)
    [(tasks_key,)] = catalog.query("SELECT DISTINCT unit_key FROM tasks")
    embeddings = load_embeddings(workspace, tasks_key, config.train.model.language_encoder)
    result = run_train(workspace, config, 0, latest_index(workspace, config.name), tasks_key, embeddings)
    per_epoch = math.ceil(result.samples / config.train.batch_size)
    [(summary,)] = catalog.query("SELECT summary FROM stage_runs WHERE stage = 'train'")
    steps = json.loads(summary)["steps"]
    assert steps == len(result.history) * per_epoch and steps - per_epoch < 20 <= steps  # the fewest whole epochs
    assert "discrete_accuracy" in result.history[-1] and "state_mse" in result.history[-1]
    longest = catalog.query("SELECT max(len(qpos)) FROM steps")[0][0]
    assert torch.load(result.checkpoint, weights_only=False)["dims"]["state_dim"] == longest
    policy = Policy.load(Path(result.checkpoint))  # no cached embeddings: encodes on first use
    obs = Observation(np.zeros((84, 84, 3), np.uint8), np.zeros(9, np.float32), {})
    nav = policy.act(obs, "go to the red room", "navigation")
    arm = policy.act(obs, "lift the red cube", "robosuite")
    assert nav.action.shape == (1,) and float(nav.action[0]).is_integer() and 0 <= nav.action[0] < 4
    assert arm.action.shape == (7,) and np.all(np.abs(arm.action) <= 1.0)
    assert 0.0 <= nav.uncertainty <= np.log(4) + 1e-6 and np.isfinite(arm.uncertainty)


def test_a_campaign_that_records_depth_trains_and_runs_an_rgbd_policy(tmp_path):
    config = load_config("smoke", overrides={
        **CAMPAIGN, "name": "rgbd", "render": {"depth": True},
        "tasks": {"specs": ["lift", "nav-room"], "colours": ["red"], "horizon": {"lift": 12, "nav-room": 8}},
        "explore": {"episodes_per_task": 1, "workers": 1},
        "train": {**CAMPAIGN["train"], "epochs": 1, "loader_workers": 0}})
    workspace = Workspace.at(tmp_path / "rgbd")
    tasks_key, embeddings, dataset = _iteration_zero_dataset(workspace, config)
    catalog = Catalog(workspace.catalog)
    [(triplets, with_depth)] = catalog.query("SELECT count(*), count(obs_depth) + count(next_obs_depth) - count(*) FROM triplets")
    assert triplets == 20 and with_depth == triplets  # every o_t and o_{t+1} has its depth map

    result = run_train(workspace, config, 0, dataset, tasks_key, embeddings)
    policy = Policy.load(Path(result.checkpoint))
    assert policy.dims.channels == 4
    obs = Observation(np.zeros((84, 84, 3), np.uint8), np.zeros(9, np.float32), {}, np.ones((84, 84), np.float32))
    assert policy.act(obs, "lift the red cube", "robosuite").action.shape == (7,)
    with pytest.raises(ValueError, match=r"reads RGB-D \(a campaign with render.depth\) frames, got 3 channels"):
        policy.act(Observation(obs.image, obs.proprio, {}), "lift the red cube", "robosuite")


def test_a_bad_selection_is_refused_before_any_work(campaign, tmp_path):
    workspace = _copy(campaign, tmp_path, "refused")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({**CAMPAIGN, "train": {**CAMPAIGN["train"], "where": "no_such_column > 1"}}))
    run = _train(bad, workspace)
    output = run.communicate(timeout=300)[0]
    assert run.returncode == 2 and output.strip().splitlines() == [
        "sim2act: train.where: 'no_such_column > 1': Binder Error: Referenced column \"no_such_column\" not found "
        "in FROM clause!"], output
    empty = tmp_path / "empty.yaml"
    empty.write_text(yaml.safe_dump({**CAMPAIGN, "train": {**CAMPAIGN["train"], "where": "task_id = 'nope'"}}))
    run = _train(empty, workspace)
    output = run.communicate(timeout=300)[0]
    assert run.returncode != 0 and "leaves no step" in output
    assert not list((workspace / "models").glob("*/*"))
    # a steps shard of the dataset quarantined since it was indexed: training would read less than its key says
    catalog = Catalog(Workspace.at(workspace).catalog)
    [(path,)] = catalog.query("SELECT path FROM shards WHERE table_name = 'steps' ORDER BY path LIMIT 1")
    assert catalog.quarantine(path, "a test")
    run = _train(campaign[0], workspace)
    output = run.communicate(timeout=300)[0]
    assert run.returncode != 0 and "has changed since it was indexed" in output, output
    assert not list((workspace / "models").glob("*/*"))
    missing = _train(campaign[0], tmp_path / "nowhere")
    output = missing.communicate(timeout=300)[0]
    assert missing.returncode == 2 and "no warehouse catalog" in output, output


def test_the_targets_are_the_expert_labels_where_recorded_else_the_executed_actions():
    executed, labels = [[0.5] * 7, [0.2] * 7, [2.0]], [[0.1] * 7, None, [1.0]]
    assert action_targets(executed, labels, "expert") == [[0.1] * 7, [0.2] * 7, [1.0]]
    assert action_targets(executed, labels, "executed") == executed
    identity = Normaliser.fit(np.zeros((0, 9)), 9)  # no values: mean 0, std 1
    collate = TrainingCollate(Normaliser.fit(np.zeros((0, 7)), 7), identity,
                              None, "expert")
    frame = encode_frame(np.zeros((8, 8, 3), np.uint8))
    rows = [{"instruction": "x", "image": frame, "depth": None, "proprio": [0.0] * 9, "action": a, "expert_action": e,
             "qpos": [0.0]} for a, e in zip(executed, labels)]
    batch = collate(rows)
    assert batch["action_index"].tolist() == [-1, -1, 1]  # a navigation label stays discrete
    assert batch["action"][0] == pytest.approx(np.full(7, 0.1), abs=1e-3)  # the label, not the noisy action
    assert batch["action"][1] == pytest.approx(np.full(7, 0.2), abs=1e-3)  # no label recorded: the action


def test_states_of_different_lengths_are_padded_normalised_and_masked():
    identity = Normaliser.fit(np.zeros((0, 9)), 9)
    state = Normaliser(np.array([1.0, 0.0, 0.0, 0.0], np.float32), np.array([2.0, 1.0, 1.0, 1.0], np.float32))
    collate = TrainingCollate(Normaliser.fit(np.zeros((0, 7)), 7), identity, None, "expert", state)
    frame = encode_frame(np.zeros((8, 8, 3), np.uint8))
    rows = [{"instruction": "x", "image": frame, "depth": None, "proprio": [0.0] * 9, "action": [0.0] * 7,
             "expert_action": None, "qpos": qpos} for qpos in ([3.0, 1.0, 2.0, 4.0], [5.0, 1.0])]
    batch = collate(rows)
    assert batch["state"].tolist() == [[1.0, 1.0, 2.0, 4.0], [2.0, 1.0, 0.0, 0.0]]
    assert batch["state_mask"].tolist() == [[1.0] * 4, [1.0, 1.0, 0.0, 0.0]]
    assert "state" not in TrainingCollate(Normaliser.fit(np.zeros((0, 7)), 7), identity, None, "expert")(rows)


def test_without_the_state_loss_a_start_model_or_a_step_budget_a_model_keeps_the_key_it_had_before_the_fields_existed(campaign):
    workspace = Workspace.at(campaign[1])
    legacy = load_config("smoke", campaign[0], {"train": {"state_weight": 0.0, "ema": None, "model": {"chunk": 1}}})
    [(tasks_key,)] = Catalog(workspace.catalog).query("SELECT DISTINCT unit_key FROM tasks")
    dataset = latest_index(workspace, legacy.name)
    added = {name: True for name in EXECUTION_FIELDS | {"state_weight", "init_from", "steps", "seed", "ema", "language_augment",
                                                  "proprio_dropout"}}
    added["model"] = {"chunk": True, "execution": True, "execute_steps": True, "ensemble_decay": True}
    before = {"train": legacy.train.model_dump(exclude=added), "seed": legacy.seed,
              "image": legacy.render.image_size, "depth": legacy.render.depth}
    assert train_unit_key(legacy, dataset, tasks_key) == unit_key(STAGE, VERSION, before, [dataset.dataset_digest, tasks_key])
    default = load_config("smoke", campaign[0])  # the state loss and the EMA on: another model
    assert train_unit_key(default, dataset, tasks_key) != train_unit_key(legacy, dataset, tasks_key)
    # a chunked model, another training seed: other models; the seed's default keeps the key
    for change in ({"model": {"chunk": 4}}, {"seed": 1}, {"model": {"chunk": 4, "execution": "receding"}}):
        other = load_config("smoke", campaign[0], {"train": {"state_weight": 0.0, "ema": None, "model": {"chunk": 1}, **change}})
        assert train_unit_key(other, dataset, tasks_key) != train_unit_key(legacy, dataset, tasks_key), change
    wrist = load_config("smoke", campaign[0], {"train": {"state_weight": 0.0, "ema": None, "model": {"chunk": 1}},
                                                "render": {"wrist_camera": True}})
    assert train_unit_key(wrist, dataset, tasks_key) != train_unit_key(legacy, dataset, tasks_key)  # reads two views


def test_proprio_dropout_zeroes_whole_rows_reproducibly_and_draws_nothing_when_off():
    proprio = torch.rand(2000, 9) + 1.0  # no row is zero by chance
    generator = torch.Generator().manual_seed(0)
    assert drop_proprio(proprio, 0.0, generator) is proprio
    assert torch.equal(torch.rand(3, generator=generator), torch.rand(3, generator=torch.Generator().manual_seed(0)))
    dropped = drop_proprio(proprio, 0.25, torch.Generator().manual_seed(1))
    zero = (dropped == 0).all(-1)
    assert ((dropped == 0) == zero.unsqueeze(-1)).all()  # a row goes whole or stays whole
    assert torch.equal(dropped[~zero], proprio[~zero])
    assert 0.2 < zero.float().mean() < 0.3
    assert torch.equal(drop_proprio(proprio, 0.25, torch.Generator().manual_seed(1)), dropped)
    assert (drop_proprio(proprio, 1.0) == 0).all()


def test_random_shift_moves_whole_frames_by_at_most_the_pad():
    frames = torch.rand(16, 3, 12, 12)
    assert random_shift(frames, 0) is frames
    shifted = random_shift(frames, 2, torch.Generator().manual_seed(0))
    assert shifted.shape == frames.shape
    padded = torch.nn.functional.pad(frames, (2, 2, 2, 2), mode="replicate")
    moves = set()
    for i in range(16):  # each output frame is one crop of the edge-padded frame
        [(dy, dx)] = [(dy, dx) for dy in range(5) for dx in range(5)
                      if torch.equal(padded[i, :, dy:dy + 12, dx:dx + 12], shifted[i])]
        moves.add((dy, dx))
    assert len(moves) > 4  # frames of one batch move independently
    torch.rand(3)  # the global generator moves (as the DataLoader's start moves it): the shifts do not
    assert torch.equal(random_shift(frames, 2, torch.Generator().manual_seed(0)), shifted)


def test_random_shift_moves_each_view_of_a_two_view_frame_within_itself():
    """A frame of the main and the hand's view (render.wrist_camera): no pixel of one view shifts into
    the other, and the two views of a frame move independently."""
    main, hand = torch.rand(8, 3, 12, 12), torch.rand(8, 3, 12, 12) + 2.0  # told apart by range
    shifted = random_shift(torch.cat([main, hand], dim=3), 2, torch.Generator().manual_seed(0), views=2)
    assert shifted.shape == (8, 3, 12, 24)
    assert shifted[..., :12].max() < 1.0 and shifted[..., 12:].min() >= 2.0

    def move(padded: torch.Tensor, out: torch.Tensor) -> tuple[int, int]:
        [found] = [(dy, dx) for dy in range(5) for dx in range(5) if torch.equal(padded[:, dy:dy + 12, dx:dx + 12], out)]
        return found

    pad = lambda frames: torch.nn.functional.pad(frames, (2, 2, 2, 2), mode="replicate")  # noqa: E731
    moves = [(move(pad(main)[i], shifted[i, :, :, :12]), move(pad(hand)[i], shifted[i, :, :, 12:])) for i in range(8)]
    assert any(a != b for a, b in moves)


def test_a_wrist_camera_campaign_trains_a_two_view_model_on_its_frames():
    """model_dims follows render.wrist_camera, and one optimiser step runs on (B, 84, 168, 3) frames."""
    from policies.model import VLAModel
    from stages.train import model_dims, optimiser_for, train_step

    config = load_config("smoke", None, {"render": {"wrist_camera": True}, "train": {"model": {"chunk": 1}}})
    model = VLAModel(config.train.model, model_dims(config))
    assert model.dims.views == 2 and model.wrist_vision is not None
    generator = torch.Generator().manual_seed(0)
    batch = {"image": torch.randint(0, 256, (4, 84, 168, 3), dtype=torch.uint8, generator=generator),
             "language": torch.randn(4, model.dims.language_dim, generator=generator), "instruction": ["x"] * 4,
             "proprio": torch.randn(4, model.dims.proprio_dim, generator=generator),
             "action": torch.randn(4, model.dims.action_dim, generator=generator),
             "action_index": torch.full((4,), -1)}
    optimiser = optimiser_for(model, config.train)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda _: 1.0)
    before = [p.detach().clone() for p in model.wrist_vision.parameters()]
    losses = train_step(model, optimiser, schedule, batch, config.train, torch.device("cpu"),
                        torch.Generator().manual_seed(0))
    assert math.isfinite(losses.total.item())
    assert any(not torch.equal(a, b) for a, b in zip(before, model.wrist_vision.parameters()))  # the hand's view learns


def test_language_augmentation_rewords_instructions_reproducibly_and_brings_their_embeddings():
    from stages.train import reworded_instructions

    identity = Normaliser(np.zeros(9, np.float32), np.ones(9, np.float32))
    frame = lambda value: encode_frame(np.full((8, 8, 3), value, np.uint8))  # noqa: E731
    rows = [{"instruction": "pick up the red block", "image": frame(i), "depth": None, "proprio": [0.0] * 9,
             "action": [0.0] * 7, "expert_action": None, "qpos": []} for i in range(40)]
    rewordings, embeddings = reworded_instructions({"pick up the red block": np.zeros(384, np.float32)},
                                                   "all-MiniLM-L6-v2", encode_them=True)
    options = rewordings["pick up the red block"]
    assert len(options) == 8 and all(text in embeddings and embeddings[text].shape == (384,) for text in options)
    half = TrainingCollate(Normaliser.fit(np.zeros((0, 7)), 7), identity, embeddings, "expert",
                           rewordings=rewordings, augment=0.5)
    said = half(rows)["instruction"]
    assert said == half(rows)["instruction"]  # the same rows draw the same rewordings (a resume reads alike)
    assert 8 < sum(text != "pick up the red block" for text in said) < 32 and set(said) - {"pick up the red block"} <= set(options)
    assert half(rows[::-1])["instruction"] != said[::-1]  # another batch, other draws
    none = TrainingCollate(Normaliser.fit(np.zeros((0, 7)), 7), identity, embeddings, "expert")
    assert set(none(rows)["instruction"]) == {"pick up the red block"}


def test_a_long_training_where_bf16_may_pay_measures_its_own_step_once_per_host_model_and_batch(
        campaign, tmp_path, monkeypatch):
    import stages.train as train

    workspace = Workspace.at(_copy(campaign, tmp_path, "precision"))
    config = load_config("smoke", campaign[0], {"train": {"loader_workers": 0, "steps": 4}})
    [(tasks_key,)] = Catalog(workspace.catalog).query("SELECT DISTINCT unit_key FROM tasks")
    embeddings = load_embeddings(workspace, tasks_key, config.train.model.language_encoder)
    dataset = latest_index(workspace, config.name)
    monkeypatch.setattr(train, "cpu_bf16_may_pay", lambda device: True)
    run_train(workspace, config, 0, dataset, tasks_key, embeddings)
    assert not workspace.precision_choices.exists()  # 4 steps of 16: far below PROBE_MIN_SAMPLES, unmeasured

    monkeypatch.setattr(train, "PROBE_MIN_SAMPLES", 0)
    seeded = config.model_copy(update={"train": config.train.model_copy(update={"seed": 1})})
    result = run_train(workspace, seeded, 0, dataset, tasks_key, embeddings)
    [(key, choice)] = json.loads(workspace.precision_choices.read_text()).items()
    assert "batch 16" in key and "threads" in key and choice["fp32_s"] > 0 and choice["bf16_s"] > 0
    assert choice["speedup"] == pytest.approx(choice["fp32_s"] / choice["bf16_s"])
    assert result.history and math.isfinite(result.history[-1]["loss"])

    # short trainings again (an adaptation's fine-tunings): they do not measure, they take the measured choice
    monkeypatch.setattr(train, "PROBE_MIN_SAMPLES", 10**9)
    catalog = Catalog(workspace.catalog)
    for seed, speedup, taken in ((2, 2.0, "bf16"), (3, 1.0, "fp32")):  # as if bf16 had won, then lost
        workspace.precision_choices.write_text(json.dumps({key: {**choice, "speedup": speedup}}))
        short = config.model_copy(update={"train": config.train.model_copy(update={"seed": seed})})
        trained = run_train(workspace, short, 0, dataset, tasks_key, embeddings)
        [(precision,)] = catalog.query("SELECT json_extract_string(summary, '$.precision') FROM stage_runs "
                                       "WHERE unit_key = ?", [trained.model_key])
        assert precision == taken, seed
