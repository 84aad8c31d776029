"""The decimated-mesh cache: a file torn by a crash or a full disk is made again, not read for ever."""

from __future__ import annotations

import numpy as np

from envs.mesh_detail import decimated


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy n x n grid of vertices, two triangles a cell."""
    x, y = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    vertices = np.stack([x.ravel(), y.ravel(), np.sin(x.ravel()) * np.cos(y.ravel())], axis=1)
    at = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([at, at + 1, at + n], 1), np.stack([at + 1, at + n + 1, at + n], 1)])
    return vertices, faces.astype(np.int32)


def test_a_torn_cached_mesh_is_made_again(tmp_path):
    vertices, faces = _grid(30)
    first = decimated(vertices, faces, 0.25, tmp_path)
    [cached] = tmp_path.glob("*.npz")
    assert len(first[1]) < len(faces) / 2 and not list(tmp_path.glob(".*"))  # no temporary file left behind
    cached.write_bytes(cached.read_bytes()[:100])  # torn
    again = decimated(vertices, faces, 0.25, tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    with np.load(cached) as stored:  # and whole on disk again
        assert np.array_equal(stored["faces"], first[1])
