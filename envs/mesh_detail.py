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
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import mujoco
import numpy as np

from schemas.config import RenderConfig
from schemas.settings import cache_dir

ALGORITHM = "fast_simplification-quadric-v1"  # part of each cached file's key: a new method, new files
MIN_FACES = 1000  # meshes with fewer faces are drawn as they are


def visual_only_meshes(model: mujoco.MjModel) -> list[int]:
    """Ids of the meshes that only non-colliding, untextured geoms draw, of MIN_FACES faces or more."""
    used_by: dict[int, list[int]] = {}
    for geom in range(model.ngeom):
        if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_MESH:
            used_by.setdefault(int(model.geom_dataid[geom]), []).append(geom)

    def drawn_plain(geom: int) -> bool:
        material = model.geom_matid[geom]
        return (model.geom_contype[geom] == 0 and model.geom_conaffinity[geom] == 0
                and (material < 0 or bool(np.all(model.mat_texid[material] < 0))))

    return sorted(mesh for mesh, geoms in used_by.items()
                  if all(drawn_plain(g) for g in geoms) and model.mesh_facenum[mesh] >= MIN_FACES)


def decimated(vertices: np.ndarray, faces: np.ndarray, keep: float, cache: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the mesh decimated to `keep` of its faces; cached by content, written
    under a temporary name and renamed, so workers racing on one mesh each read a whole file."""
    digest = hashlib.sha256(vertices.tobytes() + faces.tobytes() + f"{keep:.4f}/{ALGORITHM}".encode()).hexdigest()
    path = cache / f"{digest[:24]}.npz"
    if path.exists():
        with np.load(path) as stored:
            return stored["vertices"], stored["faces"]
    import fast_simplification

    points, triangles = fast_simplification.simplify(
        vertices.astype(np.float32), faces.astype(np.int32), target_reduction=1.0 - keep)
    points, triangles = np.asarray(points, np.float32), np.asarray(triangles, np.int32)
    cache.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{os.getpid()}-{path.name}")
    with partial.open("wb") as out:
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
    """An adapter's call, before its renderer uploads the meshes: the campaign's `render.mesh_detail`,
    decimating into the user's cache folder; nothing at full detail."""
    if render.mesh_detail < 1.0:
        simplify_visual_meshes(model, render.mesh_detail, cache_dir() / "meshes")


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
        vertex_at, face_at = model.mesh_vertadr[mesh], model.mesh_faceadr[mesh]
        vertices = model.mesh_vert[vertex_at:vertex_at + model.mesh_vertnum[mesh]]
        faces = model.mesh_face[face_at:face_at + model.mesh_facenum[mesh]]
        points, triangles = decimated(vertices, faces, keep, cache)
        normal_at = model.mesh_normaladr[mesh]
        if len(points) > model.mesh_normalnum[mesh] or len(triangles) >= len(faces):
            continue  # no room for a normal per vertex, or nothing gained: drawn as it is
        before += len(faces)
        after += len(triangles)
        model.mesh_vert[vertex_at:vertex_at + len(points)] = points
        model.mesh_vertnum[mesh] = len(points)
        model.mesh_face[face_at:face_at + len(triangles)] = triangles
        model.mesh_facenum[mesh] = len(triangles)
        model.mesh_normal[normal_at:normal_at + len(points)] = _vertex_normals(points, triangles)
        model.mesh_normalnum[mesh] = len(points)
        model.mesh_facenormal[face_at:face_at + len(triangles)] = triangles  # a normal per vertex
        model.mesh_texcoordadr[mesh], model.mesh_texcoordnum[mesh] = -1, 0  # untextured (visual_only_meshes)
    return before, after
