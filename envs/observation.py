"""What every simulator adapter returns, and the action/proprio convention they share.

Manipulation families speak one action space, end-effector deltas and a gripper command:
(dx, dy, dz, rx, ry, rz, grip) in [-1, 1], grip > 0 closes. Proprio is (eef xyz, eef quat xyzw as
robosuite gives it, two gripper coordinates); MetaWorld's Sawyer never turns its hand, and its quat is a
constant (1, 0, 0, 0) — in xyzw a hand pointing down, as the Panda's. An adapter maps its simulator's own spaces onto these, so one policy
trains across families.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTION_COMPONENTS = ("dx", "dy", "dz", "rx", "ry", "rz", "grip")  # the continuous action, in order
ACTION_DIM = len(ACTION_COMPONENTS)
PROPRIO_DIM = 9
# Families that act by the index of an action from a discrete set, stored as [index] (navigation).
DISCRETE_FAMILIES = frozenset({"navigation"})
NAVIGATION_ACTIONS = ("forward", "turn_left", "turn_right", "backward")  # its discrete action set, by index
# The continuous components a family's simulator acts on: MetaWorld's Sawyer moves and grips, no wrist
# rotation (envs/metaworld_env.to_metaworld_action drops rx, ry, rz).
ACTING_COMPONENTS = {"metaworld": ("dx", "dy", "dz", "grip")}
NO_IMAGE = np.zeros((0, 0, 3), dtype=np.uint8)  # what a camera-less adapter returns


@dataclass
class Observation:
    image: np.ndarray  # uint8 (H, W, 3), upright; OpenGL rows run bottom-up, adapters flip them
    proprio: np.ndarray  # float32 (PROPRIO_DIM,)
    privileged: dict[str, np.ndarray]  # simulator state only scripted experts may read
    depth: np.ndarray | None = None  # float32 (H, W) metres along the camera axis, upright; render.depth only


def metric_depth(zbuffer: np.ndarray, model) -> np.ndarray:
    """OpenGL's depth buffer (non-linear, in [0, 1]) as metres along the camera axis, with the
    model's clip planes (what mujoco.Renderer does for itself); 0 where nothing was drawn."""
    extent = model.stat.extent
    near, far = model.vis.map.znear * extent, model.vis.map.zfar * extent
    zbuffer = np.asarray(zbuffer, dtype=np.float64)
    metres = near / (1.0 - zbuffer * (1.0 - near / far))
    return np.where(zbuffer < 1.0, metres, 0.0).astype(np.float32)


@dataclass
class MujocoState:
    """What replay sets back into the model to reproduce a step (stored per step, float64)."""

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray  # actuator activations; empty for models without stateful actuators
    mocap: np.ndarray  # mocap body positions (3 each) then quaternions (4 each)
    time: float

    @classmethod
    def of(cls, data) -> MujocoState:
        """Copy the state out of a mujoco.MjData."""
        return cls(
            data.qpos.copy(), data.qvel.copy(), data.act.copy(),
            np.concatenate([data.mocap_pos.ravel(), data.mocap_quat.ravel()]), float(data.time),
        )

    def restore(self, model, data, before_last_substep: bool = False) -> None:
        """Write this state into a mujoco.MjData and recompute what rendering reads.

        before_last_substep: place the bodies one physics substep back, where a frame drawn right
        after mj_step shows them: mj_step computes the poses, then integrates qpos with the new
        qvel (Euler and implicit integrators, all our models'), which qpos - dt * qvel undoes up to
        rounding."""
        import mujoco  # here, not at module level: mujoco picks its GL backend (MUJOCO_GL) when first imported

        data.qpos[:] = self.qpos
        data.qvel[:] = self.qvel
        data.act[:] = self.act
        data.time = self.time
        bodies = model.nmocap
        data.mocap_pos[:] = self.mocap[: 3 * bodies].reshape(bodies, 3)
        data.mocap_quat[:] = self.mocap[3 * bodies :].reshape(bodies, 4)
        if before_last_substep:
            mujoco.mj_integratePos(model, data.qpos, data.qvel, -model.opt.timestep)
        mujoco.mj_forward(model, data)
