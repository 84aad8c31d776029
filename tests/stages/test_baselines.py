"""The baselines stage's plan, without training anything: which agent the pool starts first, the units' keys,
when each agent is evaluated."""

import numpy as np
import pytest

from envs.suite import generate_tasks
from schemas.config import RandomiseConfig, RenderConfig, load_config, render_key_fields
from schemas.keys import unit_key
from schemas.workspace import Workspace
from stages import StageUnits, UnitOutput
from stages.baselines import STAGE, VERSION, RLUnit, rl_units, training_order


def _unit(algorithm: str, family: str, env_steps: int) -> RLUnit:
    return RLUnit(unit_key=f"baselines-{algorithm}-{family}", algorithm=algorithm, family=family, tasks=[],
                  embeddings={}, render=RenderConfig(), randomise=RandomiseConfig(), env_steps=env_steps,
                  replay_size=50_000, checkpoint_every=25_000, seed=0, path="unused")


def test_on_several_workers_sac_and_the_larger_budgets_start_first_and_on_one_the_shortest():
    # rl_units' order (algorithm, then family): the generalist's budgets per family
    planned = [_unit("ppo", "metaworld", 382_023), _unit("ppo", "navigation", 254_522),
               _unit("ppo", "robosuite", 455_956), _unit("sac", "metaworld", 382_023),
               _unit("sac", "robosuite", 455_956)]
    order = [(u.algorithm, u.family) for u in training_order(planned, 2)]
    assert order == [("sac", "robosuite"), ("sac", "metaworld"), ("ppo", "robosuite"), ("ppo", "metaworld"),
                     ("ppo", "navigation")]
    # one worker: the stage ends at the same time in any order; the first rows land soonest this way
    assert [(u.algorithm, u.family) for u in training_order(planned, 1)] == [
        ("ppo", "navigation"), ("ppo", "metaworld"), ("ppo", "robosuite"), ("sac", "metaworld"), ("sac", "robosuite")]
    assert [u.unit_key for u in planned][0] == "baselines-ppo-metaworld"  # a new list; the caller's unchanged


def test_a_training_writes_its_progress_at_its_start_and_at_each_percent(tmp_path, caplog):
    """What `sim2act report` reads between checkpoints: a resumed agent's stale progress (it ran past its checkpoint
    before the kill) is replaced at the start; then a log line and progress.json at each 1% of the budget only."""
    import json
    import logging
    from types import SimpleNamespace

    from envs.pool import Progress
    from stages.baselines import progress_callback, write_progress

    write_progress(tmp_path, 132_211, 715, 0)  # the killed run's last
    env = SimpleNamespace(episodes_finished=703, successes=0)  # as the checkpoint at 130,000 restored them
    log = logging.getLogger("test.baselines")
    on_progress = progress_callback(Progress(log, "sac on robosuite", 455_956, "env steps", "env steps"), tmp_path, env)

    def written() -> dict:
        return json.loads((tmp_path / "progress.json").read_text())

    with caplog.at_level(logging.INFO, logger="test.baselines"):
        on_progress(130_000, 130_000)  # the first rollout of the resumed run
        assert written() == {"num_timesteps": 130_000, "episodes": 703, "successes": 0, "rate": None}  # none run yet
        env.episodes_finished = 704
        on_progress(131_000, 130_000)  # within the same percent (4,559 steps): nothing written
        assert written()["num_timesteps"] == 130_000 and not caplog.records
        env.episodes_finished, env.successes = 720, 1
        on_progress(132_231, 130_000)  # 29% of the budget crossed
        latest = written()
        assert latest.pop("rate") > 0  # this run's pace, the checkpoint's 130,000 steps not counted
        assert latest == {"num_timesteps": 132_231, "episodes": 720, "successes": 1}
        assert [r.getMessage().split(",")[0] for r in caplog.records] == ["sac on robosuite: 132231/455956 env steps"]


def _units_over_lift_and_reach(**baselines) -> dict[tuple[str, str], RLUnit]:
    """(algorithm, family) -> the RL unit of PPO and SAC over Lift and MetaWorld's reach, 1,000 steps explored each,
    under these baselines settings."""
    config = load_config("smoke", None, {"tasks": {"specs": ["lift", "mw-reach"]},
                                         "baselines": {"agents": ["ppo", "sac"], **baselines}})
    tasks = generate_tasks(config.tasks, config.seed)
    said = {text: np.zeros(4, np.float32) for t in tasks for text in t.instructions}
    return {(u.algorithm, u.family): u for u in rl_units(Workspace.at("unused"), config, "tasks-k", tasks, said,
                                                         {"robosuite": 1000, "metaworld": 1000})}


def test_agents_trained_to_the_horizon_and_at_the_acting_entropy_are_new_units_and_the_old_keep_their_keys():
    """baselines.end_on_success and sac_target_entropy changed what the agents are: the defaults make new units;
    the values the earlier agents were trained with give those agents' keys, as before the fields existed."""
    new, old = _units_over_lift_and_reach(), _units_over_lift_and_reach(end_on_success=True, sac_target_entropy="all")
    assert all(new[case].unit_key != old[case].unit_key for case in new)
    assert (new["sac", "metaworld"].target_entropy, new["sac", "robosuite"].target_entropy) == (-4.0, None)
    assert not new["sac", "metaworld"].end_on_success and old["sac", "metaworld"].end_on_success
    assert old["sac", "metaworld"].target_entropy is None
    # the earlier agents' keys, as the code before the fields computed them
    config = load_config("smoke")
    before = unit_key(STAGE, VERSION, {"render": render_key_fields(config.render), "randomise": config.randomise,
                                       "seed": config.seed}, ["tasks-k", "sac", "metaworld", "1000"])
    assert old["sac", "metaworld"].unit_key == before


def test_an_agents_torch_threads_are_the_configs_and_not_part_of_its_key(monkeypatch, tmp_path):
    """baselines.threads: how fast an agent trains, not what it is (a run resumed with another count resumes the same
    agent); the training worker sets it on torch before the agent's first step."""
    from types import SimpleNamespace

    import torch

    import envs.gym_env
    import policies.rl_agent
    from stages.baselines import train_rl_agent

    config = load_config("smoke", None, {"baselines": {"agents": ["sac"], "threads": 2}})
    tasks = generate_tasks(config.tasks, config.seed)
    said = {text: np.zeros(4, np.float32) for t in tasks for text in t.instructions}
    [two] = rl_units(Workspace.at(tmp_path), config, "tasks-k", tasks, said, {"robosuite": 1000})
    [one] = rl_units(Workspace.at(tmp_path), load_config("smoke", None, {"baselines": {"agents": ["sac"]}}),
                     "tasks-k", tasks, said, {"robosuite": 1000})
    assert (two.threads, one.threads) == (2, 1) and two.unit_key == one.unit_key

    seen = []

    class Agent:
        num_timesteps = 1000

        def save(self, path):
            path.write_bytes(b"agent")

    def learn(*args):
        seen.append(torch.get_num_threads())
        return Agent(), 0

    monkeypatch.setattr(envs.gym_env, "InstructedTasksEnv",
                        lambda *args: SimpleNamespace(episodes_finished=5, successes=1))
    monkeypatch.setattr(policies.rl_agent, "learn_with_checkpoints", learn)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # as a pool worker starts
        trained = train_rl_agent(two)
    finally:
        torch.set_num_threads(before)
    assert seen == [2] and (trained.steps_taken, trained.successes) == (1000, 1)


def test_budgets_per_family_override_the_exploration_steps_of_the_families_they_name():
    """baselines.env_steps as a mapping: another run's exploration steps train the same agents (the same keys) in a
    workspace whose own exploration is small; a family it leaves out keeps its exploration's steps."""
    def units(env_steps, explored) -> dict[tuple[str, str], RLUnit]:
        config = load_config("smoke", None, {"tasks": {"specs": ["lift", "mw-reach"]},
                                             "baselines": {"agents": ["sac"], "env_steps": env_steps}})
        tasks = generate_tasks(config.tasks, config.seed)
        said = {text: np.zeros(4, np.float32) for t in tasks for text in t.instructions}
        return {(u.algorithm, u.family): u for u in rl_units(Workspace.at("unused"), config, "tasks-k", tasks, said,
                                                             explored)}

    given = units({"metaworld": 382_023}, {"robosuite": 900, "metaworld": 800})
    assert (given["sac", "metaworld"].env_steps, given["sac", "robosuite"].env_steps) == (382_023, 900)
    explored = units(None, {"robosuite": 900, "metaworld": 382_023})
    assert given["sac", "metaworld"].unit_key == explored["sac", "metaworld"].unit_key
    assert units(5_000, {"robosuite": 900})["sac", "robosuite"].env_steps == 5_000
    assert ("sac", "metaworld") not in units({"robosuite": 700}, {})  # no budget given or explored: no agent


def test_a_budget_for_a_family_that_does_not_exist_or_below_64_steps_is_refused():
    import pytest

    from schemas.config import ConfigError

    for bad in ({"manipulation": 1000}, {"metaworld": 10}, 10, {}):
        with pytest.raises(ConfigError, match=r"^baselines\.env_steps: expected a number of environment steps >= 64"):
            load_config("smoke", None, {"baselines": {"env_steps": bad}})


def test_a_budget_mapping_given_by_set_merges_into_the_files_and_a_number_replaces_it(tmp_path):
    """As the README says of --set over --config: a mapping merges key by key, a plain value replaces."""
    from schemas.config import parse_settings

    given = tmp_path / "budgets.yaml"
    given.write_text("baselines:\n  env_steps: {robosuite: 2000}\n")
    merged = load_config("smoke", given, parse_settings(["baselines.env_steps={metaworld: 1000}"]))
    assert merged.baselines.env_steps == {"robosuite": 2000, "metaworld": 1000}
    assert load_config("smoke", given, parse_settings(["baselines.env_steps=500"])).baselines.env_steps == 500


def _beside_harness(tmp_path, monkeypatch, registered: list[str], failing: str | None = None, workers: int = 2):
    """run_baselines with the pool and the evaluation stood in for: the PPO finishes first, and the pool hands over
    the SAC only once the PPO's evaluation has begun (or 30 s later: an evaluation that waits for the last training
    never begins before it). `registered`: the agents an earlier run trained; `failing`: the agent whose evaluation
    raises; `workers`: baselines.workers. -> (the evaluations' calls, the run, the pools' and evaluations' order)"""
    import threading

    import stages.baselines as baselines
    from warehouse.catalog import Catalog

    ws = Workspace.at(tmp_path / "workspace").create()
    catalog = Catalog(ws.catalog)
    catalog.initialise()
    config = load_config("smoke", None, {"baselines": {"agents": ["ppo", "sac"], "workers": workers}})
    units = [_unit(algorithm, "robosuite", 300).model_copy(
        update={"path": str(ws.models / f"baselines-{algorithm}-robosuite" / "agent.zip")}) for algorithm in ("sac", "ppo")]
    ledger = StageUnits(catalog, STAGE, config.name, 0)
    for unit in units:
        if unit.algorithm in registered:
            ledger.register(unit.unit_key, UnitOutput({"algorithm": unit.algorithm}), 1.0)
    ppo_evaluating, calls, events = threading.Event(), [], []

    def evaluate_model(workspace, config, iteration, model_key, agent, cases, embeddings, per_split=None,
                       fresh_workers=False):
        calls.append((model_key, config.evaluate.workers, fresh_workers, ledger.pending([units[0].unit_key]) != []))
        events.append(f"evaluate {agent.kind}")
        if agent.kind == "ppo":
            ppo_evaluating.set()
        if agent.kind == failing:
            raise RuntimeError(f"{failing}'s evaluation failed")
        return [], 0

    def run_in_pool(work, todo, workers, label, fresh_workers=False):
        assert fresh_workers and workers == config.baselines.workers
        events.append(f"pool of {', '.join(u.algorithm for u in todo)}")
        for unit in sorted(todo, key=lambda u: u.algorithm != "ppo"):
            if unit.algorithm == "sac":
                ppo_evaluating.wait(30)
            yield unit, baselines.RLTrained(algorithm=unit.algorithm, family=unit.family, env_steps=300,
                                            steps_taken=300, episodes=5, successes=0, resumed_at=0, path=unit.path), 1.0

    for name, stand_in in {"rl_units": lambda *args: units, "exploration_steps": lambda *args: {},
                           "evaluate_model": evaluate_model, "run_in_pool": run_in_pool}.items():
        monkeypatch.setattr(baselines, name, stand_in)
    result = baselines.run_baselines(ws, config, 0, "tasks", [], {}, [])
    return calls, result, events


def test_an_agent_trained_is_evaluated_beside_the_trainings_still_running_on_the_cores_they_leave(tmp_path, monkeypatch):
    calls, result, _ = _beside_harness(tmp_path, monkeypatch, registered=[])
    # the PPO on one worker of its own while the SAC still trained; the SAC, last, on every evaluation worker
    assert calls == [("baselines-ppo-robosuite", 1, True, True), ("baselines-sac-robosuite", 2, False, False)]
    assert [b.model_key for b in result.baselines] == ["baselines-sac-robosuite", "baselines-ppo-robosuite"]


def test_an_agent_an_earlier_run_trained_is_evaluated_beside_the_trainings_a_resume_runs(tmp_path, monkeypatch):
    # a session's end cut the PPO's evaluation: the resumed run evaluates it beside the SAC's training, not after
    calls, _, _ = _beside_harness(tmp_path, monkeypatch, registered=["ppo"])
    assert calls == [("baselines-ppo-robosuite", 1, True, True), ("baselines-sac-robosuite", 2, False, False)]


def test_on_one_worker_each_agent_is_evaluated_on_every_evaluation_worker_before_the_next_training(
        tmp_path, monkeypatch):
    # the shorter PPO first, in a pool of its own; its evaluation after that pool and before the SAC's begins
    calls, result, events = _beside_harness(tmp_path, monkeypatch, registered=[], workers=1)
    assert events == ["pool of ppo", "evaluate ppo", "pool of sac", "evaluate sac"]
    assert calls == [("baselines-ppo-robosuite", 2, False, True), ("baselines-sac-robosuite", 2, False, False)]
    assert [b.model_key for b in result.baselines] == ["baselines-sac-robosuite", "baselines-ppo-robosuite"]
    # resumed after the PPO trained: its evaluation first, then the SAC's training
    _, _, events = _beside_harness(tmp_path / "resumed", monkeypatch, registered=["ppo"], workers=1)
    assert events == ["evaluate ppo", "pool of sac", "evaluate sac"]


def test_an_evaluation_beside_the_trainings_that_fails_is_said_at_once_and_raised_after_them(tmp_path, monkeypatch,
                                                                                             caplog):
    import logging

    import pytest

    with caplog.at_level(logging.ERROR, logger="sim2act.stages.baselines"), \
            pytest.raises(RuntimeError, match="ppo's evaluation failed"):
        _beside_harness(tmp_path, monkeypatch, registered=[], failing="ppo")
    assert [r.getMessage() for r in caplog.records] == [
        "baselines: evaluating ppo on robosuite beside the trainings failed: RuntimeError(\"ppo's evaluation failed\")"]


def test_baselines_families_trains_only_the_agents_of_the_families_it_names_under_their_own_keys():
    """baselines.families: one family's agents where another's rows are in (a campaign of no iteration then needs a
    budget for that family alone); the agent it keeps is the one every family would have trained."""
    every, robosuite = _units_over_lift_and_reach(), _units_over_lift_and_reach(families=["robosuite"])
    assert set(every) == {("ppo", "metaworld"), ("ppo", "robosuite"), ("sac", "metaworld"), ("sac", "robosuite")}
    assert set(robosuite) == {("ppo", "robosuite"), ("sac", "robosuite")}
    assert all(robosuite[case].unit_key == every[case].unit_key for case in robosuite)
    with pytest.raises(ValueError, match=r"baselines.families.*distinct families, got \['robosuite', 'robosuite'\]"):
        load_config("smoke", None, {"baselines": {"families": ["robosuite", "robosuite"]}})
