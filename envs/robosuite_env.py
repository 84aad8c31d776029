"""robosuite tasks behind the common interface (envs.observation): reset(task, seed), step(action).

Create an environment inside the worker process that uses it (never before a fork): its
offscreen GL context belongs to the process that made it.
"""

from __future__ import annotations

import os
import sys
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")
# robosuite reads overrides from robosuite.macros_private; ours keeps its console to errors
# (otherwise every worker prints the same five import-time warnings).
_macros = types.ModuleType("robosuite.macros_private")
_macros.CONSOLE_LOGGING_LEVEL = "ERROR"
sys.modules.setdefault("robosuite.macros_private", _macros)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.experts import horizontal  # noqa: E402
from envs.gl import select_offscreen, size_offscreen  # noqa: E402
from envs.mesh_detail import apply_mesh_detail, renderer_meshes  # noqa: E402
from envs.observation import NO_IMAGE, MujocoState, Observation, metric_depth  # noqa: E402
from envs.randomisation import ASPECTS, Randomisation, SceneRandomiser, free_bodies, jitter_rgba  # noqa: E402
from envs.robosuite_control import STOCK_CONTROL, FusedSubsteps  # noqa: E402
from schemas.config import RenderConfig  # noqa: E402
from schemas.tasks import COLOUR_RGBA, TaskRecord  # noqa: E402


Privileged = dict[str, np.ndarray]


def _across(vector: np.ndarray) -> np.ndarray:
    """The horizontal direction at right angles to `vector`."""
    return horizontal(np.array([-vector[1], vector[0], 0.0]))


# What the pick-and-place expert reads (envs.experts.PickPlaceExpert): "grasp", where the
# fingertips close; "grip_axis", the horizontal line the fingers should open along (zero: any);
# "carried", the object point brought to the goal; "goal", where that point is let go, and
# "above_goal", the waypoint it is carried through (both absent: lift and hold); "goal_yaw", how
# far the carried object is turned from a fitting orientation; "goal_fit", how far off the goal's
# vertical line it may be while going down (a nut over its peg); "stage", which of several
# placements is under way. The scene knows its objects; the expert knows only these points.

def _lift(env, raw: dict) -> Privileged:
    cube = raw["cube_pos"]
    return {"grasp": cube, "carried": cube, "grip_axis": np.zeros(3)}


def _stack(env, raw: dict) -> Privileged:
    cube, base = raw["cubeA_pos"], raw["cubeB_pos"]
    # cube centre sits at the base's top plus its own half-size (~2 cm each); fingers close
    # across the line to the base, or beside a close neighbour one lands on it
    goal = base + np.array([0.0, 0.0, 0.045])
    return {"grasp": cube, "carried": cube, "grip_axis": _across(base - cube),
            "goal": goal, "above_goal": goal + np.array([0.0, 0.0, 0.06])}


def _pick_place(obj: str):
    def privileged(env, raw: dict) -> Privileged:
        model, data = env.sim.model._model, env.sim.data._data
        geom = model.geom(f"{obj}_g0").id
        half = model.geom_aabb[geom, 3:]  # in the mesh's own frame
        centre = np.asarray(raw[f"{obj}_pos"], dtype=np.float64)
        # grasp tall objects near the top, short ones at the middle; close on the narrow side
        grasp = centre + np.array([0.0, 0.0, max(0.0, half[2] - 0.03)])
        narrow = data.geom_xmat[geom].reshape(3, 3)[:, int(np.argmin(half[:2]))]
        # the object's quarter of the bin, 5 cm in from its centre towards the robot: the far
        # quarters' centres are at the edge of the arm's reach (success allows a quarter's half-size)
        target = env.target_bin_placements[env.object_id]
        inward = np.array([-0.05, -0.05 * np.sign(target[1])])
        goal = np.array([*(target[:2] + inward), env.bin2_pos[2] + half[2] + 0.05])  # dropped the last few cm
        return {"grasp": grasp, "carried": centre, "grip_axis": horizontal(narrow),
                "goal": goal, "above_goal": goal + np.array([0.0, 0.0, 0.12])}

    return privileged


NUT_PEGS = (("SquareNut", "peg1"), ("RoundNut", "peg2"))  # robosuite's nut order: id 0, 1


def _nuts(env, raw: dict) -> Privileged:
    """The first nut of the scene not yet on its peg."""
    model, data = env.sim.model._model, env.sim.data._data
    active = [(i, nut, peg) for i, (nut, peg) in enumerate(NUT_PEGS) if f"{nut}_pos" in raw]
    stage, nut, peg = next(((i, n, p) for i, n, p in active if not env.on_peg(raw[f"{n}_pos"], i)), active[-1])
    handle, centre = (data.site_xpos[model.site(f"{nut}_{site}_site").id].copy() for site in ("handle", "center"))
    radial = handle - centre
    # let go once the nut is around the peg (3 cm below its top, 10 cm above its base): held by its
    # handle the nut hangs tilted and jams; let go, it drops flat
    goal = data.xpos[model.body(peg).id] + np.array([0.0, 0.0, 0.07])
    # the handle ends up pointing away from the peg along -x, +y or -y (a square nut fits that way):
    # pointing +x would put the hand out of the arm's reach beyond the pegs
    heading = np.arctan2(radial[1], radial[0])
    fit = min(((heading - way + np.pi) % (2 * np.pi) - np.pi for way in (np.pi, np.pi / 2, -np.pi / 2)), key=abs)
    return {"grasp": handle, "carried": centre, "grip_axis": _across(radial), "goal": goal,
            "above_goal": goal + np.array([0.0, 0.0, 0.09]), "goal_fit": np.array([0.01]),
            "goal_yaw": np.array([fit]),
            "stage": np.array([float(stage)])}


def _door(env, raw: dict) -> Privileged:
    model, data = env.sim.model._model, env.sim.data._data
    latch, hinge = model.joint(env.door.joints[1]).id, model.joint(env.door.joints[0]).id
    return {"handle": np.asarray(raw["handle_pos"], dtype=np.float64), "latch_pivot": data.xanchor[latch].copy(),
            "latch_axis": data.xaxis[latch].copy(), "hinge_pivot": data.xanchor[hinge].copy(),
            "handle_turn": np.atleast_1d(raw["handle_qpos"]).astype(np.float64)}


def _stack_reversed(env, task: TaskRecord, candidate: TaskRecord) -> bool:
    """`candidate` is the episode's pair the other way round (its picked cube the episode's base) and the
    scene ended that way: robosuite's own success test with the cubes' roles swapped (the base cube lifted
    4 cm above the table, touching the other, not held)."""
    picked, base = task.object_colours.get("pick"), task.object_colours.get("place")
    if candidate.object_colours != {"pick": base, "place": picked}:
        return False
    on_top = env.sim.data.body_xpos[env.cubeB_body_id][2] > env.table_offset[2] + 0.04
    return bool(on_top and env.check_contact(env.cubeB, env.cubeA)
                and not env._check_grasp(gripper=env.robots[0].gripper, object_geoms=env.cubeB))


@dataclass(frozen=True)
class Scene:
    """One robosuite environment as task specs and experts see it."""

    colourable: dict[str, tuple[str, ...]]  # role a spec may colour -> the visual geoms that show it
    expert: str  # the task-spec expert that solves it
    privileged: Callable[[Any, dict], Privileged]  # (robosuite env, its observation) -> what the expert reads
    options: dict[str, Any] = field(default_factory=dict)  # robosuite.make arguments
    # Mesh objects keep their size: MuJoCo scales primitive geoms only.
    randomises: frozenset[str] = frozenset(ASPECTS)
    cameras: tuple[str, ...] = ("agentview", "frontview", "birdview", "sideview")  # its arena's, by name
    # (robosuite env, the episode's task, another task of the scene) -> did the episode end doing that one
    achieved: Callable[[Any, TaskRecord, TaskRecord], bool] | None = None


# Mesh objects keep their size and their friction (scaled on primitive geoms only; on the meshes it would change
# the physics every evaluation so far was made under): recorded as null, as is a hinged door's mass.
_MESH_OBJECT = frozenset(ASPECTS) - {"size", "friction"}
_FIXED_OBJECT = _MESH_OBJECT - {"mass"}  # no free body: nothing to weigh (the door is hinged)
_NUT_GEOMS = {nut: tuple(f"{nut}_g{i}_visual" for i in range(count)) for nut, count in (("SquareNut", 5), ("RoundNut", 9))}
ROBOSUITE_SCENES: dict[str, Scene] = {
    "Lift": Scene({"target": ("cube_g0_vis",)}, "pick_place", _lift),
    "Stack": Scene({"pick": ("cubeA_g0_vis",), "place": ("cubeB_g0_vis",)}, "pick_place", _stack,
                   achieved=_stack_reversed),
    **{f"PickPlace{obj}": Scene({}, "pick_place", _pick_place(obj), randomises=_MESH_OBJECT,
                                cameras=("agentview", "frontview", "birdview"))  # the bins arena has no sideview
       for obj in ("Milk", "Bread", "Cereal", "Can")},
    "NutAssemblySquare": Scene({"nut": _NUT_GEOMS["SquareNut"]}, "pick_place", _nuts),
    "NutAssemblyRound": Scene({"nut": _NUT_GEOMS["RoundNut"]}, "pick_place", _nuts),
    "NutAssembly": Scene({"square": _NUT_GEOMS["SquareNut"], "round": _NUT_GEOMS["RoundNut"]}, "pick_place", _nuts),
    # the latched door: its handle must be turned before it opens
    "Door": Scene({"door": ("Door_panel_visual",)}, "open_door", _door, {"use_latch": True}, _FIXED_OBJECT),
}

MODEL_SEED = 0
FINGERS = ("gripper0_right_leftfinger", "gripper0_right_rightfinger")
PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
WRIST_CAMERA = "robot0_eye_in_hand"  # the Panda's camera in its hand (render.wrist_camera)


def finger_bodies(env) -> list[int]:
    """The body ids of a robosuite env's two fingers."""
    model = env.sim.model._model
    return [model.body(name).id for name in FINGERS]


def observe(env, scene: Scene, raw: dict[str, np.ndarray], camera: str | None, fingers: list[int],
            wrist: bool = False) -> Observation:
    """Our Observation of robosuite's raw observation: `camera`'s image upright (none if None; with
    `wrist`, the hand camera's beside it, schemas/frames.py), proprio, and what the scene's expert
    reads. Works on any robosuite env of the scene, ours or one made by hand (bench rollout)."""
    if camera is None:
        image = NO_IMAGE
    elif wrist:
        image = np.concatenate([raw[f"{camera}_image"][::-1], raw[f"{WRIST_CAMERA}_image"][::-1]], axis=1)
    else:
        image = raw[f"{camera}_image"][::-1].copy()
    zbuffer = None if camera is None else raw.get(f"{camera}_depth")  # robosuite's camera_depths
    depth = None if zbuffer is None else metric_depth(zbuffer[::-1, :, 0], env.sim.model._model)
    proprio = np.concatenate([raw[key] for key in PROPRIO_KEYS]).astype(np.float32)
    privileged = scene.privileged(env, raw)
    privileged["gripper"] = np.asarray(raw["robot0_eef_pos"], dtype=np.float64)
    privileged["gripper_quat"] = np.asarray(raw["robot0_eef_quat"], dtype=np.float64)  # x, y, z, w
    left, right = env.sim.data._data.xpos[fingers]  # the fingers open along this line
    privileged["finger_axis"] = right - left
    return Observation(image, proprio, privileged, depth)


class RobosuiteEnv:
    """One robosuite environment, recoloured per task, rendered with the campaign's settings."""

    def __init__(self, env_name: str, render: RenderConfig | None):
        """render=None: no camera at all (scripted experts need no pixels; 8x faster on CPU)."""
        import robosuite

        self.env_name = env_name
        self.render_config = render
        self.scene = ROBOSUITE_SCENES[env_name]
        self.task: TaskRecord | None = None  # the last reset's (achieved reads its colours)
        self.RANDOMISES = self.scene.randomises
        camera = {} if render is None else {
            "camera_names": [render.camera, WRIST_CAMERA] if render.wrist_camera else render.camera,
            "camera_heights": render.image_size, "camera_widths": render.image_size,
            "camera_depths": render.depth,
        }
        self.env = robosuite.make(
            env_name,
            robots="Panda",
            has_renderer=False,
            has_offscreen_renderer=render is not None,
            use_camera_obs=render is not None,
            **camera,
            control_freq=20,
            horizon=10_000,  # episodes end by our horizon; robosuite's own is never reached
            ignore_done=True,
            hard_reset=False,  # 0.26 s -> 0.002 s per reset (measured here); colours are re-applied anyway
            reward_shaping=True,
            # robosuite samples object sizes when it builds the model, from env.rng: a fixed seed
            # makes every worker's model identical, so an episode depends on its own seed only (on one CPU: across
            # CPUs OpenBLAS's kernels can tip a marginal one, docs/results-generalist.md "Made an eighth time").
            seed=MODEL_SEED,
            **self.scene.options,
        )
        if render is not None:
            # before the context is made again: it uploads the meshes as they are then
            apply_mesh_detail(self.env.sim.model._model, render)
            with renderer_meshes(self.env.sim.model._model, render):
                self._apply_render_settings()
        # the arm's torques between policy steps computed without robosuite's bookkeeping, bit for
        # bit the same (envs/robosuite_control.py); the variable keeps robosuite's path (benchmarks)
        self.fused_control = None if os.environ.get(STOCK_CONTROL) == "1" else FusedSubsteps(self.env)
        model = self.env.sim.model._model
        self.fingers = finger_bodies(self.env)
        self.randomiser = SceneRandomiser(
            model, render.camera if render else None,
            task_geoms=[model.geom(g).id for geoms in self.scene.colourable.values() for g in geoms], object_bodies=free_bodies(model),
        )

    def _apply_render_settings(self) -> None:
        # a framebuffer the size of the image, not robosuite's 640x480 default; no shadow map unless drawn
        size_offscreen(self.env.sim.model._model, self.render_config)
        context = self.env.sim._render_context_offscreen
        context.con.free()
        context._set_mujoco_context_and_buffers()
        context.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.render_config.shadows)
        context.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.render_config.reflections)

    def _apply_colours(self, task: TaskRecord, randomisation: Randomisation | None) -> None:
        model = self.env.sim.model._model
        for role, colour in task.object_colours.items():
            for geom in self.scene.colourable[role]:
                geom_id = model.geom(geom).id
                model.geom_matid[geom_id] = -1  # drop the texture: the colour is the cue
                model.geom_rgba[geom_id] = jitter_rgba(COLOUR_RGBA[colour], randomisation)

    def reset(self, task: TaskRecord, seed: int, randomisation: Randomisation | None = None) -> Observation:
        if task.env_name != self.env_name:
            raise ValueError(f"task {task.task_id} is for {task.env_name}, this environment is {self.env_name}")
        # robosuite samples placements from env.rng (shared with its placement sampler): reseed it in place.
        self.env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        np.random.seed(seed)
        self.randomiser.apply(randomisation)
        self._apply_colours(task, randomisation)
        self.task = task
        self._make_context_current()
        raw = self.env.reset()
        if randomisation is not None and randomisation.size is not None:
            # robosuite places objects at their nominal height; rest resized ones on the table
            self.randomiser.rest_on_support(self.env.sim.data._data, randomisation)
            raw = self._observe_again()
        return self._observation(raw)

    def achieved(self, tasks: list[TaskRecord]) -> TaskRecord | None:
        """The first of `tasks` (this scene's others) the episode ended doing instead of its own: hindsight
        relabelling (explore.relabel) and evaluation's "ended doing". None where the scene has no test
        (envs.registry.ACHIEVED_TESTS: Stack's reversed pair) or before any reset."""
        test, task = self.scene.achieved, self.task
        if test is None or task is None:
            return None
        return next((c for c in tasks if c.env_name == self.env_name and c.task_id != task.task_id
                     and test(self.env, task, c)), None)

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool]:
        self._make_context_current()
        raw, reward, _, _ = self.env.step(np.clip(action, -1.0, 1.0))
        return self._observation(raw), float(reward), bool(self.env._check_success())

    def _observation(self, raw: dict[str, np.ndarray]) -> Observation:
        if self.render_config is None:
            return observe(self.env, self.scene, raw, None, self.fingers)
        return observe(self.env, self.scene, raw, self.render_config.camera, self.fingers, self.render_config.wrist_camera)

    def _observe_again(self) -> dict[str, np.ndarray]:
        """robosuite's observations of the state as it is now, with its observable clocks restarted
        first as its reset does: a forced read advances them a substep, and their phase decides at
        which substep of every later step the camera is sampled."""
        for observable in self.env._observables.values():
            observable.reset()
        return self.env._get_observations(force_update=True)

    def _make_context_current(self) -> None:
        """robosuite renders into whichever GL context is current (envs/gl.py)."""
        if self.render_config is not None:
            context = self.env.sim._render_context_offscreen
            select_offscreen(context.gl_ctx, context.con)

    def render_state(self, state: MujocoState, after_step: bool) -> np.ndarray:
        """The frame an observation at `state` showed, through robosuite's camera observable."""
        return self.observe_state(state, after_step).image

    def observe_state(self, state: MujocoState, after_step: bool) -> Observation:
        """The observation at `state` as exploring saw it: its frame (robosuite's camera observable)
        and its privileged points, which the expert's labels were computed from (bit for bit:
        envs/label_audit.py checks). after_step: `state` ended a step, whose observables robosuite
        sampled at its last substep."""
        self._make_context_current()
        state.restore(self.env.sim.model._model, self.env.sim.data._data, before_last_substep=after_step)
        return self._observation(self._observe_again())

    def physics(self) -> tuple[mujoco.MjModel, mujoco.MjData, int]:
        """The MuJoCo model and data underneath, and the mj_steps one action takes (benchmarks)."""
        substeps = round(self.env.control_timestep / self.env.model_timestep)
        return self.env.sim.model._model, self.env.sim.data._data, substeps

    def native_step(self, action: np.ndarray) -> None:
        """robosuite's own step, its own controller at every substep, without our observation (benchmarks)."""
        fused = vars(self.env).pop("_pre_action", None)  # the class's method shows through
        try:
            self.env.step(action)
        finally:
            if fused is not None:
                self.env._pre_action = fused

    def mujoco_state(self) -> MujocoState:
        return MujocoState.of(self.env.sim.data._data)

    def close(self) -> None:
        self._make_context_current()  # robosuite frees its GL objects in the current context
        self.env.close()
