"""robosuite tasks behind the common interface (envs.observation): reset(task, seed), step(action).

Create an environment inside the worker process that uses it (never before a fork): its
offscreen GL context belongs to the process that made it.
"""

from __future__ import annotations

import os
import sys
import types

os.environ.setdefault("MUJOCO_GL", "egl")
# robosuite reads overrides from robosuite.macros_private; ours keeps its console to errors
# (otherwise every worker prints the same five import-time warnings).
_macros = types.ModuleType("robosuite.macros_private")
_macros.CONSOLE_LOGGING_LEVEL = "ERROR"
sys.modules.setdefault("robosuite.macros_private", _macros)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.observation import NO_IMAGE, Observation  # noqa: E402
from envs.randomisation import ASPECTS, Randomisation, SceneRandomiser, free_bodies, jitter_rgba  # noqa: E402
from schemas.config import RenderConfig  # noqa: E402
from schemas.tasks import COLOUR_RGBA, TaskRecord  # noqa: E402


# object role -> (robosuite object name, its visual geom): what task specs may bind colours to.
ROBOSUITE_ROLES: dict[str, dict[str, tuple[str, str]]] = {
    "Lift": {"target": ("cube", "cube_g0_vis")},
    "Stack": {"pick": ("cubeA", "cubeA_g0_vis"), "place": ("cubeB", "cubeB_g0_vis")},
}

MODEL_SEED = 0
FINGERS = ("gripper0_right_leftfinger", "gripper0_right_rightfinger")
PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


class RobosuiteEnv:
    """One robosuite environment, recoloured per task, rendered with the campaign's settings."""

    RANDOMISES = frozenset(ASPECTS)

    def __init__(self, env_name: str, render: RenderConfig | None):
        """render=None: no camera at all (scripted experts need no pixels; 8x faster on CPU)."""
        import robosuite

        self.env_name = env_name
        self.render_config = render
        self.roles = ROBOSUITE_ROLES[env_name]
        camera = {} if render is None else {
            "camera_names": render.camera, "camera_heights": render.image_size, "camera_widths": render.image_size,
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
            hard_reset=False,  # 0.26 s -> 0.002 s per reset (ANCHORS.md); colours are re-applied anyway
            reward_shaping=True,
            # robosuite samples object sizes when it builds the model, from env.rng: a fixed seed
            # makes every worker's model identical, so an episode depends on its own seed only.
            seed=MODEL_SEED,
        )
        if render is not None:
            self._apply_render_settings()
        model = self.env.sim.model._model
        self.fingers = [model.body(name).id for name in FINGERS]
        self.randomiser = SceneRandomiser(
            model, render.camera if render else None,
            task_geoms=[model.geom(visual).id for _, visual in self.roles.values()], object_bodies=free_bodies(model),
        )

    def _apply_render_settings(self) -> None:
        model = self.env.sim.model
        model.vis.quality.offsamples = self.render_config.multisamples
        # A framebuffer the size of the image, not robosuite's 640x480 default.
        model.vis.global_.offwidth = self.render_config.image_size
        model.vis.global_.offheight = self.render_config.image_size
        context = self.env.sim._render_context_offscreen
        context.con.free()
        context._set_mujoco_context_and_buffers()
        context.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.render_config.shadows)
        context.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.render_config.reflections)

    def _apply_colours(self, task: TaskRecord, randomisation: Randomisation | None) -> None:
        model = self.env.sim.model._model
        for role, colour in task.object_colours.items():
            geom_id = model.geom(self.roles[role][1]).id
            model.geom_matid[geom_id] = -1  # drop the wood texture: the colour is the cue
            model.geom_rgba[geom_id] = jitter_rgba(COLOUR_RGBA[colour], randomisation)

    def reset(self, task: TaskRecord, seed: int, randomisation: Randomisation | None = None) -> Observation:
        if task.env_name != self.env_name:
            raise ValueError(f"task {task.task_id} is for {task.env_name}, this environment is {self.env_name}")
        # robosuite samples placements from env.rng (shared with its placement sampler): reseed it in place.
        self.env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        np.random.seed(seed)
        self.randomiser.apply(randomisation)
        self._apply_colours(task, randomisation)
        raw = self.env.reset()
        if randomisation is not None and randomisation.size is not None:
            # robosuite places objects at their nominal height; rest resized ones on the table
            self.randomiser.rest_on_support(self.env.sim.data._data, randomisation)
            raw = self.env._get_observations(force_update=True)
        return self._observation(raw)

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool]:
        raw, reward, _, _ = self.env.step(np.clip(action, -1.0, 1.0))
        return self._observation(raw), float(reward), bool(self.env._check_success())

    def _observation(self, raw: dict[str, np.ndarray]) -> Observation:
        image = NO_IMAGE if self.render_config is None else raw[f"{self.render_config.camera}_image"][::-1].copy()
        proprio = np.concatenate([raw[key] for key in PROPRIO_KEYS]).astype(np.float32)
        privileged = {role: np.asarray(raw[f"{name}_pos"], dtype=np.float64) for role, (name, _) in self.roles.items()}
        privileged["gripper"] = np.asarray(raw["robot0_eef_pos"], dtype=np.float64)
        left, right = self.env.sim.data._data.xpos[self.fingers]  # the fingers open along this line
        privileged["finger_axis"] = right - left
        return Observation(image, proprio, privileged)

    def physics(self) -> tuple[mujoco.MjModel, mujoco.MjData, int]:
        """The MuJoCo model and data underneath, and the mj_steps one action takes (benchmarks)."""
        substeps = round(self.env.control_timestep / self.env.model_timestep)
        return self.env.sim.model._model, self.env.sim.data._data, substeps

    def native_step(self, action: np.ndarray) -> None:
        """robosuite's own step, without our observation (benchmarks)."""
        self.env.step(action)

    def mujoco_state(self) -> tuple[np.ndarray, np.ndarray, float]:
        data = self.env.sim.data
        return data.qpos.copy(), data.qvel.copy(), float(data.time)

    def close(self) -> None:
        self.env.close()
