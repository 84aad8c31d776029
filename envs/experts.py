"""Scripted privileged-state experts: they read object positions, which policies never see."""

from __future__ import annotations

from enum import Enum, auto

import numpy as np

from envs.observation import ACTION_DIM, Observation

GAIN = 12.0  # action = GAIN * position error; 1.0 asks OSC for its largest step (5 cm)
OPEN, CLOSED = -1.0, 1.0
# Steps a converging phase may take before the expert accepts "close enough" and goes on: a
# finger resting on a randomly turned cube's corner, or a cube shifted in the grasp, would
# otherwise hold the expert in one phase until the horizon.
PATIENCE = 25
DROPPED = 0.04  # cube this far from the fingers while carrying: it is not in the hand
TURN_GAIN, ALIGNED = 3.0, 0.1  # wrist yaw: action per radian of error; radians counted as aligned


class Phase(Enum):
    APPROACH = auto()
    DESCEND = auto()
    GRASP = auto()
    LIFT = auto()
    CARRY = auto()
    LOWER = auto()
    RELEASE = auto()


class PickPlaceExpert:
    """Pick the `pick` object; then lift it (Lift) or set it on the `place` object (Stack)."""

    def __init__(self, pick_role: str, place_role: str | None, noise: float, rng: np.random.Generator):
        self.pick_role, self.place_role = pick_role, place_role
        self.noise, self.rng = noise, rng
        self.phase, self.hold, self.waited = Phase.APPROACH, 0, 0

    @classmethod
    def for_env(cls, env_name: str, noise: float, rng: np.random.Generator) -> PickPlaceExpert:
        if env_name == "Lift":
            return cls("target", None, noise, rng)
        if env_name == "Stack":
            return cls("pick", "place", noise, rng)
        raise ValueError(f"no pick_place expert for {env_name}")

    def _towards(self, obs: Observation, target: np.ndarray, gripper: float, turn: float = 0.0) -> np.ndarray:
        action = np.zeros(ACTION_DIM)
        action[:3] = np.clip(GAIN * (target - obs.privileged["gripper"]), -1.0, 1.0)
        action[5] = np.clip(TURN_GAIN * turn, -1.0, 1.0)
        action[6] = gripper
        return action

    def _yaw_error(self, obs: Observation) -> float:
        """Radians to turn the wrist so the fingers close across the line to the place object:
        beside a neighbouring cube, fingers opening towards it land on it."""
        if self.place_role is None:
            return 0.0
        between = (obs.privileged[self.place_role] - obs.privileged[self.pick_role])[:2]
        wanted = np.arctan2(between[0], -between[1])  # perpendicular to `between`
        axis = obs.privileged["finger_axis"][:2]
        return float((wanted - np.arctan2(axis[1], axis[0]) + np.pi / 2) % np.pi - np.pi / 2)  # fingers: mod pi

    def _go(self, phase: Phase) -> None:
        self.phase, self.hold, self.waited = phase, 0, 0

    def _converged(self, error: float, tolerance: float, fallback: float) -> bool:
        """Within tolerance; or, after PATIENCE steps in this phase, within the looser fallback."""
        self.waited += 1
        return error < tolerance or (self.waited > PATIENCE and error < fallback)

    def _advance(self, obs: Observation) -> np.ndarray:
        cube = obs.privileged[self.pick_role]
        eef = obs.privileged["gripper"]
        above = cube + np.array([0.0, 0.0, 0.08])
        if self.phase is Phase.APPROACH:
            turn = self._yaw_error(obs)
            if np.linalg.norm((above - eef)[:2]) < 0.01 and abs(above[2] - eef[2]) < 0.02 and abs(turn) < ALIGNED:
                self._go(Phase.DESCEND)
            return self._towards(obs, above, OPEN, turn)
        if self.phase is Phase.DESCEND:
            grasp_point = cube + np.array([0.0, 0.0, -0.005])
            if self._converged(float(np.linalg.norm(grasp_point - eef)), 0.012, 0.025):
                self._go(Phase.GRASP)
            return self._towards(obs, grasp_point, OPEN, self._yaw_error(obs))
        if self.phase is Phase.GRASP:
            self.hold += 1
            if self.hold >= 6:
                self._go(Phase.LIFT if self.place_role is None else Phase.CARRY)
            return self._towards(obs, eef, CLOSED)
        if self.phase in (Phase.LIFT, Phase.CARRY) and np.linalg.norm(cube - eef) > DROPPED:
            self._go(Phase.APPROACH)  # the grasp missed or slipped: open and try again
            return self._towards(obs, above, OPEN)
        if self.phase is Phase.LIFT:
            return self._towards(obs, np.array([cube[0], cube[1], cube[2] + 0.25]), CLOSED)
        place = obs.privileged[self.place_role]
        # cube centre sits at the place object's top plus its own half-size (~2 cm each)
        stacked = place + np.array([0.0, 0.0, 0.045])
        if self.phase is Phase.CARRY:
            carry = stacked + np.array([0.0, 0.0, 0.06])
            offset = cube - eef  # keep the grasp offset so the cube, not the hand, is aligned
            off_line = float(np.linalg.norm((carry - cube)[:2]))
            if abs(carry[2] - cube[2]) < 0.02 and self._converged(off_line, 0.008, 0.015):
                self._go(Phase.LOWER)
            return self._towards(obs, carry - offset, CLOSED)
        if self.phase is Phase.LOWER:
            offset = cube - eef
            if self._converged(abs(cube[2] - stacked[2]), 0.008, 0.015):
                self._go(Phase.RELEASE)
            return self._towards(obs, stacked - offset, CLOSED)
        self.hold += 1
        return self._towards(obs, eef + np.array([0.0, 0.0, 0.02 if self.hold > 4 else 0.0]), OPEN)

    def act(self, obs: Observation) -> np.ndarray:
        action = self._advance(obs)
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
