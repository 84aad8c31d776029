"""Success rates with Wilson intervals, pooled per split and family; model references for `sim2act eval`."""

import functools

import pytest

from flows.model_eval import parse_registry_ref
from schemas.config import ConfigError
from stages.evaluate import TaskEvaluation, group_success, wilson_interval


@pytest.mark.parametrize(("successes", "episodes", "low", "high"), [
    (48, 60, 0.6822, 0.8817),  # the quality run's seen tasks
    (8, 10, 0.4902, 0.9433),
    (0, 10, 0.0, 0.2775),  # not [0, 0]: ten failures do not prove a zero rate
    (10, 10, 0.7225, 1.0),
])
def test_wilson_intervals_match_the_published_values(successes, episodes, low, high):
    assert wilson_interval(successes, episodes) == pytest.approx((low, high), abs=1e-4)


def _case(task_id: str, family: str, split: str, outcomes: list[bool]) -> TaskEvaluation:
    low, high = wilson_interval(sum(outcomes), len(outcomes))
    return TaskEvaluation(task_id=task_id, family=family, split=split, instruction="x", episodes=len(outcomes),
                          successes=sum(outcomes), ci_low=low, ci_high=high, mean_return=0.0,
                          mean_length=10.0, episode_lengths=[10] * len(outcomes), episode_successes=outcomes,
                          uncertainty=0.0, success_video=None, failure_video=None)


def test_groups_pool_episodes_per_split_family_and_split_within_family():
    cases = [_case("lift-red", "robosuite", "seen", [True] * 9 + [False]),
             _case("lift-orange", "robosuite", "unseen", [True] * 2 + [False] * 8),
             _case("nav-room-red", "navigation", "seen", [True] * 5 + [False] * 5)]
    groups = {g.group: g for g in group_success(cases)}
    assert set(groups) == {"seen", "unseen", "robosuite", "navigation", "robosuite/seen", "robosuite/unseen",
                           "navigation/seen"}
    assert (groups["seen"].successes, groups["seen"].episodes, groups["seen"].cases) == (14, 20, 2)
    assert (groups["robosuite"].successes, groups["robosuite"].episodes) == (11, 20)
    assert (groups["seen"].ci_low, groups["seen"].ci_high) == wilson_interval(14, 20)
    # pooling narrows the interval: 20 episodes say more than 10
    assert groups["seen"].ci_high - groups["seen"].ci_low < cases[2].ci_high - cases[2].ci_low


@pytest.mark.parametrize(("ref", "parsed"), [
    ("champion", ("sim2act-c", None, "champion")), ("@best", ("sim2act-c", None, "best")),
    ("3", ("sim2act-c", "3", None)), ("v3", ("sim2act-c", "3", None)), ("other/2", ("other", "2", None)),
    ("other@champion", ("other", None, "champion")), ("models:/other/2", ("other", "2", None)),
])
def test_registry_references_name_a_model_version_or_alias(ref, parsed):
    assert parse_registry_ref(ref, "sim2act-c") == parsed


@pytest.mark.parametrize("ref", ["other/latest", "@", "two words", "3@x y"])
def test_a_bad_reference_is_refused_naming_the_flag(ref):
    with pytest.raises(ConfigError, match="--model: .* is neither a model key"):
        parse_registry_ref(ref, "sim2act-c")


def test_a_failed_episode_says_which_other_goal_it_ended_at_and_splits_count_the_misreadings():
    """The words named the red ball; the agent ended at the green one: recorded per episode, counted as
    the colour misread (same spec, another colour) in the split's confusions."""
    import numpy as np

    from envs.rollout import worker_env
    from envs.suite import generate_tasks
    from schemas.config import TasksConfig
    from stages.evaluate import ended_doing, goal_confusions, others_of

    tasks = {t.task_id: t for t in generate_tasks(TasksConfig(specs=["nav-ball", "nav-box"],
                                                              colours=["red", "green", "blue"]), 0)}
    red = tasks["nav-ball-red"]
    cases = [(t, t.split, t.instruction) for t in tasks.values()]
    others = others_of(red, cases)
    assert [t.task_id for t in others] == ["nav-ball-green", "nav-ball-blue"]  # the same scene's goals, not itself
    env = worker_env(red, None)
    env.reset(red, seed=5)
    assert ended_doing(env, others) is None  # the start is away from every goal
    present = [t for t in others if ("ball", t.object_colours["target"]) in env.objects]
    env.data.qpos[:2] = env.objects[("ball", present[0].object_colours["target"])]
    assert ended_doing(env, others) == present[0].task_id
    assert ended_doing(env, []) is None

    def evaluation(task_id, split, successes, achieved):
        case = _case(task_id, "navigation", split, successes)
        return case.model_copy(update={"episode_achieved": achieved})

    spec_of = {t.task_id: t.spec for t in tasks.values()}
    confusions = goal_confusions([
        evaluation("nav-ball-red", "seen", [True, False, False, False],
                   ["nav-ball-red", "nav-ball-green", None, "nav-ball-green"]),
        evaluation("nav-box-red", "seen", [False, False], ["nav-ball-red", "nav-box-blue"]),
        evaluation("nav-ball-green", "unseen", [False], [None]),
        _case("nav-box-blue", "navigation", "seen", [False]),  # not recorded (an evaluation before layout 7)
    ], spec_of)
    assert [(c.split, c.failures, c.same_spec, c.other_spec) for c in confusions] == [("seen", 5, 3, 1),
                                                                                      ("unseen", 1, 0, 0)]
    assert confusions[0].commonest[0] == ("nav-ball-red", "nav-ball-green", 2)
    assert np.isclose(sum(n for *_, n in confusions[0].commonest), 4)


def test_a_case_evaluated_twice_counts_once_where_evaluations_are_summed(tmp_path):
    """A case evaluated again (a new stage version, `sim2act eval --episodes`) keeps both rows, on the
    same episode seeds: the reports read the one of most episodes (then the latest), never both."""
    from schemas.workspace import Workspace
    from stages.evaluate import read_evaluations
    from warehouse.catalog import Catalog

    workspace = Workspace.at(tmp_path).create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()

    def register(unit: str, task_id: str, outcomes: list[bool]) -> None:
        case = _case(task_id, "navigation", "seen", outcomes)
        row = {"unit_key": unit, "campaign": "c", "iteration": 0, "suite": "campaign", "model_key": "train-m",
               **case.model_dump(), "success_rate": case.success_rate}
        catalog.register_unit(unit_key=unit, stage="evaluate", campaign="c", iteration=0, summary={},
                              rows={"evaluations": [row]})

    register("evaluate-a", "nav-ball-red", [True] * 5 + [False] * 5)
    register("evaluate-b", "nav-ball-red", [True] * 12 + [False] * 8)  # more episodes: this one stands
    register("evaluate-c", "nav-ball-red", [True] * 1 + [False] * 9)  # later, fewer episodes
    register("evaluate-d", "nav-box-red", [True] * 3)
    current = read_evaluations(catalog, "v.unit_key", "WHERE v.model_key = ? ORDER BY v.unit_key", ["train-m"])
    assert [(unit, e.successes, e.episodes) for unit, e in current] == [("evaluate-b", 12, 20), ("evaluate-d", 3, 3)]
    every = read_evaluations(catalog, "v.unit_key", "WHERE v.model_key = ?", ["train-m"], table="evaluations")
    assert len(every) == 4
    groups = {g.group: g for g in group_success([e for _, e in current])}
    assert (groups["seen"].successes, groups["seen"].episodes) == (15, 23)
    # the next iteration's episode shares (in its explore keys) read the first evaluation, which stays: an
    # iteration explored with this champion plans the same after `sim2act eval --episodes` re-evaluates it
    from schemas.tasks import TaskRecord
    from warehouse.priority import plan_priorities
    tasks = [TaskRecord(task_id=t, spec=t[:-4], family="navigation", env_name="Nav", object_colours={},
                        instructions=["go", "reach", "find"], split="seen", horizon=10) for t in ("nav-ball-red", "nav-box-red")]
    [ball, box] = plan_priorities(catalog, "c", "train-m", tasks, per_task=4, floor=0.25)
    assert (ball.success, box.success) == (0.5, 1.0)


def test_promotion_compares_the_champion_on_the_new_models_own_episodes(tmp_path):
    """The champion re-evaluated on 20 episodes (`sim2act eval --episodes 20`): its first 10 are the 10 the new
    model played (seeds by episode index). Over all 20 the champion scores 50%, over those 10 it scores 30%:
    a new model at 40% beats it on the same episodes."""
    from schemas.workspace import Workspace
    from stages.evaluate import decide_promotion
    from warehouse.catalog import Catalog

    catalog = Catalog(Workspace.at(tmp_path).create().catalog)
    catalog.initialise()
    champion = _case("nav-ball-red", "navigation", "seen", [True] * 3 + [False] * 7 + [True] * 7 + [False] * 3)
    catalog.register_unit(unit_key="evaluate-champion", stage="evaluate", campaign="c", iteration=0, summary={},
                          rows={"evaluations": [{"unit_key": "evaluate-champion", "campaign": "c", "iteration": 0,
                                                 "suite": "campaign", "model_key": "train-champion",
                                                 **champion.model_dump(), "success_rate": champion.success_rate}]})
    new = [_case("nav-ball-red", "navigation", "seen", [True] * 4 + [False] * 6)]
    decide = functools.partial(decide_promotion, catalog, "c", "train-new", registered_model="m", alias="champion")
    assert decide(new).reason == "no champion yet"

    def deploy(unit: str, iteration: int, champion_key: str) -> None:
        catalog.register_unit(unit_key=unit, stage="redeploy", campaign="c", iteration=iteration, summary={}, rows={
            "deployments": [{"unit_key": unit, "model_key": champion_key, "campaign": "c", "iteration": iteration,
                             "registered_model": "m", "version": 1, "alias": "champion", "champion_version": 1,
                             "champion_model_key": champion_key, "promoted": True, "decision": "",
                             "mlflow_run_id": ""}]})

    deploy("redeploy-3-earlier-settings", 3, "train-old")  # an earlier run of the campaign, to iteration 3
    deploy("redeploy-0", 0, "train-champion")  # this run's iteration 0, deployed since: it holds the alias
    promotion = decide(new)
    assert (promotion.promote, promotion.success, promotion.champion_success) == (True, 0.4, 0.3)
    assert promotion.reason == "success 40% beats the champion's 30% on 1 cases"
    # worse, or level, on the same episodes: the champion stays
    worse = decide([_case("nav-ball-red", "navigation", "seen", [True] * 2 + [False] * 8)])
    assert (worse.promote, worse.success, worse.champion_success) == (False, 0.2, 0.3)
    assert worse.reason.startswith("success 20% does not beat")
    assert decide([_case("nav-ball-red", "navigation", "seen", [True] * 3 + [False] * 7)]).promote is False
    other = [_case("nav-box-red", "navigation", "seen", [True] * 10)]  # a case the champion never met
    assert decide(other).reason == "the champion was never evaluated on these tasks"
    # redeploy.registered_model changed: no champion there yet, so the first model makes the alias
    assert decide(new, registered_model="m-renamed").reason == "no champion yet"


def test_an_agent_acting_otherwise_than_it_trained_is_never_registered_as_the_model(tmp_path):
    """sim2act shadow --execution plays a checkpoint another way; an evaluation would file its episodes
    under the model's own keys, so evaluate_model refuses it before any work."""
    from schemas.config import Acting, CampaignConfig
    from schemas.workspace import Workspace
    from stages.evaluate import Agent, evaluate_model

    agent = Agent(kind="sim2act", path="policy.pt", acting=Acting(execution="receding", execute_steps=1))
    with pytest.raises(ValueError, match="expected the agent acting as it trained to, got acting execution receding"):
        evaluate_model(Workspace.at(tmp_path).create(), CampaignConfig(), 0, "train-m", agent, [], {})
    assert not (tmp_path / "warehouse").exists() or not any((tmp_path / "warehouse").rglob("*.parquet"))


def test_an_evaluation_takes_a_case_of_each_family_in_turn(tmp_path, monkeypatch):
    """So its first minutes' pace (and ETA) is the mix's: a navigation case runs in seconds, a robosuite one in minutes."""
    import numpy as np

    import stages.evaluate as evaluate
    from envs.suite import generate_tasks
    from schemas.config import CampaignConfig, TasksConfig
    from schemas.workspace import Workspace
    from warehouse.catalog import Catalog

    class Handed(Exception):
        pass

    handed = []

    def record(work, units, workers, label, fresh_workers=False):
        handed.extend(u.task.family for u in units)
        raise Handed
        yield  # a generator, as run_in_pool is

    monkeypatch.setattr(evaluate, "run_in_pool", record)
    config = CampaignConfig(tasks=TasksConfig(specs=["lift", "nav-room", "mw-reach", "mw-push"], colours=["red", "green"]))
    tasks = generate_tasks(config.tasks, config.seed)
    cases = evaluate.evaluation_cases(tasks)
    embeddings = {instruction: np.zeros(384, dtype=np.float32) for _, _, instruction in cases}
    workspace = Workspace.at(tmp_path).create()
    Catalog(workspace.catalog).initialise()
    with pytest.raises(Handed):
        evaluate.evaluate_model(workspace, config, 0, "train-m", evaluate.Agent(kind="expert"), cases, embeddings)
    families = [task.family for task, _, _ in cases]
    assert families[:2] == ["robosuite", "robosuite"]  # the cases' own order: task by task
    assert sorted(handed) == sorted(families)
    rounds = min(families.count(family) for family in set(families))
    assert len(set(families)) == 3 and rounds >= 2
    assert all(len(set(handed[i:i + 3])) == 3 for i in range(0, 3 * rounds, 3))


def test_an_rl_agent_meets_its_familys_cases_with_the_campaigns_episodes_per_split(tmp_path):
    """With evaluate.episodes_per_split the episodes per case come from the split's size over every family: an RL
    agent evaluated on its family's cases alone meets the same units (keys, seeds) as the policy and the expert."""
    import numpy as np

    from envs.suite import generate_tasks
    from schemas.config import CampaignConfig, EvaluateConfig, TasksConfig
    from schemas.workspace import Workspace
    from stages.evaluate import Agent, episodes_per_split, evaluation_cases, evaluation_units

    config = CampaignConfig(tasks=TasksConfig(specs=["nav-room", "mw-reach"], colours=["red", "green", "blue"]),
                            evaluate=EvaluateConfig(episodes_per_task=3, episodes_per_split=12))
    cases = evaluation_cases(generate_tasks(config.tasks, config.seed))
    navigation = [case for case in cases if case[0].family == "navigation"]
    embeddings = {instruction: np.zeros(384, dtype=np.float32) for _, _, instruction in cases}
    workspace, agent = Workspace.at(tmp_path), Agent(kind="expert")
    everyone = {u.unit_key: u.seeds for u in evaluation_units(workspace, config, "m", agent, cases, embeddings)}
    alone = evaluation_units(workspace, config, "m", agent, navigation, embeddings,
                             per_split=episodes_per_split(config, cases))
    assert alone and all(everyone[u.unit_key] == u.seeds for u in alone)
    # counted on the family alone, a split half the size would get twice the episodes: other units
    assert not set(everyone) >= {u.unit_key for u in evaluation_units(workspace, config, "m", agent, navigation,
                                                                      embeddings)}


def test_evaluate_max_steps_ends_each_episode_there_in_units_of_their_own(tmp_path):
    """evaluate.max_steps (a quick look, the suite's generalist test): every episode ends at that step at the
    latest, and its units are not the full-horizon ones (whose keys hold as they were: it is in a key only where set)."""
    import numpy as np

    from envs.suite import generate_tasks
    from schemas.config import CampaignConfig, EvaluateConfig, TasksConfig
    from schemas.workspace import Workspace
    from stages.evaluate import Agent, evaluate_unit, evaluation_cases, evaluation_units

    tasks = TasksConfig(specs=["nav-room"], colours=["red"])
    full, short = (CampaignConfig(tasks=tasks, evaluate=EvaluateConfig(episodes_per_task=2, videos=False,
                                                                       max_steps=steps)) for steps in (None, 3))
    cases = evaluation_cases(generate_tasks(full.tasks, full.seed))[:1]
    embeddings = {instruction: np.zeros(384, dtype=np.float32) for _, _, instruction in cases}
    workspace, agent = Workspace.at(tmp_path), Agent(kind="expert")
    [whole] = evaluation_units(workspace, full, "m", agent, cases, embeddings)
    [cut] = evaluation_units(workspace, short, "m", agent, cases, embeddings)
    assert cut.unit_key != whole.unit_key and cut.seeds == whole.seeds
    assert cases[0][0].horizon > 3
    evaluation = evaluate_unit(cut)
    assert evaluation.episodes == 2 and max(evaluation.episode_lengths) <= 3
    assert evaluation.successes == 0  # the room's goal is farther than three steps from its start


def test_a_familys_group_holds_each_task_once_said_canonically():
    """A seen task said again in a held-out paraphrase replays its episode seeds: pooled into `success.<family>`
    beside its canonical case it counted twice as independent episodes."""
    from stages.evaluate import TaskEvaluation, group_success

    def case(task_id: str, split: str, successes: int) -> TaskEvaluation:
        return TaskEvaluation(task_id=task_id, family="robosuite", split=split, instruction="x", episodes=10,
                              successes=successes, ci_low=0, ci_high=1, mean_return=0, mean_length=1,
                              episode_lengths=[1] * 10, episode_successes=[True] * successes + [False] * (10 - successes),
                              uncertainty=0, success_video=None, failure_video=None)

    groups = {g.group: g for g in group_success([case("lift-red", "seen", 8), case("lift-red", "unseen_paraphrase", 2),
                                                 case("lift-purple", "unseen", 5)])}
    assert (groups["robosuite"].episodes, groups["robosuite"].successes) == (20, 13)  # seen and unseen, once each
    assert groups["robosuite/unseen_paraphrase"].successes == 2 and groups["unseen_paraphrase"].episodes == 10
