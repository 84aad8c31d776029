"""robosuite's arm control between policy steps, without its per-call bookkeeping.

robosuite runs the arm's operational-space controller (OSC) at every physics substep, 25 per step
at 20 Hz, and each time it resolves site names, rebuilds the action limits three times, asks
MuJoCo for the same site Jacobians three times and walks its composite-controller dictionaries:
in a no-camera Lift step (8.3 ms here) 6.8 ms are Python around 1.5 ms of physics. Between policy
steps the goal is fixed, so a substep's torques are a function of the MuJoCo state alone.
`FusedSubsteps` computes them with the same arithmetic, in the same order and through the same
numba kernels, on ids resolved once per episode — bit for bit robosuite's torques (checked
against the stock controller in tests/envs/test_robosuite_control.py), so the data does not
change. The first substep of each step (setting the goal, robosuite's proprioceptive history)
still goes through robosuite, and any setup this module was not written for (another controller,
interpolators, more than one arm or robot, an environment with its own `_pre_action`) keeps
robosuite's own path throughout.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import mujoco
import numpy as np

# set to "1" in a process's environment (before it makes its environments): robosuite's own path
# throughout, for benchmarks that compare the two
STOCK_CONTROL = "SIM2ACT_STOCK_ROBOSUITE_CONTROL"


@contextmanager
def controller_path(stock: bool) -> Iterator[None]:
    """Environments made meanwhile (here, or in workers spawned meanwhile) take robosuite's own
    controller path (stock) or the fused substeps; the variable is restored afterwards."""
    before = os.environ.get(STOCK_CONTROL)
    os.environ[STOCK_CONTROL] = "1" if stock else "0"
    try:
        yield
    finally:
        if before is None:
            del os.environ[STOCK_CONTROL]
        else:
            os.environ[STOCK_CONTROL] = before


@dataclass
class _Bound:
    """One episode's controllers, the simulator they drive and the ids and indexes they read
    (robosuite makes new controllers at every reset, and a new simulator at a hard reset)."""

    sim: object  # robosuite's MjSim the controllers were made on
    model: mujoco.MjModel
    data: mujoco.MjData
    composite: object
    arm: object  # robosuite OperationalSpaceController
    gripper: object  # robosuite SimpleGripController
    arm_actuators: list[int]
    gripper_actuators: list[int]
    ref_site: int  # the end-effector site the OSC tracks
    centre_site: int  # the arm's base frame ("<prefix><arm>_center"), where its goal is expressed
    jacp: np.ndarray  # (3, nv) buffers for mj_jacSite and mj_fullM, as robosuite allocates them
    jacr: np.ndarray
    centre_jacp: np.ndarray
    centre_jacr: np.ndarray
    full_mass: np.ndarray


def _bind(env, robot) -> _Bound | None:
    """The controllers of `robot` in `env` if they are the setup this module reproduces, else None."""
    from robosuite.controllers.composite.composite_controller import CompositeController
    from robosuite.controllers.parts.arm.osc import OperationalSpaceController
    from robosuite.controllers.parts.gripper.simple_grip import SimpleGripController
    from robosuite.environments.robot_env import RobotEnv
    from robosuite.robots.fixed_base_robot import FixedBaseRobot

    # an environment class with its own _pre_action does more per substep than robot.control
    if type(env)._pre_action is not RobotEnv._pre_action or env.lite_physics is not True:
        return None
    if type(robot) is not FixedBaseRobot or len(robot.arms) != 1:
        return None
    arm_name = robot.arms[0]
    gripper_name = robot.get_gripper_name(arm_name)
    composite = robot.composite_controller
    parts = composite.part_controllers
    if (type(composite) is not CompositeController or set(parts) != {arm_name, gripper_name}
            or not all(robot._enabled_parts.get(p, False) for p in parts)):
        return None
    arm, gripper = parts[arm_name], parts[gripper_name]
    if (
        type(arm) is not OperationalSpaceController or arm.interpolator_pos is not None
        or arm.interpolator_ori is not None or arm.input_ref_frame != "base" or arm.num_ref_sites != 1
        or not arm.lite_physics or type(gripper) is not SimpleGripController or gripper.interpolator is not None
        or not (arm.sim is gripper.sim is robot.sim is env.sim)
    ):
        return None
    sim = env.sim
    model, nv = sim.model, sim.model.nv
    return _Bound(
        sim=sim, model=model._model, data=sim.data._data, composite=composite, arm=arm, gripper=gripper,
        arm_actuators=robot._ref_actuators_indexes_dict[arm_name],
        gripper_actuators=robot._ref_actuators_indexes_dict[gripper_name],
        ref_site=model.site_name2id(arm.ref_name),
        centre_site=model.site_name2id(f"{arm.naming_prefix}{arm.part_name}_center"),
        jacp=np.zeros((3, nv)), jacr=np.zeros((3, nv)), centre_jacp=np.zeros((3, nv)), centre_jacr=np.zeros((3, nv)),
        full_mass=np.ndarray(shape=(nv, nv), dtype=np.float64, order="C"),
    )


class FusedSubsteps:
    """Installs itself as `env._pre_action`: policy substeps go to robosuite's, the others are
    computed here when the robot's setup is the one reproduced (`active`)."""

    def __init__(self, env):
        from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error

        self.env = env
        self.stock_pre_action = env._pre_action
        self.kernels = (opspace_matrices, orientation_error, nullspace_torques)  # robosuite's numba kernels
        self.bound: _Bound | None = None
        self.fused = 0  # substeps computed here (tests, benchmarks)
        env._pre_action = self.pre_action

    @property
    def active(self) -> bool:
        return self.bound is not None

    def pre_action(self, action, policy_step: bool = False) -> None:
        bound = self.bound
        if policy_step or bound is None or bound.sim is not self.env.sim:
            self.stock_pre_action(action, policy_step)
            if policy_step:  # (re)bind after robosuite's goal setting: new controllers come with each reset
                robots = self.env.robots
                if (bound is None or len(robots) != 1 or robots[0].composite_controller is not bound.composite
                        or bound.sim is not self.env.sim):
                    self.bound = _bind(self.env, robots[0]) if len(robots) == 1 else None
            return
        data, model = bound.data, bound.model
        # robot.control: the composite controller's update_state (the arm's base frame) ...
        origin_pos = np.array(data.site_xpos[bound.centre_site])
        origin_ori = np.array(data.site_xmat[bound.centre_site].reshape([3, 3]))
        bound.arm.update_origin(origin_pos, origin_ori)
        # ... then every part's run_controller, clipped to the actuators' ranges
        torques = self._arm_torques(bound)
        vels = self._gripper_vels(bound)
        ctrlrange = model.actuator_ctrlrange
        data.ctrl[bound.arm_actuators] = np.clip(
            torques, ctrlrange[bound.arm_actuators, 0], ctrlrange[bound.arm_actuators, 1]
        )
        data.ctrl[bound.gripper_actuators] = np.clip(
            vels, ctrlrange[bound.gripper_actuators, 0], ctrlrange[bound.gripper_actuators, 1]
        )
        self.fused += 1

    @staticmethod
    def _update_arm(bound: _Bound) -> None:
        """Controller.update (lite physics: no forward) with its one reference site."""
        model, data, arm, site = bound.model, bound.data, bound.arm, bound.ref_site
        arm.ref_pos[:] = np.array(data.site_xpos[site])
        arm.ref_ori_mat[:, :] = np.array(data.site_xmat[site].reshape([3, 3]))
        # robosuite asks MuJoCo for jacp and jacr in separate calls, three times; they are
        # computed independently, so one call gives the same numbers
        mujoco.mj_jacSite(model, data, bound.jacp, bound.jacr, site)
        arm.ref_pos_vel[:] = np.array(np.dot(bound.jacp, data.qvel))
        arm.ref_ori_vel[:] = np.array(np.dot(bound.jacr, data.qvel))
        arm.J_pos[:, :] = np.array(bound.jacp.reshape((3, -1))[:, arm.qvel_index])
        arm.J_ori[:, :] = np.array(bound.jacr.reshape((3, -1))[:, arm.qvel_index])
        arm.J_full[:, :] = np.vstack([arm.J_pos, arm.J_ori])
        arm.joint_pos = np.array(data.qpos[arm.qpos_index])
        arm.joint_vel = np.array(data.qvel[arm.qvel_index])
        mujoco.mj_fullM(model, bound.full_mass, data.qM)
        arm.mass_matrix = bound.full_mass[arm.qvel_index, :][:, arm.qvel_index]
        arm.new_update = False

    def _arm_torques(self, bound: _Bound) -> np.ndarray:
        """OperationalSpaceController.run_controller without interpolators, goal in the base frame."""
        opspace_matrices, orientation_error, nullspace_torques = self.kernels
        arm, data = bound.arm, bound.data
        self._update_arm(bound)
        desired_world_pos = arm.origin_pos + np.dot(arm.origin_ori, arm.goal_pos)
        desired_world_ori = np.dot(arm.origin_ori, arm.goal_ori)
        ori_error = orientation_error(desired_world_ori, arm.ref_ori_mat)

        position_error = desired_world_pos - arm.ref_pos
        mujoco.mj_jacSite(bound.model, data, bound.centre_jacp, bound.centre_jacr, bound.centre_site)
        base_pos_vel = np.array(np.dot(bound.centre_jacp, data.qvel))
        vel_pos_error = -(arm.ref_pos_vel - base_pos_vel)
        desired_force = np.multiply(np.array(position_error), np.array(arm.kp[0:3])) + np.multiply(
            vel_pos_error, arm.kd[0:3]
        )
        base_ori_vel = np.array(np.dot(bound.centre_jacr, data.qvel))
        vel_ori_error = -(arm.ref_ori_vel - base_ori_vel)
        desired_torque = np.multiply(np.array(ori_error), np.array(arm.kp[3:6])) + np.multiply(
            vel_ori_error, arm.kd[3:6]
        )

        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(
            arm.mass_matrix, arm.J_full, arm.J_pos, arm.J_ori
        )
        if arm.uncoupling:
            decoupled_wrench = np.concatenate([np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)])
        else:
            decoupled_wrench = np.dot(lambda_full, np.concatenate([desired_force, desired_torque]))
        arm.torques = np.dot(arm.J_full.T, decoupled_wrench) + data.qfrc_bias[arm.qvel_index]
        arm.torques += nullspace_torques(arm.mass_matrix, nullspace_matrix, arm.initial_joint, arm.joint_pos, arm.joint_vel)
        arm.new_update = True
        return arm.torques

    @staticmethod
    def _gripper_vels(bound: _Bound) -> np.ndarray:
        """SimpleGripController.run_controller without an interpolator (its goal set at the policy step)."""
        gripper, data = bound.gripper, bound.data
        gripper.joint_pos = np.array(data.qpos[gripper.qpos_index])
        gripper.joint_vel = np.array(data.qvel[gripper.qvel_index])
        desired_qvel = np.array(gripper.goal_qvel)
        gripper.vels = desired_qvel
        if gripper.use_action_scaling:
            ctrl_range = np.stack([gripper.actuator_min, gripper.actuator_max], axis=-1)
            bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
            weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])
            gripper.vels = bias + weight * desired_qvel
        gripper.new_update = True
        return gripper.vels
