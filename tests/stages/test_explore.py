"""The explore stage's own decisions: who explores which episode, what a shard records (DAgger
labels, a VLM explorer's counters), what a failure mid-episode costs, and how a curriculum
explores long-horizon tasks by chaining their sub-tasks. Real navigation
scenes, rendered; the VLM is a local server speaking the chat-completions protocol."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from envs.navigation_env import ACTIONS, ROOM_SIZE
from envs.observation import ACTION_DIM, PROPRIO_DIM
from envs.rollout import worker_env
from policies.model import ModelDims, VLAModel
from policies.policy import Normaliser, Policy, policy_state
from schemas.config import CampaignConfig, ExploreConfig, ModelConfig, TasksConfig, VlmExplorerConfig
from schemas.keys import unit_key
from schemas.workspace import Workspace
from stages.explore import (CHAINED, EXPERT, STAGE, VERSION, PolicyExplorer, _explorer, curriculum_subgoals, expert_takeover,
                            plan_explore, run_explore, run_explore_unit)
from envs.suite import generate_tasks
from tests.chat_server import closed_port
from warehouse.catalog import Catalog
from warehouse.shard_writer import read_shard


def _config(**explore) -> CampaignConfig:
    return CampaignConfig(
        name="explore-test",
        tasks=TasksConfig(specs=["nav-room"], colours=["red", "green"], horizon={"nav-room": 6}),
        explore=ExploreConfig(**{"episodes_per_task": 4, "episodes_per_shard": 4, "workers": 1, **explore}),
    )


def _plan(config: CampaignConfig, tmp_path, iteration: int = 0, policy: PolicyExplorer | None = None):
    tasks = generate_tasks(config.tasks, config.seed)
    embeddings = {text: np.zeros(384, dtype=np.float32) for t in tasks for text in t.instructions}
    return plan_explore(config, iteration, tasks, policy, embeddings, Workspace.at(tmp_path).create())


def test_the_policy_and_the_vlm_take_their_shares_of_each_task(tmp_path):
    vlm = VlmExplorerConfig(url="http://127.0.0.1:1/v1", model="tiny-vlm")
    config = _config(episodes_per_task=10, episodes_per_shard=5, policy_fraction=0.4, vlm=vlm, vlm_fraction=0.5)
    policy = PolicyExplorer(name="policy:m/1", model_key="m1", checkpoint="unused")
    units = _plan(config, tmp_path, 1, policy)
    per_task = {task: Counter(e.explorer for u in units if u.task.task_id == task for e in u.episodes)
                for task in {u.task.task_id for u in units}}
    assert all(c == {"policy:m/1": 4, "vlm:tiny-vlm": 3, EXPERT: 3} for c in per_task.values())
    assert [e.explorer for u in _plan(config, tmp_path, 1, policy) for e in u.episodes] == \
        [e.explorer for u in units for e in u.episodes]  # drawn from seeds: the same every time
    iteration_0 = Counter(e.explorer for u in _plan(config, tmp_path) for e in u.episodes)
    assert iteration_0 == {"vlm:tiny-vlm": 10, EXPERT: 10}  # no policy yet: the VLM takes half of all


def _shards(unit):
    files = {f.table: f.path for f in run_explore_unit(unit)}
    return read_shard("episodes", files["episodes"]).to_pylist(), read_shard("steps", files["steps"]).to_pylist()


def test_a_shard_records_vlm_counters_and_the_experts_labels_everywhere(tmp_path, serve_chat):
    server = serve_chat(json.dumps({"action": "forward"}))
    config = _config(vlm=VlmExplorerConfig(url=server.url, model="tiny-vlm"), vlm_fraction=0.5)
    unit = _plan(config, tmp_path)[0]
    episodes, steps = _shards(unit)
    by_explorer = Counter(e["explorer"] for e in episodes)
    assert by_explorer == {"vlm:tiny-vlm": 2, EXPERT: 2}
    for episode in episodes:
        own = [s for s in steps if s["episode_id"] == episode["episode_id"]]
        assert episode["error"] is None and len(own) == episode["num_steps"] > 0
        assert all(len(s["expert_action"]) == 1 for s in own)  # the noiseless expert, on every state
        later = {"mesh_detail", "wrist_camera", "decimate_colliding"}  # in the unit's summary
        assert episode["render"] == config.render.model_dump(exclude=later)
        if episode["explorer"] == EXPERT:
            assert json.loads(episode["explorer_stats"]) == {"expert_noise": config.explore.expert_noise}
        else:
            stats = json.loads(episode["explorer_stats"])
            assert stats["calls"] == stats["steps"] == len(own) and stats["invalid_answers"] == 0
            assert all(s["action"] == [ACTIONS.index("forward")] for s in own)
    assert len(server.requests) == sum(1 for s in steps if s["episode_id"] in
                                       {e["episode_id"] for e in episodes if e["explorer"] != EXPERT})


def test_the_expert_takes_over_its_share_of_the_policys_steps_and_labels_every_one():
    """DAgger's beta: per step the expert's action is executed with probability `share`; the policy is
    asked at every step (its chunks stay in step), the expert once per step, and the label is the
    expert's action in every state either way."""
    for share, expected in ((0.0, 0), (1.0, 300), (0.5, None)):
        calls = Counter()

        def policy(obs):
            calls["policy"] += 1
            return np.full(ACTION_DIM, -1.0, dtype=np.float32)

        def expert(obs):
            calls["expert"] += 1
            return np.full(ACTION_DIM, float(obs), dtype=np.float32)  # says which state it saw

        explorer, label = expert_takeover(policy, expert, share, np.random.default_rng(0))
        driven = 0
        for state in range(300):  # the rollout's order: the actor, then the labeller, on one state
            action = explorer.act(state)
            assert label(state)[0] == state
            driven += int(action[0] == state)
        assert calls == {"policy": 300, "expert": 300}
        assert explorer.stats() == {"expert_takeover": share, "expert_steps": driven, "steps": 300}
        assert driven == expected if expected is not None else 120 < driven < 180


def test_expert_takeover_needs_the_labelling_expert():
    with pytest.raises(ValueError, match="expert_takeover: expected expert_labels true"):
        ExploreConfig(expert_takeover=0.5, expert_labels=False)
    with pytest.raises(ValueError, match=r"expert_takeover\.constrained-float\s+Input should be less than or equal to 1"):
        ExploreConfig(expert_takeover=1.5)


def test_a_takeover_schedule_gives_each_iteration_its_share_and_shares_keys_with_a_single_share(tmp_path):
    falling = ExploreConfig(expert_takeover=[0.5, 0.25, 0.125])
    assert [falling.takeover_of(i) for i in range(6)] == [0.5, 0.5, 0.25, 0.125, 0.125, 0.125]
    assert [ExploreConfig(expert_takeover=0.3).takeover_of(i) for i in (0, 1, 4)] == [0.3, 0.3, 0.3]
    with pytest.raises(ValueError, match="expert_takeover: the schedule is empty"):
        ExploreConfig(expert_takeover=[])
    with pytest.raises(ValueError, match="expert_takeover: expected expert_labels true"):
        ExploreConfig(expert_takeover=[0.0, 0.5], expert_labels=False)

    config, tasks, _ = _curriculum(tmp_path, curriculum=False)
    policy = PolicyExplorer(name="policy:m/1", model_key="m1", checkpoint="policy.pt")
    embeddings = {text: np.zeros(384, dtype=np.float32) for t in tasks for text in t.instructions}

    def plan(takeover, iteration):
        campaign = config.model_copy(update={"explore": config.explore.model_copy(update={"expert_takeover": takeover})})
        units = plan_explore(campaign, iteration, tasks, policy if iteration else None, embeddings,
                             Workspace.at(tmp_path).create())
        return [u.unit_key for u in units], {u.expert_takeover for u in units}

    for iteration in (0, 1):  # the schedule's first level is the single share's: the same work
        assert plan([0.5, 0.25], iteration)[0] == plan(0.5, iteration)[0]
    keys, shares = plan([0.5, 0.25], 2)
    assert shares == {0.25} and keys != plan(0.5, 2)[0] and keys == plan(0.25, 2)[0]


def test_without_labels_the_column_stays_empty(tmp_path):
    _, steps = _shards(_plan(_config(expert_labels=False), tmp_path)[0])
    assert steps and all(s["expert_action"] is None for s in steps)


def test_a_failure_mid_episode_fails_that_episode_not_the_shard(tmp_path, monkeypatch):
    unit = _plan(_config(), tmp_path)[0]
    env = worker_env(unit.task, unit.render)
    step, calls = env.step, {"n": 0}

    def step_that_breaks_once(action):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("mjWARNING_BADQACC: simulation unstable")
        return step(action)

    monkeypatch.setattr(env, "step", step_that_breaks_once)
    episodes, steps = _shards(unit)
    errors = [e["error"] for e in episodes]
    assert len(errors) == 4 and sum(error is None for error in errors) == 3
    assert any(error and error.startswith("RuntimeError: mjWARNING_BADQACC") for error in errors)
    failed = {e["episode_id"] for e in episodes if e["error"]}
    assert all(e["num_steps"] == 0 for e in episodes if e["error"])
    assert steps and not any(s["episode_id"] in failed for s in steps)


def test_a_vlm_endpoint_that_does_not_answer_fails_the_unit_not_its_episodes(tmp_path):
    """An outage is the endpoint's, not the episode's: recorded as failed episodes, they stayed failed under
    the unit's key for good; the unit fails instead, writes nothing, and is redone when the same command runs."""
    from policies.openai_chat import ChatUnavailable

    vlm = VlmExplorerConfig(url=f"http://127.0.0.1:{closed_port()}/v1", model="gone", retries=0)
    workspace = Workspace.at(tmp_path).create()
    unit = _plan(_config(vlm=vlm, vlm_fraction=0.25), tmp_path)[0]
    with pytest.raises(ChatUnavailable, match=r"^explore: VLM explorer at http://127.0.0.1:\d+/v1/chat/completions did "
                                              r"not answer .* set explore.vlm_fraction=0\), then run the same command"):
        run_explore_unit(unit)
    assert not [p for p in workspace.warehouse.rglob("*.parquet")]


def test_a_vlm_endpoint_that_refuses_the_request_fails_the_unit_saying_what_to_check(tmp_path, serve_chat):
    """A 401 (a wrong key) or 404 (a wrong model) is not an outage: starting the endpoint fixes nothing."""
    from policies.openai_chat import ChatUnavailable

    server = serve_chat(("{}", 401, 0.0))
    unit = _plan(_config(vlm=VlmExplorerConfig(url=server.url, model="tiny-vlm"), vlm_fraction=0.25), tmp_path)[0]
    with pytest.raises(ChatUnavailable, match=r"did not answer \(HTTP 401\) after 1 tries: it refused the request: "
                                              r"check explore.vlm \(url, model, api_key_env\)") as raised:
        run_explore_unit(unit)
    assert raised.value.refused and len(server.requests) == 1  # not tried again either


def test_a_noise_schedule_cycles_over_each_tasks_episodes(tmp_path):
    units = _plan(_config(expert_noise=[0.0, 0.3]), tmp_path)
    assert [e.expert_noise for e in units[0].episodes] == [0.0, 0.3, 0.0, 0.3]
    episodes, steps = _shards(units[0])
    assert [json.loads(e["explorer_stats"])["expert_noise"] for e in episodes] == [0.0, 0.3, 0.0, 0.3]
    clean = [s for s in steps if s["episode_id"] == episodes[0]["episode_id"]]
    assert all(s["action"] == s["expert_action"] for s in clean)  # no noise: the action is the label
    mixed = _plan(_config(expert_noise=[0.0, 0.3], vlm=VlmExplorerConfig(url="http://127.0.0.1:1/v1", model="m")),
                  tmp_path)
    for unit in mixed:  # the schedule runs over the expert's own episodes: both levels, whoever else explores
        assert sorted(e.expert_noise for e in unit.episodes if e.explorer == EXPERT) == [0.0, 0.3]
        assert all(e.expert_noise is None for e in unit.episodes if e.explorer != EXPERT)
    with pytest.raises(ValueError, match="expert_noise: the schedule is empty"):
        ExploreConfig(expert_noise=[])


def _curriculum(tmp_path, curriculum: bool = True) -> tuple[CampaignConfig, list, Path]:
    """A campaign of nav-room and its long-horizon composition, and a real (untrained) policy checkpoint."""
    config = CampaignConfig(
        name="curriculum-test",
        tasks=TasksConfig(specs=["nav-room", "nav-room-sequence"], colours=["red", "green"],
                          horizon={"nav-room": 6, "nav-room-sequence": 6}),
        explore=ExploreConfig(episodes_per_task=2, episodes_per_shard=2, workers=1, curriculum=curriculum),
    )
    torch.manual_seed(0)
    # chunk 1: each step's action is the policy's stateless `act` on that step's instruction (checked below)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=1),
                     ModelDims(84, PROPRIO_DIM, ACTION_DIM, len(ACTIONS), 384))
    checkpoint = tmp_path / "policy.pt"
    torch.save(policy_state([model], Normaliser(np.zeros(ACTION_DIM), np.ones(ACTION_DIM)),
                            Normaliser(np.zeros(PROPRIO_DIM), np.ones(PROPRIO_DIM))), checkpoint)
    return config, generate_tasks(config.tasks, config.seed), checkpoint


def _plan_curriculum(config, tasks, tmp_path, policy: PolicyExplorer | None):
    embeddings = {text: np.zeros(384, dtype=np.float32) for t in tasks for text in t.instructions}
    return plan_explore(config, 1 if policy else 0, tasks, policy, embeddings, Workspace.at(tmp_path).create(),
                        subgoals_of=curriculum_subgoals(config, tasks))


def test_a_curriculum_leaves_long_tasks_to_the_policy_chaining_their_subtasks(tmp_path):
    config, tasks, checkpoint = _curriculum(tmp_path)
    first = _plan_curriculum(config, tasks, tmp_path, None)
    assert {u.task.task_id for u in first} == {"nav-room-red", "nav-room-green"}  # no policy yet to chain them
    policy = PolicyExplorer(name="policy:m/1", model_key="m1", checkpoint=str(checkpoint))
    units = {u.task.task_id: u for u in _plan_curriculum(config, tasks, tmp_path, policy)}
    assert set(units) == {t.task_id for t in tasks}
    chained = units["nav-room-sequence-green-red"]
    assert {e.explorer for e in chained.episodes} == {f"policy:m/1 {CHAINED}"}
    assert all(e.subgoals == ["go to the green room", "go to the red room"] for e in chained.episodes)
    assert not any(e.subgoals for e in units["nav-room-red"].episodes)
    assert EXPERT in {e.explorer for e in units["nav-room-red"].episodes}  # sub-tasks keep their expert

    episodes, steps = _shards(chained)
    assert len(episodes) == 2 and all(e["error"] is None and e["num_steps"] > 0 for e in episodes)
    said = {e["episode_id"]: e["instruction"] for e in episodes}
    assert all(s["instruction"] == said[s["episode_id"]] in chained.task.instructions for s in steps)
    assert all(s["expert_action"] is None for s in steps)  # the curriculum withholds the expert's labels

    plan = chained.episodes[0]
    policy = Policy.load(checkpoint, {t: np.asarray(v, np.float32) for t, v in chained.embeddings.items()})
    asked, act = [], policy.act
    policy.act = lambda obs, instruction, family: asked.append(instruction) or act(obs, instruction, family)
    explorer = _explorer(chained, plan, policy)
    obs = worker_env(chained.task, chained.render).reset(chained.task, plan.seed)
    for stage in (0, 1, 1, 0):  # the environment's goal picks the instruction
        obs.privileged["stage"] = np.array([stage])
        assert explorer.act(obs) == act(obs, plan.subgoals[stage], "navigation").action
    assert asked == [plan.subgoals[s] for s in (0, 1, 1, 0)]


def test_without_a_curriculum_long_tasks_are_the_experts_and_keys_stay_as_before(tmp_path):
    config, tasks, _ = _curriculum(tmp_path, curriculum=False)
    units = _plan_curriculum(config, tasks, tmp_path, None)
    assert {u.task.task_id for u in units} == {t.task_id for t in tasks}
    assert all(e.explorer == EXPERT and not e.subgoals for u in units for e in u.episodes)
    explore = config.explore.model_dump(exclude={"workers", "dask_address", "curriculum", "relabel",
                                                 "expert_takeover", "policy_steps",
                                                 "first_episodes_per_task"})  # added later
    render = config.render.model_dump(exclude={"mesh_detail", "wrist_camera", "decimate_colliding"})  # added later
    reads = {"campaign": config.name, "seed": config.seed, "iteration": 0, "render": render,
             "randomise": config.randomise, "explore": explore, "policy": None}
    assert [u.unit_key for u in units] == [
        unit_key(STAGE, VERSION, reads, [u.task.model_dump_json(), str(u.shard), "2"]) for u in units]


def test_a_failed_episode_that_did_another_seen_task_is_relabelled_as_it(tmp_path):
    """Hindsight relabelling: 6-step navigation episodes never reach their room; those that end inside
    another seen task's room are recorded as that task's successes, in its words, without the expert's
    labels (they led elsewhere); the rest stay failures of their own task."""
    config = CampaignConfig(
        name="relabel-test",
        tasks=TasksConfig(specs=["nav-room"], colours=["red", "green", "blue", "yellow"], unseen_colours=["yellow"],
                          horizon={"nav-room": 6}),
        explore=ExploreConfig(episodes_per_task=6, episodes_per_shard=6, workers=1, relabel=True),
    )
    units = _plan(config, tmp_path)
    tasks = {t.task_id: t for t in generate_tasks(config.tasks, config.seed)}
    assert all(sorted(t.task_id for t in u.relabel_to) == sorted(t for t in tasks if t != u.task.task_id
                                                                 and tasks[t].split == "seen") for u in units)
    relabelled = 0
    for unit in units:
        episodes, steps = _shards(unit)
        for episode in episodes:
            stats = json.loads(episode["explorer_stats"])
            rows = [s for s in steps if s["episode_id"] == episode["episode_id"]]
            if "relabelled_from" not in stats:
                assert episode["task_id"] == unit.task.task_id and not episode["success"]
                assert all(s["expert_action"] is not None for s in rows)
                continue
            relabelled += 1
            achieved = tasks[episode["task_id"]]
            assert stats["relabelled_from"] == unit.task.task_id != achieved.task_id and achieved.split == "seen"
            assert episode["success"] and rows[-1]["success"] and episode["instruction"] in achieved.instructions
            assert all(s["task_id"] == achieved.task_id and s["instruction"] == episode["instruction"]
                       and s["expert_action"] is None for s in rows)
            # the achieved task's sparse reward, not progress toward the room it set out for
            assert [s["reward"] for s in rows] == [0.0] * (len(rows) - 1) + [1.0] and episode["episode_return"] == 1.0
    assert relabelled > 0
    # off by default: the same plan without it relabels nothing, and keeps its keys
    plain = _plan(CampaignConfig(**{**config.model_dump(), "explore": {**config.explore.model_dump(), "relabel": False}}),
                  tmp_path / "plain")
    assert all(u.relabel_to == [] for u in plain)


def test_the_navigation_scene_says_which_task_the_agent_is_doing_now():
    config = TasksConfig(specs=["nav-room", "nav-ball"], colours=["red", "green", "blue"])
    tasks = {t.task_id: t for t in generate_tasks(config, 0)}
    env = worker_env(tasks["nav-room-red"], None)
    env.reset(tasks["nav-room-red"], seed=3)
    rooms = env.room_colours
    for index, colour in enumerate(rooms):  # stand in the middle of each room in turn
        env.data.qpos[:2] = [(index + 0.5) * ROOM_SIZE, ROOM_SIZE / 2]
        wanted = f"nav-room-{colour}"
        found = env.achieved([t for t in tasks.values() if t.env_name == "GoToRoom"])
        assert (found.task_id if found else None) == (wanted if wanted in tasks else None)
    assert env.achieved([tasks["nav-ball-red"]]) is None  # another environment's task


def _nav_room_policy(tmp_path) -> tuple[CampaignConfig, list, PolicyExplorer]:
    """nav-room in two colours, 6-step episodes, and a real (untrained) policy to explore them."""
    config, _, checkpoint = _curriculum(tmp_path, curriculum=False)
    config = config.model_copy(update={"tasks": config.tasks.model_copy(update={"specs": ["nav-room"],
                                                                                 "horizon": {"nav-room": 6}})})
    return (config, generate_tasks(config.tasks, config.seed),
            PolicyExplorer(name="policy:m/1", model_key="m1", checkpoint=str(checkpoint)))


def test_with_expert_takeover_the_policys_episodes_say_how_many_steps_the_expert_drove(tmp_path):
    config, tasks, policy = _nav_room_policy(tmp_path)
    plain = _plan_curriculum(config, tasks, tmp_path, policy)
    taken = config.model_copy(update={"explore": config.explore.model_copy(update={"expert_takeover": 1.0})})
    units = _plan_curriculum(taken, tasks, tmp_path, policy)
    assert {u.unit_key for u in units}.isdisjoint(u.unit_key for u in plain)  # the share enters the key
    episodes, steps = _shards(units[0])
    by_policy = [e for e in episodes if e["explorer"] == "policy:m/1"]
    assert by_policy and all(e["error"] is None for e in episodes)
    for episode in by_policy:
        own = [s for s in steps if s["episode_id"] == episode["episode_id"]]
        assert json.loads(episode["explorer_stats"]) == {"expert_takeover": 1.0, "expert_steps": len(own), "steps": len(own)}
        assert all(s["action"] == s["expert_action"] for s in own)  # the expert drove every step
    episodes, _ = _shards(plain[0])
    assert all(e["explorer_stats"] is None for e in episodes if e["explorer"] == "policy:m/1")


def test_policy_steps_cut_the_policys_episodes_only_and_key_only_where_a_policy_explores(tmp_path):
    config, tasks, policy = _nav_room_policy(tmp_path)
    cut = config.model_copy(update={"explore": config.explore.model_copy(update={"policy_steps": 2})})
    assert [u.unit_key for u in _plan_curriculum(cut, tasks, tmp_path, None)] == \
        [u.unit_key for u in _plan_curriculum(config, tasks, tmp_path, None)]  # iteration 0: no policy, same work
    plain, units = (_plan_curriculum(c, tasks, tmp_path, policy) for c in (config, cut))
    assert {u.unit_key for u in units}.isdisjoint(u.unit_key for u in plain)
    for unit, before in zip(units, plain):
        episodes, steps = _shards(unit)
        _, steps_before = _shards(before)
        assert {e["explorer"] for e in episodes} == {"policy:m/1", EXPERT}
        for episode in episodes:
            own = [s for s in steps if s["episode_id"] == episode["episode_id"]]
            uncut = [s for s in steps_before if s["episode_id"].endswith(episode["episode_id"][-5:])
                     and s["task_id"] == episode["task_id"]]
            if episode["explorer"] == EXPERT:  # the expert's episodes run as before
                assert len(own) == len(uncut)
                continue
            assert len(own) == episode["num_steps"] == min(2, len(uncut))
            assert own[-1]["done"] and not any(s["done"] for s in own[:-1])
            assert [s["qpos"] for s in own] == [s["qpos"] for s in uncut[:len(own)]]  # the same episode, cut


def test_iteration_0_explores_first_episodes_per_task_as_a_campaign_of_that_many_would(tmp_path):
    config, tasks, policy = _nav_room_policy(tmp_path)
    explore = config.explore.model_copy(update={"prioritise": False, "episodes_per_shard": 1})
    small = config.model_copy(update={"explore": explore.model_copy(update={"episodes_per_task": 2})})
    grown = config.model_copy(update={"explore": explore.model_copy(update={"episodes_per_task": 5,
                                                                             "first_episodes_per_task": 2})})
    first = _plan_curriculum(grown, tasks, tmp_path, None)
    assert [u.unit_key for u in first] == [u.unit_key for u in _plan_curriculum(small, tasks, tmp_path, None)]
    assert Counter(u.task.task_id for u in first) == {"nav-room-red": 2, "nav-room-green": 2}
    later = _plan_curriculum(grown, tasks, tmp_path, policy)
    assert Counter(u.task.task_id for u in later) == {"nav-room-red": 5, "nav-room-green": 5}
    assert [grown.explore.episodes_at(i) for i in (0, 1, 3)] == [2, 5, 5]
    assert [small.explore.episodes_at(i) for i in (0, 1)] == [2, 2]


def test_a_unit_that_could_relabel_keys_on_its_scenes_achieved_test(tmp_path, monkeypatch):
    """Stack's test came after units were keyed: with relabelling on, a Stack unit's key names the test (a
    cached unit explored without it redoes); a Lift unit (no test) and every unit with relabelling off key as before."""
    def keys(relabel: bool) -> dict[str, str]:
        config = CampaignConfig(name="relabel-keys", tasks=TasksConfig(specs=["stack", "lift"], colours=["red", "green"],
                                                                       weak_experts="keep"),
                                explore=ExploreConfig(episodes_per_task=1, episodes_per_shard=1, workers=1, relabel=relabel))
        return {unit.task.task_id: unit.unit_key for unit in _plan(config, tmp_path)}

    with_test = {relabel: keys(relabel) for relabel in (True, False)}
    monkeypatch.setattr("stages.explore.ACHIEVED_TESTS", {})
    without = {relabel: keys(relabel) for relabel in (True, False)}
    assert sorted(with_test[True]) == ["lift-green", "lift-red", "stack-green-red", "stack-red-green"]
    assert sorted(t for t in with_test[True] if with_test[True][t] != without[True][t]) == ["stack-green-red", "stack-red-green"]
    assert with_test[False] == without[False]


def test_a_relabelling_unit_keys_on_the_tasks_it_may_file_a_failure_under(tmp_path):
    """Holding blue out takes nav-room-blue off nav-room-red's relabelling targets: a cached unit that filed
    failures under it (a held-out task, in training) must not be reused."""
    def keys(unseen: list[str]) -> dict[str, str]:
        config = CampaignConfig(name="relabel-targets", tasks=TasksConfig(specs=["nav-room"], colours=["red", "green", "blue"],
                                                                          unseen_colours=unseen),
                                explore=ExploreConfig(episodes_per_task=1, episodes_per_shard=1, workers=1, relabel=True))
        return {unit.task.task_id: unit.unit_key for unit in _plan(config, tmp_path)}

    every, blue_held_out = keys([]), keys(["blue"])
    assert sorted(blue_held_out) == ["nav-room-green", "nav-room-red"]
    assert all(every[task] != blue_held_out[task] for task in blue_held_out)


def test_an_iteration_runs_shard_0_of_every_task_before_any_tasks_shard_1(tmp_path):
    """So the first minutes' pace (and ETA) is the whole mix's, not the first family's."""
    config = _config(episodes_per_task=4, episodes_per_shard=2)
    workspace = Workspace.at(tmp_path).create()
    Catalog(workspace.catalog).initialise()
    tasks = generate_tasks(config.tasks, config.seed)
    handed = []

    def record(units):
        handed.extend((u.task.task_id, u.shard) for u in units)
        return iter(())

    run_explore(workspace, config, 0, tasks, None, {}, execute=record)
    seen = [t.task_id for t in tasks if t.split == "seen"]
    assert len(seen) >= 2
    assert handed == [(task, shard) for shard in (0, 1) for task in seen]
