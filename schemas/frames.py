"""How a camera frame is stored in the warehouse: its raw RGB bytes, row-major (H, W, 3), uint8,
upright, square — or, for campaigns with a wrist camera (`render.wrist_camera`), two square views side
by side, (H, 2H, 3): the main camera left, the hand's right. The byte count alone says which (3·H² is never
3·2·S²: √2 is irrational), so a stored frame decodes without its campaign's config. The Parquet file's zstd compresses them: on rendered robosuite frames that is
~2.9 KB per 84x84 frame against ~8 KB as PNG, and it decodes ~5x faster (measured; see
docs/warehouse.md), which is what lets training read >5,000 frames/s on two cores.

In SQL a frame is a BLOB; in Python `decode_frame(blob)` gives the array back.

A depth map (campaigns with `render.depth`) is stored beside it the same way: distance along the
camera axis in millimetres, uint16, row-major (H, W), upright; 0 where nothing was hit within the
camera's far plane. Millimetres keep what a policy can use at 84 px (a 4 px cube is ~3 cm) and
compress as well as the colours; `decode_depth(blob)` gives metres back as float32.
"""

from __future__ import annotations

import math

import numpy as np


def encode_frame(image: np.ndarray) -> bytes:
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or image.shape[1] not in (
            image.shape[0], 2 * image.shape[0]):
        raise ValueError(f"a frame is a uint8 RGB array of one or two square views (H, H or 2H, 3), "
                         f"got {image.dtype} {image.shape}")
    return np.ascontiguousarray(image).tobytes()


def _square_side(data: bytes, bytes_per_pixel: int) -> int | None:
    side = math.isqrt(len(data) // bytes_per_pixel)
    return side if side > 0 and side * side * bytes_per_pixel == len(data) else None


def frame_shape(data: bytes) -> tuple[int, int] | None:
    """(height, width) of the RGB frame these bytes hold — one square view or two side by side — or
    None if they cannot be one."""
    for views in (1, 2):
        side = _square_side(data, 3 * views)
        if side is not None:
            return side, views * side
    return None


def encode_depth(depth_m: np.ndarray) -> bytes:
    if depth_m.ndim != 2 or depth_m.shape[0] != depth_m.shape[1]:
        raise ValueError(f"a depth map is a square (H, W) array of metres, got {depth_m.shape}")
    millimetres = np.rint(np.clip(np.nan_to_num(depth_m, nan=0.0, posinf=0.0), 0.0, 65.535) * 1000.0)
    return np.ascontiguousarray(millimetres.astype(np.uint16)).tobytes()


def depth_side(data: bytes) -> int | None:
    """The side of the square depth map these bytes hold, or None if they cannot be one."""
    return _square_side(data, 2)


def decode_depth(data: bytes) -> np.ndarray:
    side = depth_side(data)
    if side is None:
        raise ValueError(f"{len(data)} bytes are not a square depth map")
    return np.frombuffer(data, dtype=np.uint16).reshape(side, side).astype(np.float32) / 1000.0


def decode_frame(data: bytes) -> np.ndarray:
    shape = frame_shape(data)
    if shape is None:
        raise ValueError(f"{len(data)} bytes are not an RGB frame of one or two square views")
    return np.frombuffer(data, dtype=np.uint8).reshape(*shape, 3)
