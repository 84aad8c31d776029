"""Multi-room navigation in our own MuJoCo scene.

Rooms in a row joined by doorways; each room's floor has a colour, and coloured balls and boxes
stand in them. A round agent moves on the floor under real contact physics with a *discrete*
action set, seen from its own egocentric camera (or a top-down one). Colours and placements are
drawn per episode from the seed; the task's colours are always present.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.gl import select_offscreen  # noqa: E402
from envs.observation import NAVIGATION_ACTIONS as ACTIONS  # noqa: E402
from envs.observation import NO_IMAGE, PROPRIO_DIM, MujocoState, Observation  # noqa: E402
from envs.randomisation import VISUAL_ASPECTS, Randomisation, SceneRandomiser, jitter_rgba  # noqa: E402
from schemas.config import RenderConfig  # noqa: E402
from schemas.tasks import COLOUR_RGBA, TaskRecord  # noqa: E402

ROOMS, ROOM_SIZE, DOOR_HALF_WIDTH = 3, 4.0, 0.6
SHAPES = ("ball", "box")
OBJECTS_PER_SHAPE = 2
SPEED, TURN_RATE = 1.5, 2.5  # m/s, rad/s
CONTROL_DT, SUBSTEPS = 0.1, 5
REACH = 0.7  # an object is found within this distance
CAMERAS = {"agentview": "ego", "frontview": "ego", "birdview": "top", "sideview": "top"}

# object role -> what the role names: a room (by floor colour) or a shape
NAVIGATION_ROLES: dict[str, dict[str, str]] = {
    "GoToRoom": {"room": "room"},
    "FindBall": {"target": "ball"},
    "FindBox": {"target": "box"},
    "RoomSequence": {"first": "room", "second": "room"},  # long-horizon: both rooms, in order
}


def _box(name: str, pos, size, rgba="0.8 0.8 0.8 1", collide=True) -> str:
    contact = "" if collide else ' contype="0" conaffinity="0"'
    return (f'<geom name="{name}" type="box" pos="{pos[0]} {pos[1]} {pos[2]}" size="{size[0]} {size[1]} {size[2]}" '
            f'rgba="{rgba}"{contact}/>')


def scene_xml(image_size: int) -> str:
    width, depth = ROOMS * ROOM_SIZE, ROOM_SIZE
    walls = [
        _box("wall_south", (width / 2, -0.05, 0.5), (width / 2 + 0.1, 0.05, 0.5)),
        _box("wall_north", (width / 2, depth + 0.05, 0.5), (width / 2 + 0.1, 0.05, 0.5)),
        _box("wall_west", (-0.05, depth / 2, 0.5), (0.05, depth / 2, 0.5)),
        _box("wall_east", (width + 0.05, depth / 2, 0.5), (0.05, depth / 2, 0.5)),
    ]
    for k in range(1, ROOMS):  # inner walls with a doorway in the middle
        x, half = k * ROOM_SIZE, (depth / 2 - DOOR_HALF_WIDTH) / 2
        walls.append(_box(f"wall_{k}_s", (x, half, 0.5), (0.05, half, 0.5)))
        walls.append(_box(f"wall_{k}_n", (x, depth - half, 0.5), (0.05, half, 0.5)))
    floors = [_box(f"floor_{i}", ((i + 0.5) * ROOM_SIZE, depth / 2, -0.01), (ROOM_SIZE / 2, depth / 2, 0.01),
                   collide=False) for i in range(ROOMS)]
    objects = []
    for shape in SHAPES:
        form = 'type="sphere" size="0.25"' if shape == "ball" else 'type="box" size="0.22 0.22 0.22"'
        for j in range(OBJECTS_PER_SHAPE):
            geom = f'<geom name="{shape}_{j}_geom" {form} contype="0" conaffinity="0"/>'
            objects.append(f'<body name="{shape}_{j}" pos="0 0 0.25">{geom}</body>')
    return f"""
<mujoco model="sim2act_rooms">
  <option timestep="{CONTROL_DT / SUBSTEPS}"/>
  <visual><global offwidth="{image_size}" offheight="{image_size}"/><quality offsamples="0" shadowsize="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5"/></visual>
  <worldbody>
    <light pos="{width / 2} {depth / 2} 6" dir="0 0 -1" directional="true" castshadow="false"/>
    <camera name="top" pos="{width / 2} {depth / 2} 11" xyaxes="1 0 0 0 1 0" fovy="60"/>
    {''.join(walls)}{''.join(floors)}{''.join(objects)}
    <body name="agent" pos="0 0 0.2">
      <joint name="agent_x" type="slide" axis="1 0 0" damping="0"/>
      <joint name="agent_y" type="slide" axis="0 1 0" damping="0"/>
      <joint name="agent_yaw" type="hinge" axis="0 0 1" damping="0"/>
      <geom name="agent_body" type="cylinder" size="0.2 0.18" rgba="0.15 0.15 0.15 1" mass="5"/>
      <geom type="box" pos="0.18 0 0.1" size="0.05 0.05 0.03" rgba="0.9 0.9 0.9 1" contype="0" conaffinity="0" mass="0"/>
      <camera name="ego" pos="0.15 0 0.35" xyaxes="0 -1 0 0.2 0 1" fovy="75"/>
    </body>
  </worldbody>
  <actuator>
    <velocity name="vx" joint="agent_x" kv="60" ctrlrange="-2 2"/>
    <velocity name="vy" joint="agent_y" kv="60" ctrlrange="-2 2"/>
    <velocity name="vyaw" joint="agent_yaw" kv="8" ctrlrange="-4 4"/>
  </actuator>
</mujoco>"""


def room_of(x: float) -> int:
    return int(np.clip(x // ROOM_SIZE, 0, ROOMS - 1))


class NavigationEnv:
    # Balls and boxes vary in size; they are static markers, so mass and friction mean nothing.
    RANDOMISES = VISUAL_ASPECTS | {"size"}

    def __init__(self, env_name: str, render: RenderConfig | None):
        self.env_name = env_name
        self.roles = NAVIGATION_ROLES[env_name]
        self.render_config = render
        self.model = mujoco.MjModel.from_xml_string(scene_xml(render.image_size if render else 64))
        self.data = mujoco.MjData(self.model)
        self.renderer = None
        if render is not None:
            self.renderer = mujoco.Renderer(self.model, render.image_size, render.image_size)
            self.camera = CAMERAS[render.camera]
            self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(render.shadows)
            self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(render.reflections)
        coloured = [self.model.geom(f"floor_{i}").id for i in range(ROOMS)] + [
            self.model.geom(f"{shape}_{j}_geom").id for shape in SHAPES for j in range(OBJECTS_PER_SHAPE)]
        markers = [self.model.body(f"{shape}_{j}").id for shape in SHAPES for j in range(OBJECTS_PER_SHAPE)]
        self.randomiser = SceneRandomiser(self.model, CAMERAS[render.camera] if render else None,
                                          task_geoms=coloured, object_bodies=markers)

    # -- episode set-up ---------------------------------------------------------------------

    def _layout(self, task: TaskRecord, rng: np.random.Generator, randomisation: Randomisation | None) -> None:
        """Room colours and object placements, drawn from the seed around the task's colours."""
        palette = list(COLOUR_RGBA)
        needed_rooms = [c for role, c in task.object_colours.items() if self.roles[role] == "room"]
        others = [c for c in rng.permutation(palette) if c not in needed_rooms]
        self.room_colours = list(rng.permutation(needed_rooms + others[: ROOMS - len(needed_rooms)]))
        for i, colour in enumerate(self.room_colours):
            floor = np.array(COLOUR_RGBA[colour]) * [0.8, 0.8, 0.8, 1]
            self.model.geom_rgba[self.model.geom(f"floor_{i}").id] = jitter_rgba(floor, randomisation)
        self.objects: dict[tuple[str, str], np.ndarray] = {}
        for shape in SHAPES:
            needed = [c for role, c in task.object_colours.items() if self.roles[role] == shape]
            colours = needed + [c for c in rng.permutation(palette) if c not in needed][: OBJECTS_PER_SHAPE - len(needed)]
            for j, colour in enumerate(colours):
                position = np.array([rng.uniform(0.6, ROOMS * ROOM_SIZE - 0.6), rng.uniform(0.6, ROOM_SIZE - 0.6)])
                self.model.body_pos[self.model.body(f"{shape}_{j}").id][:2] = position
                self.model.geom_rgba[self.model.geom(f"{shape}_{j}_geom").id] = jitter_rgba(COLOUR_RGBA[colour],
                                                                                            randomisation)
                self.objects[(shape, colour)] = position

    def reset(self, task: TaskRecord, seed: int, randomisation: Randomisation | None = None) -> Observation:
        if task.env_name != self.env_name:
            raise ValueError(f"task {task.task_id} is for {task.env_name}, this environment is {self.env_name}")
        rng = np.random.default_rng(seed)
        self.task = task
        self.randomiser.apply(randomisation)
        self._layout(task, rng, randomisation)
        mujoco.mj_resetData(self.model, self.data)
        self.stage = 0  # index of the goal being pursued (RoomSequence has two)
        while True:  # start away from the first goal, so no episode succeeds on its first step
            self.data.qpos[:] = [rng.uniform(0.5, ROOMS * ROOM_SIZE - 0.5), rng.uniform(0.5, ROOM_SIZE - 0.5),
                                 rng.uniform(-np.pi, np.pi)]
            if np.hypot(*(self.goal_point() - self.data.qpos[:2])) > 2.5:
                break
        mujoco.mj_forward(self.model, self.data)
        return self._observation()

    # -- goals ------------------------------------------------------------------------------

    def _goals(self) -> list[tuple[str, str]]:
        """(kind, colour) per stage, in order."""
        return [(self.roles[role], colour) for role, colour in self.task.object_colours.items()]

    def goal_point(self) -> np.ndarray:
        kind, colour = self._goals()[self.stage]
        if kind == "room":
            return np.array([(self.room_colours.index(colour) + 0.5) * ROOM_SIZE, ROOM_SIZE / 2])
        return self.objects[(kind, colour)]

    def _reached(self) -> bool:
        kind, colour = self._goals()[self.stage]
        x, y = self.data.qpos[:2]
        if kind == "room":
            return self.room_colours[room_of(x)] == colour and abs(x % ROOM_SIZE - ROOM_SIZE / 2) < ROOM_SIZE / 2 - 0.4
        return float(np.hypot(*(self.objects[(kind, colour)] - [x, y]))) < REACH

    def achieved(self, tasks: list[TaskRecord]) -> TaskRecord | None:
        """The first of `tasks` (this environment's, one goal each) whose goal the agent is at now:
        hindsight relabelling (explore.relabel). A goal the scene does not hold is not achieved."""
        task, stage = self.task, self.stage
        try:
            for candidate in tasks:
                if candidate.env_name != self.env_name or len(candidate.object_colours) != 1:
                    continue
                goals = [(self.roles[role], colour) for role, colour in candidate.object_colours.items()]
                kind, colour = goals[0]
                present = colour in self.room_colours if kind == "room" else (kind, colour) in self.objects
                self.task, self.stage = candidate, 0
                if present and self._reached():
                    return candidate
        finally:
            self.task, self.stage = task, stage
        return None

    # -- stepping ---------------------------------------------------------------------------

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool]:
        index = int(np.asarray(action).reshape(-1)[0])
        if not 0 <= index < len(ACTIONS):
            raise ValueError(f"navigation action must be 0..{len(ACTIONS) - 1}, got {index}")
        yaw = self.data.qpos[2]
        move = {"forward": SPEED, "backward": -SPEED}.get(ACTIONS[index], 0.0)
        turn = {"turn_left": TURN_RATE, "turn_right": -TURN_RATE}.get(ACTIONS[index], 0.0)
        before = np.hypot(*(self.goal_point() - self.data.qpos[:2]))
        self.data.ctrl[:] = [move * np.cos(yaw), move * np.sin(yaw), turn]
        mujoco.mj_step(self.model, self.data, nstep=SUBSTEPS)
        after = np.hypot(*(self.goal_point() - self.data.qpos[:2]))
        reward = float(before - after)  # progress towards the current goal
        if self._reached():
            reward += 1.0
            self.stage += 1
        success = self.stage == len(self._goals())
        if success:
            self.stage -= 1  # stay on the last goal: success holds while it holds
        return self._observation(), reward, success

    def _render(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(frame, depth in metres or None): the scene drawn once more for depth where recorded."""
        if self.renderer is None:
            return NO_IMAGE, None
        self.renderer.update_scene(self.data, camera=self.camera)
        # Renderer.render() makes its context current but does not re-select the offscreen buffer
        select_offscreen(self.renderer._gl_context, self.renderer._mjr_context)
        image = self.renderer.render().copy()
        if not self.render_config.depth:
            return image, None
        self.renderer.enable_depth_rendering()
        try:
            return image, self.renderer.render().copy()
        finally:
            self.renderer.disable_depth_rendering()

    def render_state(self, state: MujocoState, after_step: bool) -> np.ndarray:
        """The frame an observation at `state` showed. after_step: `state` ended a step, whose
        frame was drawn right after mj_step, with the poses of before its last substep."""
        state.restore(self.model, self.data, before_last_substep=after_step)
        return self._render()[0]

    def _observation(self) -> Observation:
        image, depth = self._render()
        x, y, yaw = self.data.qpos[:3]
        proprio = np.zeros(PROPRIO_DIM, dtype=np.float32)
        proprio[:4] = [x, y, np.cos(yaw), np.sin(yaw)]
        privileged = {"pose": self.data.qpos[:3].copy(), "goal": self.goal_point(), "stage": np.array([self.stage])}
        return Observation(image, proprio, privileged, depth)

    def physics(self) -> tuple[mujoco.MjModel, mujoco.MjData, int]:
        """The MuJoCo model and data, and the mj_steps one action takes (benchmarks)."""
        return self.model, self.data, SUBSTEPS

    def mujoco_state(self) -> MujocoState:
        return MujocoState.of(self.data)

    def close(self) -> None:
        if self.renderer is not None:
            # its GL objects go with its own context: MuJoCo's Renderer frees them after the context,
            # in whichever is current then (envs/gl.py)
            select_offscreen(self.renderer._gl_context, self.renderer._mjr_context)
            self.renderer.close()


class NavigationExpert:
    """Privileged planner: through the doorways to the goal, turning then driving; with
    probability `noise` a random action (the discrete counterpart of action noise)."""

    def __init__(self, noise: float, rng: np.random.Generator):
        self.noise, self.rng = noise, rng

    def waypoint(self, pose: np.ndarray, goal: np.ndarray) -> np.ndarray:
        here, there = room_of(pose[0]), room_of(goal[0])
        if here == there:
            return goal
        step = 1 if there > here else -1
        door_x = (here + (step > 0)) * ROOM_SIZE
        if abs(pose[1] - ROOM_SIZE / 2) > 0.25 or abs(pose[0] - door_x) > 1.0:
            return np.array([door_x - 0.7 * step, ROOM_SIZE / 2])  # line up in front of the doorway
        return np.array([door_x + 0.9 * step, ROOM_SIZE / 2])  # then drive through

    def act(self, obs: Observation) -> np.ndarray:
        if self.noise and self.rng.random() < self.noise:
            return np.array([self.rng.integers(len(ACTIONS))], dtype=np.float32)
        pose = obs.privileged["pose"]
        target = self.waypoint(pose, obs.privileged["goal"])
        heading = np.arctan2(target[1] - pose[1], target[0] - pose[0])
        error = (heading - pose[2] + np.pi) % (2 * np.pi) - np.pi
        if abs(error) > 0.25:
            return np.array([ACTIONS.index("turn_left" if error > 0 else "turn_right")], dtype=np.float32)
        return np.array([ACTIONS.index("forward")], dtype=np.float32)
