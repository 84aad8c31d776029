"""MetaWorld v3 tasks behind the common interface (envs.observation).

MetaWorld's action is (dx, dy, dz, grip); ours adds a zero rotation. Its 39-d state is kept as
privileged state for its scripted policies; proprio is the hand position and finger opening.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.gl import select_offscreen, size_offscreen  # noqa: E402
from envs.mesh_detail import apply_mesh_detail, renderer_meshes  # noqa: E402
from envs.observation import NO_IMAGE, MujocoState, Observation, metric_depth  # noqa: E402
from envs.randomisation import VISUAL_ASPECTS, Randomisation, SceneRandomiser, free_bodies  # noqa: E402
from schemas.config import RenderConfig  # noqa: E402
from schemas.tasks import TaskRecord  # noqa: E402

BENCHMARK_SEED = 0  # fixes MetaWorld's 50 pre-sampled object/goal variations per task
METAWORLD_PATH_LENGTH = 500  # SawyerXYZEnv.max_path_length: the steps its episodes take at most
PLACEMENT_STREAM = 0x9A5E  # a "fresh" placement's generator: (episode seed, this), apart from randomisation's
CAMERAS = {"agentview": "corner", "frontview": "corner2", "sideview": "corner3", "birdview": "topview"}
IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)  # a constant: read as xyzw, a hand pointing down


def known_envs() -> list[str]:
    import metaworld

    return list(metaworld.ALL_V3_ENVIRONMENTS)


def to_metaworld_action(action: np.ndarray) -> np.ndarray:
    return np.asarray([action[0], action[1], action[2], action[6]], dtype=np.float32)


def from_metaworld_action(action: np.ndarray) -> np.ndarray:
    return np.asarray([action[0], action[1], action[2], 0.0, 0.0, 0.0, action[3]], dtype=np.float32)


class MetaWorldEnv:
    # What every scene randomises: objects keep their size (MetaWorld's scripted policies and success checks
    # assume it); no colour jitter (its tasks are not told apart by colour). Mass and friction come on top
    # where the scene can change them (`RANDOMISES`, per instance).
    VISUAL = VISUAL_ASPECTS - {"colour_jitter"}

    def __init__(self, env_name: str, render: RenderConfig | None):
        """render=None: no camera at all (scripted experts need no pixels)."""
        import metaworld

        self.env_name = env_name
        self.render_config = render
        self.benchmark = metaworld.MT1(env_name, seed=BENCHMARK_SEED)
        if render is None:
            self.env = self.benchmark.train_classes[env_name]()
        else:
            self.env = self.benchmark.train_classes[env_name](
                render_mode="rgbd_tuple" if render.depth else "rgb_array", camera_name=CAMERAS[render.camera], width=render.image_size,
                height=render.image_size,
            )
            size_offscreen(self.env.model, render)  # read when the renderer is created, at the first frame
            apply_mesh_detail(self.env.model, render)  # before the first render uploads the meshes
            self._scene_configured = False
        self.randomiser = SceneRandomiser(self.env.model, CAMERAS[render.camera] if render else None,
                                          task_geoms=[], object_bodies=free_bodies(self.env.model))
        # the record says what the episode saw: a mass where a free body moves (24 of the 50 scenes have none: a
        # door, a drawer, a button), a friction where one has a primitive geom (14 more collide through meshes)
        self.RANDOMISES = self.VISUAL | {aspect for aspect, scaled in (("mass", self.randomiser.bodies),
                                                                       ("friction", self.randomiser.geoms)) if len(scaled)}

    def _render(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(frame, depth in metres or None), upright."""
        if self.render_config is None:
            return NO_IMAGE, None
        if not self._scene_configured:  # gymnasium makes its renderer, uploading the meshes, when first asked
            with renderer_meshes(self.env.model, self.render_config):
                scene = self._viewer().scn
            scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.render_config.shadows)
            scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.render_config.reflections)
            self._scene_configured = True
        self._make_context_current()
        drawn = self.env.render()
        image, zbuffer = drawn if self.render_config.depth else (drawn, None)
        depth = None if zbuffer is None else metric_depth(zbuffer[::-1], self.env.model)  # flipped as the frame
        # rows flipped: the corner cameras are rolled upside down, so this is upright but mirrored left to right
        # (a half turn would be the true view); kept, as every MetaWorld frame in a warehouse was made so
        return image[::-1].copy(), depth

    def _viewer(self):
        return self.env.mujoco_renderer._get_viewer(self.env.render_mode)

    def _make_context_current(self) -> None:
        """gymnasium switches GL contexts only between its own viewers (envs/gl.py)."""
        viewer = self._viewer()
        select_offscreen(viewer.opengl_context, viewer.con)

    def render_state(self, state: MujocoState, after_step: bool) -> np.ndarray:
        """The frame an observation at `state` showed. MetaWorld's step ends in mj_forward, so its
        frames show the state itself, after a step (`after_step`) or not."""
        state.restore(self.env.model, self.env.data)
        return self._render()[0]

    def _observation(self, state: np.ndarray) -> Observation:
        proprio = np.concatenate([state[:3], IDENTITY_QUAT, [state[3], -state[3]]]).astype(np.float32)
        image, depth = self._render()
        return Observation(image, proprio, {"state": np.asarray(state, dtype=np.float64)}, depth)

    def reset(self, task: TaskRecord, seed: int, randomisation: Randomisation | None = None,
              placements: str = "benchmark") -> Observation:
        """`placements`: "benchmark", MT1's 50 fixed object/goal placements (`seed % 50`: what exploration
        uses); "fresh", one drawn from the task's own reset space by `seed`, as MT1 drew its 50 (MetaWorld
        draws again while goal and object are too close), so an evaluation can meet placements no
        exploration saw."""
        if task.env_name != self.env_name:
            raise ValueError(f"task {task.task_id} is for {task.env_name}, this environment is {self.env_name}")
        if placements not in ("benchmark", "fresh"):
            raise ValueError(f"placements: expected 'benchmark' or 'fresh', got {placements!r}")
        variations = self.benchmark.train_tasks
        self.env.set_task(variations[seed % len(variations)])  # the task's class and settings (and its placement)
        # MetaWorld refuses a step past its own 500 (max_path_length); tasks.horizon may ask for more
        self.env.max_path_length = max(METAWORLD_PATH_LENGTH, task.horizon)
        if placements == "fresh":  # drawn at reset from the env's generator (its reset ignores a seed): seeded here
            self.env._freeze_rand_vec, self.env.seeded_rand_vec = False, True
            self.env.np_random = np.random.default_rng([seed, PLACEMENT_STREAM])
        self.randomiser.apply(randomisation)
        try:
            state, _ = self.env.reset(seed=seed)
        finally:
            self.env._freeze_rand_vec = True  # the draw is kept for this episode (a reset_model inside it re-reads it)
        return self._observation(state)

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool]:
        state, reward, _, _, info = self.env.step(to_metaworld_action(np.clip(action, -1.0, 1.0)))
        return self._observation(state), float(reward), bool(info["success"])

    def physics(self) -> tuple[mujoco.MjModel, mujoco.MjData, int]:
        """The MuJoCo model and data underneath, and the mj_steps one action takes (benchmarks)."""
        return self.env.model, self.env.data, self.env.frame_skip

    def native_step(self, action: np.ndarray) -> None:
        """MetaWorld's own step, without our observation (benchmarks)."""
        self.env.step(to_metaworld_action(action))

    def mujoco_state(self) -> MujocoState:
        return MujocoState.of(self.env.data)

    def close(self) -> None:
        viewer = self.env.mujoco_renderer._viewers.get(self.env.render_mode) if self.render_config else None
        if viewer is not None:  # made at the first frame, not before
            # gymnasium frees only the GL context and leaves MuJoCo's GL objects to the garbage collector,
            # which would delete them by name in whichever scene's context is current then
            self._make_context_current()
            viewer.con.free()
        self.env.close()
