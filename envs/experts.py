"""Scripted privileged-state experts: they read object positions, which policies never see."""

from __future__ import annotations

from enum import Enum, auto

import mujoco
import numpy as np

from envs.observation import ACTION_DIM, Observation

GAIN = 12.0  # action = GAIN * position error; 1.0 asks OSC for its largest step (5 cm)
OPEN, CLOSED = -1.0, 1.0
# Steps a converging phase may take before the expert accepts "close enough" and goes on: a
# finger resting on a randomly turned cube's corner, or a cube shifted in the grasp, would
# otherwise hold the expert in one phase until the horizon.
PATIENCE = 25
DROPPED = 0.04  # grasp point this far from the fingers while carrying: the object is not in the hand
TURN_GAIN, ALIGNED = 3.0, 0.1  # wrist yaw: action per radian of error; radians counted as aligned
BACK_OFF = 12  # steps spent letting go and rising between placements
GRASP_STEPS = 10  # fingers take ~0.5 s to close on a thin nut handle
AT_GRASP, ABOVE_LINE = 0.025, 0.01  # metres: the hand counted at the grasp point; on the line above it
GRASP_DEPTH = np.array([0.0, 0.0, -0.005])  # where the fingertips close, from the scene's "grasp" point


def expert_phase(expert) -> tuple[int, str]:
    """(order, name) of a stateful expert's current phase; (0, "-") for one without phases."""
    phase = getattr(expert, "phase", None)
    return (0, "-") if phase is None else (phase.value, phase.name.lower())


def hand_to_grasp(seen: dict[str, np.ndarray]) -> float | None:
    """Metres from the hand to where its fingertips would close on the object (a scene's privileged
    "grasp" point, GRASP_DEPTH below it); None for a scene without one (a door, MetaWorld, navigation)."""
    if "grasp" not in seen or "gripper" not in seen:
        return None
    return float(np.linalg.norm(seen["grasp"] + GRASP_DEPTH - seen["gripper"]))


def horizontal(vector: np.ndarray) -> np.ndarray:
    """`vector` flattened onto the floor, as a unit vector."""
    flat = np.array([vector[0], vector[1], 0.0])
    return flat / max(float(np.linalg.norm(flat)), 1e-9)


def grip_turn(grip_axis: np.ndarray, finger_angle: float) -> float:
    """Radians to turn fingers heading `finger_angle` (atan2 of their axis) onto `grip_axis`, the
    shorter way: two fingers look the same every half turn, so within [-pi/2, pi/2)."""
    return float((np.arctan2(grip_axis[1], grip_axis[0]) - finger_angle + np.pi / 2) % np.pi - np.pi / 2)


def _matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of a robosuite quaternion (x, y, z, w order)."""
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.roll(quat_xyzw, 1))
    return matrix.reshape(3, 3)


class Phase(Enum):
    APPROACH = auto()
    DESCEND = auto()
    GRASP = auto()
    LIFT = auto()
    CARRY = auto()
    LOWER = auto()
    RELEASE = auto()


class PickPlaceExpert:
    """Grasp, then lift and hold (no goal) or carry to the goal and let go: the robosuite scenes
    describe what to grasp and where it goes (envs.robosuite_env), this follows them."""

    def __init__(self, noise: float, rng: np.random.Generator):
        self.noise, self.rng = noise, rng
        self.phase, self.hold, self.waited, self.stage, self.next_stage = Phase.APPROACH, 0, 0, None, False
        self.wrist, self.finger_angle = 0.0, None  # radians turned since the start; the fingers' last heading
        self.aim: float | None = None  # the wrist angle this phase turns to

    def _towards(self, obs: Observation, target: np.ndarray, gripper: float, turn: float = 0.0) -> np.ndarray:
        action = np.zeros(ACTION_DIM)
        action[:3] = np.clip(GAIN * (target - obs.privileged["gripper"]), -1.0, 1.0)
        # keep the hand pointing straight down: noise on the rotation actions random-walks its tilt,
        # and over a long task a tilted hand puts a finger on the object
        pointing = _matrix(obs.privileged["gripper_quat"])[:, 2]
        action[3:5] = np.clip(TURN_GAIN * np.cross(pointing, [0.0, 0.0, -1.0])[:2], -1.0, 1.0)
        action[5] = np.clip(TURN_GAIN * turn, -1.0, 1.0)
        action[6] = gripper
        return action

    def _track_wrist(self, obs: Observation) -> None:
        axis = obs.privileged["finger_axis"]
        angle = float(np.arctan2(axis[1], axis[0]))
        if self.finger_angle is not None:
            self.wrist += (angle - self.finger_angle + np.pi) % (2 * np.pi) - np.pi
        self.finger_angle = angle

    def _turn_to_grip(self, obs: Observation) -> float:
        """Radians to turn the wrist so the fingers open along the scene's grip axis (two fingers
        look the same every half turn); the way chosen is kept for the rest of the phase."""
        wanted = obs.privileged["grip_axis"]
        if not wanted[:2].any():
            return 0.0
        turn = grip_turn(wanted, self.finger_angle)
        ways = (turn, turn - np.pi, turn + np.pi)
        if self.aim is not None:  # keep the way chosen: at a right angle both are equally near, and noise flips them
            turn = min(ways, key=lambda way: abs(self.wrist + way - self.aim))
        else:  # the way that ends nearest the wrist's start: its last joint has ~2 rad of travel each way
            turn = min(ways, key=lambda way: abs(self.wrist + way))
        self.aim = self.wrist + turn
        return turn

    def _go(self, phase: Phase) -> None:
        self.phase, self.hold, self.waited, self.aim = phase, 0, 0, None

    def _catch_up(self, eef: np.ndarray, grasp_point: np.ndarray, above: np.ndarray) -> None:
        """Leave APPROACH for the phase the hand is already in: on the line above the object
        (descend) or at its grasp point (grasp). A DAgger labeller follows another explorer's hand,
        which reaches the object without stopping at this expert's waypoint above it; waiting for
        that waypoint labelled every grasp the labeller did not make itself "open, go back up"
        (4% of the labels on the policy's successful Lift episodes said "closed")."""
        if np.linalg.norm(grasp_point - eef) < AT_GRASP:
            self._go(Phase.GRASP)
        elif np.linalg.norm((above - eef)[:2]) < ABOVE_LINE and grasp_point[2] < eef[2] < above[2] + 0.02:
            self._go(Phase.DESCEND)

    def _converged(self, error: float, tolerance: float, fallback: float) -> bool:
        """Within tolerance; or, after PATIENCE steps in this phase, within the looser fallback."""
        self.waited += 1
        return error < tolerance or (self.waited > PATIENCE and error < fallback)

    def _advance(self, obs: Observation) -> np.ndarray:
        seen = obs.privileged
        self._track_wrist(obs)
        if "stage" in seen and seen["stage"][0] != self.stage:
            if self.stage is not None:  # the next placement: let go, back off, start over
                self.next_stage = True
                self._go(Phase.RELEASE)
            self.stage = float(seen["stage"][0])
        grasp, eef = seen["grasp"], seen["gripper"]
        above = grasp + np.array([0.0, 0.0, 0.08])
        grasp_point = grasp + GRASP_DEPTH
        if self.phase is Phase.APPROACH:
            turn = self._turn_to_grip(obs)
            if abs(turn) < ALIGNED:
                self._catch_up(eef, grasp_point, above)
            if self.phase is Phase.APPROACH:
                return self._towards(obs, above, OPEN, turn)
        if self.phase is Phase.DESCEND:
            if self._converged(float(np.linalg.norm(grasp_point - eef)), 0.012, 0.025):
                self._go(Phase.GRASP)
            return self._towards(obs, grasp_point, OPEN, self._turn_to_grip(obs))
        if self.phase is Phase.GRASP:
            self.hold += 1
            if self.hold >= GRASP_STEPS:
                self._go(Phase.CARRY if "goal" in seen else Phase.LIFT)
            # keep reaching for the grasp point while closing: a low handle is held by its whole height
            return self._towards(obs, grasp_point, CLOSED)
        if self.phase in (Phase.LIFT, Phase.CARRY) and np.linalg.norm(grasp - eef) > DROPPED:
            self._go(Phase.APPROACH)  # the grasp missed or slipped: open and try again
            return self._towards(obs, above, OPEN)
        if self.phase is Phase.LIFT:
            return self._towards(obs, np.array([grasp[0], grasp[1], grasp[2] + 0.25]), CLOSED)
        if self.phase is Phase.RELEASE:
            self.hold += 1
            if self.next_stage and self.hold > BACK_OFF:
                self.next_stage = False
                self._go(Phase.APPROACH)
            return self._towards(obs, eef + np.array([0.0, 0.0, 0.02 if self.hold > 4 else 0.0]), OPEN)
        carried = seen["carried"]
        offset = carried - eef  # keep the grasp offset so the object, not the hand, is aligned
        # turning the object to fit its goal (a square nut onto a square peg)
        fit = -float(seen["goal_yaw"][0]) if "goal_yaw" in seen else 0.0
        if self.phase is Phase.CARRY:
            waypoint = seen["above_goal"]
            if waypoint[2] - carried[2] > 0.02:  # up first: the way over may be lined with walls and pegs
                waypoint = np.array([carried[0], carried[1], waypoint[2]])
                return self._towards(obs, waypoint - offset, CLOSED, fit)
            off_line = float(np.linalg.norm((waypoint - carried)[:2]))
            if abs(fit) < ALIGNED and self._converged(off_line, 0.008, 0.015):
                self._go(Phase.LOWER)
            return self._towards(obs, waypoint - offset, CLOSED, fit)
        goal = seen["goal"]
        target = goal - offset
        if "goal_fit" in seen and np.linalg.norm((goal - carried)[:2]) > seen["goal_fit"][0]:
            target[2] = eef[2]  # come back over the goal's line before going further down
        if self._converged(abs(carried[2] - goal[2]), 0.008, 0.015):
            self._go(Phase.RELEASE)
        return self._towards(obs, target, CLOSED, fit)

    def act(self, obs: Observation) -> np.ndarray:
        action = self._advance(obs)
        if self.noise:
            action[:6] += self.rng.normal(0.0, self.noise, size=6)
        return np.clip(action, -1.0, 1.0)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    quat, matrix = np.zeros(4), np.zeros(9)
    mujoco.mju_axisAngle2Quat(quat, axis, angle)
    mujoco.mju_quat2Mat(matrix, quat)
    return matrix.reshape(3, 3)


def _rotation_error(wanted: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """The world-frame rotation vector that turns the gripper to `wanted`."""
    quat, error = np.zeros(4), np.zeros(3)
    mujoco.mju_mat2Quat(quat, (wanted @ _matrix(quat_xyzw).T).ravel())
    mujoco.mju_quat2Vel(error, quat, 1.0)
    return error


class DoorPhase(Enum):
    APPROACH = auto()
    REACH = auto()
    GRASP = auto()
    TURN = auto()
    PULL = auto()


class DoorExpert:
    """Open robosuite's latched door: grasp the lever from the front (fingers closing on its
    height), turn it down about the latch's axis until the latch clears (~1.3 rad), then pull
    along the door's swing."""

    TURNED, TURN_STEP, MAX_TURN = 1.3, 0.06, 1.5  # radians of handle turn; per step; commanded at most
    STANDOFF, TOWARD_PIVOT = 0.12, 0.04  # metres in front of the lever to line up; grasp this far in from its end
    GRASP_STEPS = 6  # the lever is as tall as a cube is wide: the fingers close on it in 6 steps

    def __init__(self, noise: float, rng: np.random.Generator):
        self.noise, self.rng = noise, rng
        self.phase, self.steps, self.turn = DoorPhase.APPROACH, 0, 0.0
        self.grasp_pose: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    @staticmethod
    def _facing(latch_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Out of the door (towards the robot), and the gripper orientation that points into it
        with the fingers opening vertically."""
        out = horizontal(-latch_axis)
        fingers = np.array([0.0, 0.0, 1.0])
        return out, np.stack([np.cross(fingers, -out), fingers, -out], axis=1)

    def _advance(self, obs: Observation) -> tuple[np.ndarray, np.ndarray, float]:
        seen = obs.privileged
        eef, handle, pivot, axis = seen["gripper"], seen["handle"], seen["latch_pivot"], seen["latch_axis"]
        out, facing = self._facing(axis)
        grasp = handle + self.TOWARD_PIVOT * horizontal(pivot - handle)
        self.steps += 1
        if self.phase is DoorPhase.APPROACH:
            target = grasp + self.STANDOFF * out
            lined_up = np.linalg.norm(_rotation_error(facing, seen["gripper_quat"])) < ALIGNED
            if np.linalg.norm(target - eef) < 0.015 and lined_up:
                self.phase = DoorPhase.REACH
            return target, facing, OPEN
        if self.phase is DoorPhase.REACH:
            if np.linalg.norm(grasp - eef) < 0.012:
                self.phase, self.steps = DoorPhase.GRASP, 0
            return grasp, facing, OPEN
        if self.phase is DoorPhase.GRASP:
            if self.steps >= self.GRASP_STEPS:
                self.phase, self.steps, self.grasp_pose = DoorPhase.TURN, 0, (eef.copy(), pivot.copy(), axis.copy(), facing)
            return eef, facing, CLOSED
        if self.phase is DoorPhase.TURN:
            start, start_pivot, start_axis, start_facing = self.grasp_pose
            self.turn = min(self.turn + self.TURN_STEP, self.MAX_TURN)
            turned = _rotation(start_axis, self.turn)  # the hand follows the lever's arc about the latch
            if seen["handle_turn"][0] > self.TURNED or self.steps > 60:
                self.phase = DoorPhase.PULL
            return start_pivot + turned @ (start - start_pivot), turned @ start_facing, CLOSED
        # along the door's swing about its hinge, the way that opens it
        swing = horizontal(np.cross([0.0, 0.0, 1.0], eef - seen["hinge_pivot"]))
        if swing @ out < 0:
            swing = -swing
        return eef + 0.1 * swing, _rotation(axis, self.turn) @ facing, CLOSED

    def act(self, obs: Observation) -> np.ndarray:
        target, orientation, gripper = self._advance(obs)
        action = np.zeros(ACTION_DIM)
        action[:3] = np.clip(GAIN * (target - obs.privileged["gripper"]), -1.0, 1.0)
        action[3:6] = np.clip(TURN_GAIN * _rotation_error(orientation, obs.privileged["gripper_quat"]), -1.0, 1.0)
        action[6] = gripper
        if self.noise:
            action[:6] += self.rng.normal(0.0, self.noise, size=6)
        return np.clip(action, -1.0, 1.0)


class MetaWorldExpert:
    """MetaWorld's own scripted policy for the task, with the same Gaussian noise as ours."""

    def __init__(self, env_name: str, noise: float, rng: np.random.Generator):
        from metaworld.policies import ENV_POLICY_MAP

        from envs.metaworld_env import from_metaworld_action

        self.policy = ENV_POLICY_MAP[env_name]()
        self.to_common = from_metaworld_action
        self.noise, self.rng = noise, rng

    def act(self, obs: Observation) -> np.ndarray:
        action = self.to_common(self.policy.get_action(obs.privileged["state"]))
        if self.noise:
            action[:3] += self.rng.normal(0.0, self.noise, size=3)
        return np.clip(action, -1.0, 1.0)
