"""robosuite tasks behind one small interface: reset(seed) -> Observation, step(action).

Create an environment inside the worker process that uses it (never before a fork): its
offscreen GL context belongs to the process that made it.
"""

from __future__ import annotations

import os
import sys
import types
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")
# robosuite reads overrides from robosuite.macros_private; ours keeps its console to errors
# (otherwise every worker prints the same five import-time warnings).
_macros = types.ModuleType("robosuite.macros_private")
_macros.CONSOLE_LOGGING_LEVEL = "ERROR"
sys.modules.setdefault("robosuite.macros_private", _macros)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from schemas.config import RenderConfig  # noqa: E402
from schemas.tasks import COLOUR_RGBA, TaskRecord  # noqa: E402


@dataclass(frozen=True)
class EnvMeta:
    """What task generation may know of an environment without starting it."""

    # object role -> (robosuite object name, its visual geom)
    objects: dict[str, tuple[str, str]]
    templates: tuple[str, ...]


ENV_METADATA: dict[str, EnvMeta] = {
    "Lift": EnvMeta(
        objects={"target": ("cube", "cube_g0_vis")},
        templates=(
            "pick up the {target} block",
            "lift the {target} cube",
            "grab the {target} block and raise it",
            "raise the {target} cube off the table",
            "take the {target} block and hold it up",
        ),
    ),
    "Stack": EnvMeta(
        objects={"pick": ("cubeA", "cubeA_g0_vis"), "place": ("cubeB", "cubeB_g0_vis")},
        templates=(
            "stack the {pick} block on the {place} block",
            "put the {pick} cube on top of the {place} cube",
            "place the {pick} block onto the {place} one",
            "set the {pick} cube down on the {place} cube",
        ),
    ),
}

MODEL_SEED = 0
ACTION_DIM = 7  # OSC_POSE deltas (xyz, axis-angle) + gripper, each in [-1, 1]
PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
PROPRIO_DIM = 9


@dataclass
class Observation:
    image: np.ndarray  # uint8 (H, W, 3), upright
    proprio: np.ndarray  # float32 (PROPRIO_DIM,)
    objects: dict[str, np.ndarray]  # privileged: role -> position, for scripted experts only
    gripper_pos: np.ndarray


class TaskEnv:
    """One robosuite environment, recoloured per task, rendered with the campaign's settings."""

    def __init__(self, env_name: str, render: RenderConfig, horizon: int):
        import robosuite

        self.env_name = env_name
        self.render_config = render
        self.meta = ENV_METADATA[env_name]
        self.horizon = horizon
        self.env = robosuite.make(
            env_name,
            robots="Panda",
            has_renderer=False,
            has_offscreen_renderer=True,
            use_camera_obs=True,
            camera_names=render.camera,
            camera_heights=render.image_size,
            camera_widths=render.image_size,
            control_freq=20,
            horizon=horizon,
            ignore_done=True,
            hard_reset=False,  # 0.26 s -> 0.002 s per reset (ANCHORS.md); colours are re-applied anyway
            reward_shaping=True,
            # robosuite samples object sizes when it builds the model, from env.rng: a fixed seed
            # makes every worker's model identical, so an episode depends on its own seed only.
            seed=MODEL_SEED,
        )
        self._apply_render_settings()

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

    def _apply_colours(self, task: TaskRecord) -> None:
        model = self.env.sim.model
        for role, colour in task.object_colours.items():
            geom_id = model.geom_name2id(self.meta.objects[role][1])
            model._model.geom_matid[geom_id] = -1  # drop the wood texture: the colour is the cue
            model._model.geom_rgba[geom_id] = COLOUR_RGBA[colour]

    def reset(self, task: TaskRecord, seed: int) -> Observation:
        if task.env_name != self.env_name:
            raise ValueError(f"task {task.task_id} is for {task.env_name}, this environment is {self.env_name}")
        # robosuite samples placements from env.rng (shared with its placement sampler): reseed it in place.
        self.env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        np.random.seed(seed)
        self._apply_colours(task)
        return self._observation(self.env.reset())

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool]:
        raw, reward, _, _ = self.env.step(np.clip(action, -1.0, 1.0))
        return self._observation(raw), float(reward), bool(self.env._check_success())

    def _observation(self, raw: dict[str, np.ndarray]) -> Observation:
        image = raw[f"{self.render_config.camera}_image"][::-1].copy()  # OpenGL rows run bottom-up
        proprio = np.concatenate([raw[key] for key in PROPRIO_KEYS]).astype(np.float32)
        objects = {role: np.asarray(raw[f"{name}_pos"], dtype=np.float64) for role, (name, _) in self.meta.objects.items()}
        return Observation(image, proprio, objects, np.asarray(raw["robot0_eef_pos"], dtype=np.float64))

    def mujoco_state(self) -> tuple[np.ndarray, np.ndarray, float]:
        data = self.env.sim.data
        return data.qpos.copy(), data.qvel.copy(), float(data.time)

    def close(self) -> None:
        self.env.close()
