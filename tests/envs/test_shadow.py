"""sim2act shadow: the noiseless expert asked at every state a policy reaches, on real robosuite Lift
episodes (no camera: the experts read no pixels). Policies whose parting from the expert is known
by construction — the expert itself, the expert at half speed, a hand that never moves but closes —
must be measured as exactly that."""

import numpy as np
import pytest

from envs.registry import make_expert
from envs.rollout import worker_env
from envs.shadow import CaseShadow, markdown, placement_markdown, shadow_episode
from schemas.config import TasksConfig
from envs.suite import generate_tasks

SEED = 3


@pytest.fixture(scope="module")
def lift():
    config = TasksConfig(specs=["lift"], include=["lift-red"], weak_experts="keep", horizon={"lift": 70})
    [task] = generate_tasks(config, 0)
    return task, worker_env(task, None)


def _expert(task):
    return make_expert(task, 0.0, np.random.default_rng(SEED))


def test_the_expert_shadowing_itself_agrees_at_every_step(lift):
    task, env = lift
    episode = shadow_episode(env, task, SEED, _expert(task), _expert(task))
    assert episode.success and 0 < episode.steps < task.horizon
    assert episode.closes_short == episode.opens_early == 0
    assert episode.cosines and np.allclose(episode.cosines, 1.0)
    assert 0 < len(episode.cosines_before_close) < len(episode.cosines)  # it closed part-way, then lifted
    assert episode.policy_speed == pytest.approx(episode.expert_speed) and episode.expert_speed > 0
    assert episode.first_close_cm is not None and episode.first_close_cm < 2.0  # it closes at the grasp point
    assert episode.furthest_phase == "lift"


def test_a_policy_at_half_the_experts_speed_is_measured_at_half(lift):
    task, env = lift
    own = _expert(task)

    def slow(obs):
        action = np.asarray(own(obs), dtype=np.float64).copy()
        action[:3] *= 0.5
        return action

    episode = shadow_episode(env, task, SEED, slow, _expert(task))
    assert episode.expert_speed > 0 and episode.policy_speed == pytest.approx(0.5 * episode.expert_speed)
    assert episode.cosines and np.allclose(episode.cosines, 1.0)  # the same direction at every state


def test_a_hand_that_closes_where_it_starts_is_a_grasp_tried_short(lift):
    task, env = lift
    start = env.reset(task, SEED).privileged
    distance_cm = 100 * float(np.linalg.norm(start["grasp"] + np.array([0.0, 0.0, -0.005]) - start["gripper"]))

    def closes_in_place(obs):
        return np.array([0, 0, 0, 0, 0, 0, 1.0])

    episode = shadow_episode(env, task, SEED, closes_in_place, _expert(task))
    assert not episode.success and episode.steps == task.horizon
    assert episode.closes_short == episode.steps  # the expert never closes: the hand is never at the cube
    assert episode.opens_early == 0 and episode.policy_speed == 0 and episode.expert_speed > 0
    assert episode.first_close_cm == pytest.approx(distance_cm) and distance_cm > 5
    assert episode.furthest_phase == "approach"

    case = CaseShadow(task.task_id, "seen", False).add(episode).add(episode)
    table = markdown([case], "a test policy")
    # a hand that never moves has no direction to compare: no cosine, speed 0
    assert (f"| lift-red | seen | 0/2 | {2 * task.horizon} | - | - | 0.00 | {2 * task.horizon} | 0 | {distance_cm:.1f} "
            "| approach 2 |") in table


def test_the_placement_table_tells_a_policy_that_follows_the_object_from_one_that_does_not(lift):
    """The expert's first move points at the cube, which each seed places elsewhere: the expert shadowing itself
    correlates perfectly across placements; a policy that always makes the same first move has nothing to correlate."""
    task, env = lift
    follows = CaseShadow(task.task_id, "seen", False, spec=task.spec)
    ignores = CaseShadow("lift-blind", "seen", False, spec="lift-blind")
    for seed in range(4):
        follows.add(shadow_episode(env, task, seed, make_expert(task, 0.0, np.random.default_rng(seed)),
                                   make_expert(task, 0.0, np.random.default_rng(seed))))
        ignores.add(shadow_episode(env, task, seed, lambda obs: np.array([0.5, 0.0, -0.5, 0, 0, 0, -1.0]),
                                   make_expert(task, 0.0, np.random.default_rng(seed))))
    rows = {line.split(" | ")[0].strip("| "): [cell.strip() for cell in line.strip("|").split(" | ")]
            for line in placement_markdown([follows, ignores]).splitlines() if line.startswith("| lift")}
    assert rows[task.spec][1:4] == ["4", "+1.00", "+1.00"]  # spec, episodes, r x, r y
    assert rows["lift-blind"][1:4] == ["4", "policy constant", "policy constant"]
    assert rows["lift-blind"][5].startswith("0.00 / ")  # the policy's spread in x is none, the expert's is not
    assert placement_markdown([follows], least=5) == ""  # too few episodes to correlate
    assert "starts from an object placement the model never trained on" in placement_markdown([follows])
    assert "training episodes started from" in placement_markdown([follows], trained=True)
