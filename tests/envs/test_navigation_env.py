"""Our own MuJoCo multi-room scene: discrete actions, real contacts, egocentric rendering."""

import mujoco
import numpy as np
import pytest

from envs.navigation_env import ACTIONS, ROOM_SIZE, NavigationEnv, NavigationExpert
from envs.rollout import rollout
from envs.suite import generate_tasks
from schemas.config import RenderConfig, TasksConfig


def _task(task_id: str):
    [task] = generate_tasks(TasksConfig(specs=[task_id.rsplit("-", 1)[0] if "sequence" not in task_id
                                               else "nav-room-sequence"], include=[task_id]), seed=0)
    return task


@pytest.mark.parametrize("task_id", ["nav-room-red", "nav-ball-blue", "nav-box-green", "nav-room-sequence-yellow-red"])
def test_the_planner_solves_each_kind_of_navigation_task(task_id):
    task = _task(task_id)
    env = NavigationEnv(task.env_name, RenderConfig())
    successes = 0
    for seed in range(3):
        rows, final, success = rollout(env, task, seed, NavigationExpert(0.1, np.random.default_rng(seed)).act)
        successes += success
        assert final.image.shape == (84, 84, 3) and all(len(r["action"]) == 1 for r in rows)
    env.close()
    assert successes == 3


def test_the_long_horizon_task_needs_both_rooms_in_order():
    task = _task("nav-room-sequence-yellow-red")
    env = NavigationEnv(task.env_name, None)
    env.reset(task, seed=2)
    second = env.room_colours.index("red")
    env.data.qpos[:2] = [(second + 0.5) * ROOM_SIZE, ROOM_SIZE / 2]  # straight to the second room
    _, _, success = env.step(np.array([ACTIONS.index("turn_left")]))
    assert not success and env.stage == 0
    first = env.room_colours.index("yellow")
    env.data.qpos[:2] = [(first + 0.5) * ROOM_SIZE, ROOM_SIZE / 2]
    _, _, success = env.step(np.array([ACTIONS.index("turn_left")]))
    assert not success and env.stage == 1
    env.data.qpos[:2] = [(second + 0.5) * ROOM_SIZE, ROOM_SIZE / 2]
    _, _, success = env.step(np.array([ACTIONS.index("turn_left")]))
    assert success


def test_walls_stop_the_agent():
    task = _task("nav-room-red")
    env = NavigationEnv(task.env_name, None)
    env.reset(task, seed=0)
    env.data.qpos[:3] = [1.0, 1.0, np.pi]  # facing the west wall, 1 m away
    for _ in range(30):
        env.step(np.array([ACTIONS.index("forward")]))
    assert 0.15 < env.data.qpos[0] < 0.3  # pressed against the wall (radius 0.2), not through it


def test_depth_is_metres_along_the_camera_axis_and_leaves_the_frame_as_it_was():
    task = _task("nav-room-red")
    frames = {}
    for depth in (False, True):
        env = NavigationEnv(task.env_name, RenderConfig(depth=depth))
        env.reset(task, seed=0)
        env.data.qpos[:3] = [1.0, 1.0, np.pi]  # facing the west wall (x = 0), 1 m away
        mujoco.mj_forward(env.model, env.data)
        frames[depth] = env._observation()
        env.close()
    assert frames[False].depth is None and np.array_equal(frames[False].image, frames[True].image)
    # the ego camera sits 0.15 m ahead of the body, its axis tilted down by atan(0.2)
    expected = 0.85 / np.cos(np.arctan(0.2))
    assert frames[True].depth.shape == (84, 84) and abs(frames[True].depth[42, 42] - expected) < 0.01


def test_layouts_follow_the_seed_and_always_hold_the_task_colours():
    task = _task("nav-ball-orange")
    env = NavigationEnv(task.env_name, None)
    first = env.reset(task, seed=4).proprio.copy(), dict(env.objects)
    env.reset(task, seed=5)
    again = env.reset(task, seed=4).proprio.copy(), dict(env.objects)
    assert np.array_equal(first[0], again[0]) and first[1].keys() == again[1].keys()
    assert all(np.array_equal(first[1][k], again[1][k]) for k in first[1])  # the same places, not just the same objects
    assert ("ball", "orange") in again[1]
    env.reset(task, seed=5)
    other = dict(env.objects)  # another seed, another layout
    assert other.keys() != first[1].keys() or not all(np.allclose(other[k], first[1][k]) for k in other)


def test_bad_actions_are_refused():
    task = _task("nav-room-red")
    env = NavigationEnv(task.env_name, None)
    env.reset(task, seed=0)
    with pytest.raises(ValueError, match="navigation action must be 0..3"):
        env.step(np.array([7]))


def test_frames_stay_real_when_robosuite_renders_in_the_same_worker():
    """A worker caches one env per family; robosuite's renderer used to leave ours reading black."""
    from envs.robosuite_env import RobosuiteEnv

    task = _task("nav-room-red")
    navigation, robosuite = NavigationEnv("GoToRoom", RenderConfig()), RobosuiteEnv("Lift", RenderConfig())
    try:
        [lift] = generate_tasks(TasksConfig(specs=["lift"], include=["lift-red"]), seed=0)
        before = navigation.reset(task, seed=3).image
        robosuite.reset(lift, seed=3)
        after = navigation.reset(task, seed=3).image
        assert before.mean() > 20 and np.array_equal(before, after)
    finally:
        robosuite.close()
        navigation.close()


def test_robosuite_frames_stay_real_when_other_envs_render_or_close_in_the_same_worker():
    """robosuite draws into whichever GL context is current, and frees its GL objects in it on close:
    a navigation env made after it used to get its frames, a closed robosuite env to delete its objects."""
    from envs.robosuite_env import RobosuiteEnv

    [lift] = generate_tasks(TasksConfig(specs=["lift"], include=["lift-red"]), seed=0)
    robosuite = RobosuiteEnv("Lift", RenderConfig())
    try:
        first = robosuite.reset(lift, seed=3).image
        navigation = NavigationEnv("GoToRoom", RenderConfig())
        navigation.reset(_task("nav-room-red"), seed=3)
        RobosuiteEnv("Lift", RenderConfig()).close()
        assert first.mean() > 20 and np.array_equal(robosuite.reset(lift, seed=3).image, first)
        navigation.close()
    finally:
        robosuite.close()
