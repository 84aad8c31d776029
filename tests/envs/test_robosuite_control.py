"""The fused substeps (envs/robosuite_control.py) against robosuite's own controller: real robosuite,
the same episodes stepped side by side, every MuJoCo state compared bit for bit."""

import numpy as np

from envs import robosuite_control
from envs.registry import make_expert
from envs.robosuite_control import STOCK_CONTROL
from envs.robosuite_env import RobosuiteEnv
from schemas.tasks import TaskRecord


def _task(env_name: str, task_id: str, colours: dict[str, str], horizon: int) -> TaskRecord:
    return TaskRecord(task_id=task_id, spec=task_id.rsplit("-", 1)[0], family="robosuite", env_name=env_name,
                      object_colours=colours, instructions=["a", "b", "c"], split="seen", horizon=horizon)


def _pair(monkeypatch, env_name: str) -> tuple[RobosuiteEnv, RobosuiteEnv]:
    """(robosuite's controller, the fused substeps), no camera."""
    with monkeypatch.context() as patch:
        patch.setenv(STOCK_CONTROL, "1")
        stock = RobosuiteEnv(env_name, None)
    assert stock.fused_control is None
    return stock, RobosuiteEnv(env_name, None)


def _same_state(a: RobosuiteEnv, b: RobosuiteEnv) -> bool:
    da, db = a.env.sim.data._data, b.env.sim.data._data
    return all(np.array_equal(getattr(da, name), getattr(db, name)) for name in ("qpos", "qvel", "ctrl", "act", "qacc"))


def _step_both(stock: RobosuiteEnv, fused: RobosuiteEnv, task: TaskRecord, seed: int, act) -> tuple[int, bool, float]:
    """One episode on both; -> (steps, success, largest gripper command). Fails at the first state that differs."""
    obs, other = stock.reset(task, seed), fused.reset(task, seed)
    assert _same_state(stock, fused)
    gripper_closed = -1.0
    for step in range(task.horizon):
        action = np.asarray(act(obs), dtype=np.float32)
        gripper_closed = max(gripper_closed, float(action[-1]))
        (obs, reward, success), (other, other_reward, other_success) = stock.step(action), fused.step(action)
        assert _same_state(stock, fused), f"{task.task_id} seed {seed}: the states differ after step {step}"
        assert (reward, success) == (other_reward, other_success)
        assert np.array_equal(obs.proprio, other.proprio)
        if success:
            return step + 1, True, gripper_closed
    return task.horizon, False, gripper_closed


def test_fused_substeps_give_robosuites_states_bit_for_bit_through_a_grasp(monkeypatch):
    stock, fused = _pair(monkeypatch, "Lift")
    task = _task("Lift", "lift-red", {"target": "red"}, horizon=80)
    try:
        successes, total = 0, 0
        for seed in range(2):
            steps, success, gripper = _step_both(stock, fused, task, seed, make_expert(task, 0.1, np.random.default_rng(seed)))
            successes += success
            total += steps
            assert gripper > 0.5  # the expert closed the gripper: contact and the gripper's controller covered
        assert successes >= 1
        # the fused path computed every substep but each step's first (robosuite's goal setting)
        assert fused.fused_control.fused == 24 * total
    finally:
        stock.close()
        fused.close()


def test_fused_substeps_follow_robosuites_new_controllers_across_resets(monkeypatch):
    """robosuite makes new controllers at every reset; random actions on another scene (Door)."""
    stock, fused = _pair(monkeypatch, "Door")
    task = _task("Door", "door-red", {"door": "red"}, horizon=25)
    rng = np.random.default_rng(0)
    try:
        controllers, total = [], 0
        for seed in range(3):
            total += _step_both(stock, fused, task, seed, lambda _obs: rng.uniform(-1, 1, 7))[0]
            controllers.append(fused.fused_control.bound.arm)  # kept alive: their ids stay distinct
        assert len({id(arm) for arm in controllers}) == 3
        assert fused.fused_control.fused == 24 * total
    finally:
        stock.close()
        fused.close()


def test_a_controller_setup_not_reproduced_keeps_robosuites_path(monkeypatch):
    """Another setup (here: the goal in world coordinates) is not what the fused substeps compute."""
    env = RobosuiteEnv("Lift", None)
    task = _task("Lift", "lift-red", {"target": "red"}, horizon=5)
    try:
        env.reset(task, 0)
        arm = env.env.robots[0].composite_controller.part_controllers["right"]
        assert robosuite_control._bind(env.env, env.env.robots[0]) is not None
        arm.input_ref_frame = "world"
        assert robosuite_control._bind(env.env, env.env.robots[0]) is None

        monkeypatch.setattr(robosuite_control, "_bind", lambda env, robot: None)
        env.reset(task, 1)
        arm = env.env.robots[0].composite_controller.part_controllers["right"]
        calls, stock_run = [], arm.run_controller
        arm.run_controller = lambda: calls.append(1) or stock_run()
        env.step(np.zeros(7, dtype=np.float32))
        assert not env.fused_control.active and env.fused_control.fused == 0
        assert len(calls) == 25  # robosuite's controller at every substep, not only the policy's
    finally:
        env.close()


def test_the_variable_keeps_robosuites_path(monkeypatch):
    monkeypatch.setenv(STOCK_CONTROL, "1")
    env = RobosuiteEnv("Lift", None)
    try:
        assert env.fused_control is None
        assert "_pre_action" not in vars(env.env)
    finally:
        env.close()


def test_index_lists_become_slices_only_where_they_select_the_same_elements():
    from envs.robosuite_control import _index

    values = np.arange(10.0)
    for indexes in ([0, 1, 2, 3, 4, 5, 6], [7, 8], [3], [1, 3, 4], [5, 4], [-3, -2, -1], [-2, -1, 0], []):
        index = _index(indexes)
        assert np.array_equal(values[index], values[indexes]), indexes
    assert _index([7, 8]) == slice(7, 9) and not isinstance(_index([-2, -1]), slice)
