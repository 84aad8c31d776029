"""Simplified visual meshes: fewer triangles for what the camera sees, the same physics.

On this CPU an 84 px frame's cost is its triangles (docs/bench-rollout.md): robosuite's Lift draws
167k faces of visual meshes (the Panda's links, its pedestal) beside 15k of collision geometry. A
campaign's `render.mesh_detail` < 1 renders each visual-only mesh (a mesh no colliding geom uses)
decimated to that fraction of its faces (quadric decimation, `fast_simplification`), once per mesh
file and fraction, cached under the user's cache folder; collision meshes, bodies and inertias are
untouched, so an episode's states are the same at any detail and only its pixels differ. A mesh
drawn with a texture keeps its full detail (decimation drops texture coordinates), as does a small
one (under MIN_FACES faces: nothing to gain).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import mujoco
import numpy as np

ALGORITHM = "fast_simplification-quadric-v1"  # part of each cached file's name: a new method, new files
MIN_FACES = 1000  # meshes with fewer faces are drawn as they are
_MESH_TAG = re.compile(r"<mesh\b[^>]*/>")


def visual_only_meshes(model: mujoco.MjModel) -> set[str]:
    """Names of the meshes that only non-colliding, untextured geoms draw."""
    used_by: dict[int, list[int]] = {}
    for geom in range(model.ngeom):
        if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_MESH:
            used_by.setdefault(int(model.geom_dataid[geom]), []).append(geom)

    def drawn_plain(geom: int) -> bool:
        material = model.geom_matid[geom]
        return (model.geom_contype[geom] == 0 and model.geom_conaffinity[geom] == 0
                and (material < 0 or bool(np.all(model.mat_texid[material] < 0))))

    return {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MESH, mesh) for mesh, geoms in used_by.items()
            if all(drawn_plain(g) for g in geoms) and model.mesh_facenum[mesh] >= MIN_FACES}


def simplified_mesh(source: Path, keep: float, cache: Path) -> Path:
    """The cached decimated copy of a mesh file (STL), made on first use. Written under a temporary
    name and renamed, so workers that race on one file each see a whole one."""
    digest = hashlib.sha256(source.read_bytes()).hexdigest()[:16]
    target = cache / f"{source.stem}-{digest}-{keep:.3f}-{ALGORITHM}.stl"
    if target.exists():
        return target
    import fast_simplification
    import trimesh

    mesh = trimesh.load(source, force="mesh", process=True)  # welds the file's split vertices: decimation
    mesh.merge_vertices(merge_tex=True, merge_norm=True)    # of unwelded triangles tears the surface apart
    vertices, faces = fast_simplification.simplify(
        np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32), target_reduction=1.0 - keep)
    cache.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{os.getpid()}-{target.name}")
    trimesh.Trimesh(vertices, faces, process=False).export(partial)
    os.replace(partial, target)
    return target


def simplify_visual_meshes(xml: str, model: mujoco.MjModel, keep: float, cache: Path) -> tuple[str, int, int]:
    """The model's XML with each visual-only mesh's file replaced by its decimated copy.

    Args:
        xml: the compiled model's XML (robosuite's `sim.model.get_xml()`: mesh files by absolute path).
        model: the model compiled from it, to tell visual-only meshes and count faces.
        keep: the fraction of faces kept, in (0, 1).
        cache: the folder of decimated files.

    Returns:
        (the new XML, faces drawn before, faces drawn after) over the meshes it replaced.
    """
    if not 0.0 < keep < 1.0:
        raise ValueError(f"expected a fraction of faces in (0, 1), got {keep}")
    names = visual_only_meshes(model)
    before = after = 0

    def replace(match: re.Match) -> str:
        nonlocal before, after
        tag = match.group(0)
        name, file = re.search(r'\bname="([^"]+)"', tag), re.search(r'\bfile="([^"]+)"', tag)
        if not name or not file or name.group(1) not in names:
            return tag
        simplified = simplified_mesh(Path(file.group(1)), keep, cache)
        before += int(model.mesh_facenum[model.mesh(name.group(1)).id])
        after += _stl_faces(simplified)
        return tag.replace(f'file="{file.group(1)}"', f'file="{simplified}"')

    return _MESH_TAG.sub(replace, xml), before, after


def _stl_faces(path: Path) -> int:
    with path.open("rb") as stl:  # binary STL: an 80-byte header, then the face count
        stl.seek(80)
        return int.from_bytes(stl.read(4), "little")
