"""Per-episode domain randomisation: what is drawn from an episode's seed, and how it is
applied to a MuJoCo model.

Values are drawn for every aspect in a fixed order (so an episode's light does not depend on
which other aspects its family applies), then the aspects an adapter does not apply are set
to None: the record says exactly what the episode saw. The model is always rewritten from the
nominal values captured at construction, so an episode never inherits the previous one's draw.
"""

from __future__ import annotations

from collections.abc import Iterable

import mujoco
import numpy as np
from pydantic import BaseModel

from schemas.config import RandomiseConfig

RANDOMISE_STREAM = 0x52414E44  # keeps these draws apart from the episode's own use of its seed
_PRIMITIVES = {int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_SPHERE),
               int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER),
               int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)}
_NOMINAL_FIELDS = ("light_diffuse", "cam_pos", "cam_quat", "mat_rgba", "geom_rgba", "geom_size", "geom_rbound",
                   "geom_aabb", "geom_friction", "body_mass", "body_inertia")


class Randomisation(BaseModel):
    """One episode's draw; None where the episode's family does not apply that aspect."""

    light: float | None = None
    camera_shift: list[float] | None = None  # metres, world x, y, z
    camera_rotation_deg: list[float] | None = None  # about the camera's own x, y, z
    tint: list[float] | None = None  # RGB scale of scene colours (not the task's objects)
    colour_jitter: list[float] | None = None  # RGB offset of the task's object colours
    size: float | None = None
    mass: float | None = None
    friction: float | None = None


ASPECTS = tuple(Randomisation.model_fields)
VISUAL_ASPECTS = frozenset(ASPECTS[:5])


def sample_randomisation(config: RandomiseConfig, seed: int, applies: Iterable[str]) -> Randomisation | None:
    """Pure: the draw for an episode seed, or None when randomisation is off."""
    if not config.enabled:
        return None
    rng = np.random.default_rng([seed, RANDOMISE_STREAM])
    drawn = {
        "light": rng.uniform(*config.light),
        "camera_shift": rng.uniform(-config.camera_shift_m, config.camera_shift_m, 3),
        "camera_rotation_deg": rng.uniform(-config.camera_rotation_deg, config.camera_rotation_deg, 3),
        "tint": rng.uniform(1 - config.tint, 1 + config.tint, 3),
        "colour_jitter": rng.uniform(-config.colour_jitter, config.colour_jitter, 3),
        "size": rng.uniform(*config.size),
        "mass": rng.uniform(*config.mass),
        "friction": rng.uniform(*config.friction),
    }
    applied = set(applies)
    return Randomisation(**{
        name: (np.round(value, 6).tolist() if name in applied else None) for name, value in drawn.items()
    })


def free_bodies(model: mujoco.MjModel) -> list[int]:
    """Bodies on a free joint: the loose objects of a manipulation scene."""
    return [int(model.jnt_bodyid[j]) for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]


def jitter_rgba(rgba: Iterable[float], randomisation: Randomisation | None) -> np.ndarray:
    """A task object's colour with the episode's jitter: small enough that red stays red."""
    colour = np.asarray(rgba, dtype=np.float64).copy()
    if randomisation is not None and randomisation.colour_jitter is not None:
        colour[:3] = np.clip(colour[:3] + randomisation.colour_jitter, 0.0, 1.0)
    return colour


class SceneRandomiser:
    """Writes a Randomisation into an MjModel, always starting from its nominal values.

    camera: the rendered camera's name (None: no camera); task_geoms: geoms that carry the
    task's colours (left out of the tint; the adapter colours them); object_bodies: bodies
    whose size, mass and friction vary.
    """

    def __init__(self, model: mujoco.MjModel, camera: str | None, task_geoms: Iterable[int],
                 object_bodies: Iterable[int]):
        self.model = model
        self.camera = model.camera(camera).id if camera is not None else None
        # A geom with a material takes its colour from the material (MuJoCo reads geom_rgba only
        # while it is left at the default); tinting the material tints it.
        self.tinted = model.geom_matid < 0
        self.tinted[list(task_geoms)] = False
        bodies = sorted(set(object_bodies))
        self.bodies = np.asarray(bodies, dtype=int)
        self.geoms = np.asarray([g for g in range(model.ngeom)
                                 if model.geom_bodyid[g] in bodies and model.geom_type[g] in _PRIMITIVES], dtype=int)
        self.nominal = {name: getattr(model, name).copy() for name in _NOMINAL_FIELDS}
        self.nominal_headlight = model.vis.headlight.diffuse.copy()

    def apply(self, r: Randomisation | None) -> None:
        model, nominal = self.model, self.nominal
        for name in _NOMINAL_FIELDS:
            getattr(model, name)[:] = nominal[name]
        model.vis.headlight.diffuse[:] = self.nominal_headlight
        if r is None:
            return
        if r.light is not None:
            model.light_diffuse[:] = np.clip(nominal["light_diffuse"] * r.light, 0.0, 1.0)
            model.vis.headlight.diffuse[:] = np.clip(self.nominal_headlight * r.light, 0.0, 1.0)
        if self.camera is not None and r.camera_shift is not None:
            model.cam_pos[self.camera] = nominal["cam_pos"][self.camera] + r.camera_shift
        if self.camera is not None and r.camera_rotation_deg is not None:
            turn = np.zeros(4)
            mujoco.mju_euler2Quat(turn, np.radians(r.camera_rotation_deg), "xyz")
            mujoco.mju_mulQuat(model.cam_quat[self.camera], nominal["cam_quat"][self.camera], turn)
        if r.tint is not None:
            model.mat_rgba[:, :3] = np.clip(nominal["mat_rgba"][:, :3] * r.tint, 0.0, 1.0)
            model.geom_rgba[self.tinted, :3] = np.clip(nominal["geom_rgba"][self.tinted, :3] * r.tint, 0.0, 1.0)
        if r.size is not None and len(self.geoms):
            for name in ("geom_size", "geom_rbound"):
                getattr(model, name)[self.geoms] = nominal[name][self.geoms] * r.size
            model.geom_aabb[self.geoms, 3:] = nominal["geom_aabb"][self.geoms, 3:] * r.size
        if r.mass is not None and len(self.bodies):
            for name in ("body_mass", "body_inertia"):
                getattr(model, name)[self.bodies] = nominal[name][self.bodies] * r.mass
        if r.friction is not None and len(self.geoms):
            model.geom_friction[self.geoms, 0] = nominal["geom_friction"][self.geoms, 0] * r.friction

    def rest_on_support(self, data: mujoco.MjData, r: Randomisation | None) -> None:
        """Raise (or lower) free objects by their change in half-height: a simulator that places
        them for their nominal size would start a grown one inside the table."""
        if r is None or r.size is None:
            return
        model = self.model
        for body in self.bodies:
            joint = model.body_jntadr[body]
            if joint < 0 or model.jnt_type[joint] != mujoco.mjtJoint.mjJNT_FREE:
                continue
            geoms = self.geoms[model.geom_bodyid[self.geoms] == body]
            half_heights = [self._half_height(g) for g in geoms]
            if half_heights:
                data.qpos[model.jnt_qposadr[joint] + 2] += (r.size - 1.0) * max(half_heights)
        mujoco.mj_forward(model, data)

    def _half_height(self, geom: int) -> float:
        size, kind = self.nominal["geom_size"][geom], self.model.geom_type[geom]
        if kind == mujoco.mjtGeom.mjGEOM_BOX or kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            return float(size[2])
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            return float(size[0])
        return float(size[1] + (size[0] if kind == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0))
