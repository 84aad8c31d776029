"""MP4 video of frames, H.264 through the pinned imageio-ffmpeg's own ffmpeg (libx264): a codec
every LeRobot tool and video player takes. The LeRobot export and `sim2act replay` write with it."""

from __future__ import annotations

from pathlib import Path

VIDEO_CODEC = "h264"
CONTROL_FPS = 20  # where a family is unknown: robosuite's control rate (each family's: schemas.tasks.CONTROL_HZ)


def video_writer(path: Path, fps: int):
    """imageio's writer: append_data(frame) for each uint8 RGB frame (even sides: yuv420p), then close()."""
    import imageio.v2 as iio

    # g=2 as LeRobot's encoder: a random frame decodes from a keyframe at most one back.
    # macro_block_size=1: imageio would otherwise resize 84 px to 96.
    return iio.get_writer(
        path, format="FFMPEG", fps=fps, codec="libx264", pixelformat="yuv420p", quality=None,
        macro_block_size=1, ffmpeg_log_level="error", ffmpeg_params=["-g", "2", "-crf", "23"],
    )
