"""Simplified visual meshes: fewer triangles for what the camera sees, the same physics.

On this CPU an 84 px frame's cost is mostly its triangles (docs/bench-envs.md): robosuite's Lift
draws 167k faces of visual meshes (the Panda's links, its pedestal), MetaWorld's Sawyer 51k, beside
15k of collision geometry. A campaign's `render.mesh_detail` < 1 decimates each visual-only mesh (one
that only non-colliding geoms draw) of the compiled model to that fraction of its faces (quadric
decimation, `fast_simplification`), in place, before the renderer uploads the meshes. Nothing that
physics reads changes (collision meshes, bodies, inertias were computed at compile time), so an
episode's states are the same at any detail and only its pixels differ. A mesh drawn with a texture
keeps its full detail (its texture coordinates would not survive), as does a small one (under
MIN_FACES faces: nothing to gain). Each decimated mesh is cached under the user's cache folder, by
the hash of its compiled vertices and faces, so a worker decimates a mesh once per host.

A mesh that collides stays whole in the model: physics reads it (its convex hull indexes its
vertices). With `render.decimate_colliding` the renderer is given a decimated copy anyway: the mesh
is decimated in place while the adapter makes its renderer (which uploads every mesh then) and
restored bit for bit afterwards (`renderer_meshes`; the config refuses it at full detail).
MetaWorld's Sawyer draws its gripper base and last link this way: 16k of the 23k faces left at
0.1, ~1 ms of a ~3.3 ms frame here.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path

import mujoco
import numpy as np

from schemas.config import RenderConfig
from schemas.settings import cache_dir

ALGORITHM = "fast_simplification-quadric-v1"  # part of each cached file's key: a new method, new files
MIN_FACES = 1000  # meshes with fewer faces are drawn as they are


def _meshes_by_geom(model: mujoco.MjModel) -> dict[int, list[int]]:
    """Each mesh (of MIN_FACES faces or more) and the geoms that draw it."""
    used_by: dict[int, list[int]] = {}
    for geom in range(model.ngeom):
        mesh = int(model.geom_dataid[geom])
        if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_MESH and model.mesh_facenum[mesh] >= MIN_FACES:
            used_by.setdefault(mesh, []).append(geom)
    return used_by


def _untextured(model: mujoco.MjModel, geom: int) -> bool:
    material = model.geom_matid[geom]
    return material < 0 or bool(np.all(model.mat_texid[material] < 0))


def _colliding(model: mujoco.MjModel, geom: int) -> bool:
    return model.geom_contype[geom] != 0 or model.geom_conaffinity[geom] != 0


def visual_only_meshes(model: mujoco.MjModel) -> list[int]:
    """Ids of the meshes that only non-colliding, untextured geoms draw, of MIN_FACES faces or more."""
    return sorted(mesh for mesh, geoms in _meshes_by_geom(model).items()
                  if all(_untextured(model, g) and not _colliding(model, g) for g in geoms))


def colliding_meshes(model: mujoco.MjModel) -> list[int]:
    """Ids of the untextured meshes of MIN_FACES faces or more that a colliding geom uses: physics reads
    them, so only the renderer's copy may be decimated (`renderer_meshes`)."""
    return sorted(mesh for mesh, geoms in _meshes_by_geom(model).items()
                  if all(_untextured(model, g) for g in geoms) and any(_colliding(model, g) for g in geoms))


def decimated(vertices: np.ndarray, faces: np.ndarray, keep: float, cache: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the mesh decimated to `keep` of its faces; cached by content and the
    decimating library's version (pinned in pyproject.toml: another version may make other meshes),
    written under a unique temporary name and renamed, so workers racing on one mesh each read a whole
    file; a cached file that cannot be read is made again."""
    method = f"{keep:.4f}/{ALGORITHM}/{version('fast-simplification')}"
    digest = hashlib.sha256(vertices.tobytes() + faces.tobytes() + method.encode()).hexdigest()
    path = cache / f"{digest[:24]}.npz"
    try:
        with np.load(path) as stored:
            return stored["vertices"], stored["faces"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):  # not made yet, or torn (a full disk): made
        pass
    import fast_simplification

    points, triangles = fast_simplification.simplify(
        vertices.astype(np.float32), faces.astype(np.int32), target_reduction=1.0 - keep)
    points, triangles = np.asarray(points, np.float32), np.asarray(triangles, np.int32)
    cache.mkdir(parents=True, exist_ok=True)
    handle, partial = tempfile.mkstemp(dir=cache, prefix=f".{path.stem}-", suffix=".partial")
    with os.fdopen(handle, "wb") as out:
        np.savez(out, vertices=points, faces=triangles)
    os.replace(partial, path)
    return points, triangles


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (smooth shading), unit length."""
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


def apply_mesh_detail(model: mujoco.MjModel, render: RenderConfig) -> None:
    """An adapter's call, before its renderer uploads the meshes: the campaign's `render.mesh_detail`
    on the visual-only meshes, for good (physics never reads them), decimating into the user's cache
    folder; nothing at full detail."""
    if render.mesh_detail < 1.0:
        simplify_visual_meshes(model, render.mesh_detail, cache_dir() / "meshes")


@contextmanager
def renderer_meshes(model: mujoco.MjModel, render: RenderConfig) -> Iterator[None]:
    """An adapter makes its renderer inside this block, which uploads the model's meshes as they are then:
    with `render.decimate_colliding`, the colliding meshes are decimated meanwhile and restored bit for bit
    when the block ends, so the renderer holds the decimated copy and physics the full mesh. Their convex
    hulls (drawn only by MuJoCo's debug view) are not uploaded meanwhile: they index the full mesh's vertices.
    Without it, the block changes nothing."""
    meshes = colliding_meshes(model) if render.decimate_colliding else []
    saved = [_mesh_record(model, mesh) for mesh in meshes]
    try:
        for mesh in meshes:
            model.mesh_graphadr[mesh] = -1
            _decimate_in_place(model, mesh, render.mesh_detail, cache_dir() / "meshes")
        yield
    finally:
        for mesh, record in zip(meshes, saved):
            _restore_mesh(model, mesh, record)


_MESH_COUNTS = ("mesh_vertnum", "mesh_normalnum", "mesh_facenum", "mesh_texcoordadr", "mesh_texcoordnum",
                "mesh_graphadr")


def _mesh_record(model: mujoco.MjModel, mesh: int) -> dict[str, np.ndarray | int]:
    """Copies of everything `_decimate_in_place` and `renderer_meshes` write for one mesh."""
    vertex_at, normal_at, face_at = model.mesh_vertadr[mesh], model.mesh_normaladr[mesh], model.mesh_faceadr[mesh]
    record: dict[str, np.ndarray | int] = {name: int(getattr(model, name)[mesh]) for name in _MESH_COUNTS}
    record["vert"] = model.mesh_vert[vertex_at:vertex_at + model.mesh_vertnum[mesh]].copy()
    record["normal"] = model.mesh_normal[normal_at:normal_at + model.mesh_normalnum[mesh]].copy()
    record["face"] = model.mesh_face[face_at:face_at + model.mesh_facenum[mesh]].copy()
    record["facenormal"] = model.mesh_facenormal[face_at:face_at + model.mesh_facenum[mesh]].copy()
    return record


def _restore_mesh(model: mujoco.MjModel, mesh: int, record: dict[str, np.ndarray | int]) -> None:
    for name in _MESH_COUNTS:
        getattr(model, name)[mesh] = record[name]
    vertex_at, normal_at, face_at = model.mesh_vertadr[mesh], model.mesh_normaladr[mesh], model.mesh_faceadr[mesh]
    model.mesh_vert[vertex_at:vertex_at + len(record["vert"])] = record["vert"]
    model.mesh_normal[normal_at:normal_at + len(record["normal"])] = record["normal"]
    model.mesh_face[face_at:face_at + len(record["face"])] = record["face"]
    model.mesh_facenormal[face_at:face_at + len(record["facenormal"])] = record["facenormal"]


def simplify_visual_meshes(model: mujoco.MjModel, keep: float, cache: Path) -> tuple[int, int]:
    """Decimate the model's visual-only meshes in place, before a renderer uploads them.

    Args:
        model: a compiled model (its mesh arrays are rewritten; nothing physics reads is).
        keep: the fraction of faces kept, in (0, 1).
        cache: the folder of decimated meshes.

    Returns:
        (faces drawn before, faces drawn after), over the meshes it decimated.

    Raises:
        ValueError: `keep` outside (0, 1).
    """
    if not 0.0 < keep < 1.0:
        raise ValueError(f"expected a fraction of faces in (0, 1), got {keep}")
    before = after = 0
    for mesh in visual_only_meshes(model):
        faces = int(model.mesh_facenum[mesh])
        if _decimate_in_place(model, mesh, keep, cache):
            before += faces
            after += int(model.mesh_facenum[mesh])
    return before, after


def _decimate_in_place(model: mujoco.MjModel, mesh: int, keep: float, cache: Path) -> bool:
    """The mesh's arrays rewritten with its decimated copy, drawn untextured with a normal per vertex;
    False (nothing written) where that copy has no room or gains nothing."""
    vertex_at, face_at = model.mesh_vertadr[mesh], model.mesh_faceadr[mesh]
    vertices = model.mesh_vert[vertex_at:vertex_at + model.mesh_vertnum[mesh]]
    faces = model.mesh_face[face_at:face_at + model.mesh_facenum[mesh]]
    points, triangles = decimated(vertices, faces, keep, cache)
    normal_at = model.mesh_normaladr[mesh]
    if len(points) > model.mesh_normalnum[mesh] or len(triangles) >= len(faces):
        return False  # no room for a normal per vertex, or nothing gained: drawn as it is
    model.mesh_vert[vertex_at:vertex_at + len(points)] = points
    model.mesh_vertnum[mesh] = len(points)
    model.mesh_face[face_at:face_at + len(triangles)] = triangles
    model.mesh_facenum[mesh] = len(triangles)
    model.mesh_normal[normal_at:normal_at + len(points)] = _vertex_normals(points, triangles)
    model.mesh_normalnum[mesh] = len(points)
    model.mesh_facenormal[face_at:face_at + len(triangles)] = triangles  # a normal per vertex
    model.mesh_texcoordadr[mesh], model.mesh_texcoordnum[mesh] = -1, 0  # untextured (the callers' choice of meshes)
    return True
