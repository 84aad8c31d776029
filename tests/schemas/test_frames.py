import numpy as np
import pytest

from schemas.config import ConfigError, RenderConfig, load_config, parse_settings
from schemas.frames import decode_frame, encode_frame, frame_shape


@pytest.mark.parametrize("shape", [(84, 84, 3), (84, 168, 3), (32, 64, 3), (1, 2, 3)])
def test_a_frame_of_one_or_two_views_decodes_from_its_bytes_alone(shape):
    frame = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    data = encode_frame(frame)
    assert frame_shape(data) == shape[:2]
    assert np.array_equal(decode_frame(data), frame)


def test_other_shapes_are_refused():
    for shape in [(84, 85, 3), (84, 252, 3), (84, 84, 4), (168, 84, 3)]:
        with pytest.raises(ValueError, match="one or two square views"):
            encode_frame(np.zeros(shape, np.uint8))
    assert frame_shape(b"x" * 100) is None
    with pytest.raises(ValueError, match="100 bytes are not an RGB frame"):
        decode_frame(b"x" * 100)


def test_the_wrist_camera_and_depth_maps_are_not_combined():
    assert RenderConfig(wrist_camera=True).views == 2 and RenderConfig().views == 1
    with pytest.raises(ConfigError, match=r"^render: wrist_camera: depth maps are recorded for one view only"):
        load_config("smoke", None, parse_settings(["render.wrist_camera=true", "render.depth=true"]))
