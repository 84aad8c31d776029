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

_clip = np.core.umath.clip  # the ufunc np.clip calls, without its Python wrappers (~5 us a call here)

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
    arm_ctrl: slice | np.ndarray  # the arm's and the gripper's entries of data.ctrl (a slice where contiguous)
    gripper_ctrl: slice | np.ndarray
    arm_range: tuple[np.ndarray, np.ndarray]  # their actuators' ctrlrange, low and high
    gripper_range: tuple[np.ndarray, np.ndarray]
    arm_qpos: slice | np.ndarray  # arm.qpos_index, arm.qvel_index, the gripper's, as slices where contiguous
    arm_qvel: slice | np.ndarray
    gripper_qpos: slice | np.ndarray
    gripper_qvel: slice | np.ndarray
    gripper_scaling: tuple[np.ndarray, np.ndarray] | None  # (bias, weight) of its action scaling, robosuite's arithmetic
    ref_site: int  # the end-effector site the OSC tracks
    centre_site: int  # the arm's base frame ("<prefix><arm>_center"), where its goal is expressed
    jacp: np.ndarray  # (3, nv) buffers for mj_jacSite and mj_fullM, as robosuite allocates them
    jacr: np.ndarray
    centre_jacp: np.ndarray
    centre_jacr: np.ndarray
    full_mass: np.ndarray


def _index(indexes) -> slice | np.ndarray:
    """robosuite's index list as a slice where it is a contiguous run (a view, no gather), else an array:
    the same elements either way."""
    indexes = np.asarray(indexes, dtype=np.int64).ravel()
    if len(indexes) and indexes[0] >= 0 and np.array_equal(indexes, np.arange(indexes[0], indexes[0] + len(indexes))):
        return slice(int(indexes[0]), int(indexes[0]) + len(indexes))
    return indexes


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
    arm_actuators = robot._ref_actuators_indexes_dict[arm_name]
    gripper_actuators = robot._ref_actuators_indexes_dict[gripper_name]
    ctrlrange = model._model.actuator_ctrlrange
    scaling = None
    if gripper.use_action_scaling:  # SimpleGripController.run_controller's bias and weight, computed as it does
        ctrl_range = np.stack([gripper.actuator_min, gripper.actuator_max], axis=-1)
        scaling = (0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0]), 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0]))
    return _Bound(
        sim=sim, model=model._model, data=sim.data._data, composite=composite, arm=arm, gripper=gripper,
        arm_ctrl=_index(arm_actuators), gripper_ctrl=_index(gripper_actuators),
        arm_range=(ctrlrange[arm_actuators, 0].copy(), ctrlrange[arm_actuators, 1].copy()),
        gripper_range=(ctrlrange[gripper_actuators, 0].copy(), ctrlrange[gripper_actuators, 1].copy()),
        arm_qpos=_index(arm.qpos_index), arm_qvel=_index(arm.qvel_index),
        gripper_qpos=_index(gripper.qpos_index), gripper_qvel=_index(gripper.qvel_index), gripper_scaling=scaling,
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
        data = bound.data
        # robot.control: the composite controller's update_state (the arm's base frame: update_origin) ...
        bound.arm.origin_pos = data.site_xpos[bound.centre_site].copy()
        bound.arm.origin_ori = data.site_xmat[bound.centre_site].reshape([3, 3]).copy()
        # ... then every part's run_controller, clipped to the actuators' ranges (np.clip's own ufunc)
        data.ctrl[bound.arm_ctrl] = _clip(self._arm_torques(bound), *bound.arm_range)
        data.ctrl[bound.gripper_ctrl] = _clip(self._gripper_vels(bound), *bound.gripper_range)
        self.fused += 1

    @staticmethod
    def _update_arm(bound: _Bound) -> None:
        """Controller.update (lite physics: no forward) with its one reference site. Copies where
        robosuite makes new arrays, in place where the fused path owns the buffer; the values are
        robosuite's either way (a copy or a view of the same floats)."""
        model, data, arm, site, qvel = bound.model, bound.data, bound.arm, bound.ref_site, bound.arm_qvel
        arm.ref_pos[:] = data.site_xpos[site]
        arm.ref_ori_mat[:, :] = data.site_xmat[site].reshape([3, 3])
        # robosuite asks MuJoCo for jacp and jacr in separate calls, three times; they are
        # computed independently, so one call gives the same numbers
        mujoco.mj_jacSite(model, data, bound.jacp, bound.jacr, site)
        arm.ref_pos_vel[:] = np.dot(bound.jacp, data.qvel)
        arm.ref_ori_vel[:] = np.dot(bound.jacr, data.qvel)
        arm.J_pos[:, :] = bound.jacp[:, qvel]
        arm.J_ori[:, :] = bound.jacr[:, qvel]
        arm.J_full[:3] = arm.J_pos
        arm.J_full[3:] = arm.J_ori
        arm.joint_pos = data.qpos[bound.arm_qpos].copy()
        arm.joint_vel = data.qvel[qvel].copy()
        mujoco.mj_fullM(model, bound.full_mass, data.qM)
        # robosuite's own gather: it leaves the matrix Fortran-ordered, and numba compiles its kernels
        # per layout (a C-ordered copy of the same numbers takes another BLAS path there: other bits)
        arm.mass_matrix = bound.full_mass[arm.qvel_index, :][:, arm.qvel_index]
        arm.new_update = False

    def _arm_torques(self, bound: _Bound) -> np.ndarray:
        """OperationalSpaceController.run_controller without interpolators, goal in the base frame:
        every dot product the same call on the same layouts as robosuite's (the same BLAS kernel)."""
        opspace_matrices, orientation_error, nullspace_torques = self.kernels
        arm, data = bound.arm, bound.data
        self._update_arm(bound)
        desired_world_pos = arm.origin_pos + np.dot(arm.origin_ori, arm.goal_pos)
        desired_world_ori = np.dot(arm.origin_ori, arm.goal_ori)
        ori_error = orientation_error(desired_world_ori, arm.ref_ori_mat)

        position_error = desired_world_pos - arm.ref_pos
        mujoco.mj_jacSite(bound.model, data, bound.centre_jacp, bound.centre_jacr, bound.centre_site)
        base_pos_vel = np.dot(bound.centre_jacp, data.qvel)
        vel_pos_error = -(arm.ref_pos_vel - base_pos_vel)
        kp, kd = arm.kp, arm.kd
        desired_force = np.multiply(position_error, kp[0:3]) + np.multiply(vel_pos_error, kd[0:3])
        base_ori_vel = np.dot(bound.centre_jacr, data.qvel)
        vel_ori_error = -(arm.ref_ori_vel - base_ori_vel)
        desired_torque = np.multiply(ori_error, kp[3:6]) + np.multiply(vel_ori_error, kd[3:6])

        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(
            arm.mass_matrix, arm.J_full, arm.J_pos, arm.J_ori
        )
        if arm.uncoupling:
            decoupled_wrench = np.concatenate([np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)])
        else:
            decoupled_wrench = np.dot(lambda_full, np.concatenate([desired_force, desired_torque]))
        torques = np.dot(arm.J_full.T, decoupled_wrench) + data.qfrc_bias[bound.arm_qvel]
        torques += nullspace_torques(arm.mass_matrix, nullspace_matrix, arm.initial_joint, arm.joint_pos, arm.joint_vel)
        arm.torques = torques
        arm.new_update = True
        return torques

    @staticmethod
    def _gripper_vels(bound: _Bound) -> np.ndarray:
        """SimpleGripController.run_controller without an interpolator (its goal set at the policy step)."""
        gripper, data = bound.gripper, bound.data
        gripper.joint_pos = data.qpos[bound.gripper_qpos].copy()
        gripper.joint_vel = data.qvel[bound.gripper_qvel].copy()
        desired_qvel = np.array(gripper.goal_qvel)
        gripper.vels = desired_qvel
        if bound.gripper_scaling is not None:
            bias, weight = bound.gripper_scaling
            gripper.vels = bias + weight * desired_qvel
        gripper.new_update = True
        return gripper.vels
