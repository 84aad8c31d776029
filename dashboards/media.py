"""The videos the page plays: the evaluation rollouts' MP4s in the workspace's media folder,
and explored episodes drawn from the frames their steps store.

Exploration writes no video, but every step keeps the frame the explorer saw, so an episode's
video is those frames themselves, encoded once on first request (H.264, warehouse.video) into
the server's own temporary folder: nothing is written into the workspace.
"""

from __future__ import annotations

import hashlib
import threading
from pathlib import Path

import numpy as np

from dashboards.reads import episode_frames
from schemas.frames import decode_frame
from schemas.tasks import CONTROL_HZ
from schemas.workspace import Workspace
from warehouse.catalog import Catalog

MIN_VIDEO_SIDE = 256  # 84 px frames are enlarged by whole pixels so the player does not blur them


def media_file(workspace: Workspace, name: str) -> Path | None:
    """The MP4 `name` names inside the workspace's media folder, or None: nothing outside it
    (no `..`, no absolute path, no link out) and nothing but MP4s."""
    if "\0" in name:  # no file has one: resolve() would raise
        return None
    folder = workspace.media.resolve()
    try:
        path = (folder / name).resolve()
        if path.suffix.lower() != ".mp4" or not path.is_relative_to(folder) or not path.is_file():
            return None
    except OSError:  # a name too long for the file system (ENAMETOOLONG): no such file either
        return None
    return path


def media_url(workspace: Workspace, stored: str | None) -> str | None:
    """Where the page fetches a video the catalog names. The catalog stores the path it was written
    at; a workspace copied or moved keeps its media folder, so the file name is what counts."""
    if not stored or media_file(workspace, Path(stored).name) is None:
        return None
    return f"/media/{Path(stored).name}"


def _enlarged(frame: np.ndarray) -> np.ndarray:
    side = frame.shape[0]
    factor = max(1, -(-MIN_VIDEO_SIDE // side))
    factor += (side * factor) % 2  # yuv420p needs even sides
    return frame.repeat(factor, axis=0).repeat(factor, axis=1) if factor > 1 else frame


class EpisodeVideos:
    """Explored episodes' MP4s, made from their stored frames on first request and kept."""

    def __init__(self, catalog: Catalog, folder: Path):
        self.catalog = catalog
        self.folder = folder
        # two requests for one episode encode it once; another episode's (or a made one's) do not wait on it
        self._locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()
        self._made: dict[str, Path] = {}  # episode -> its video, once made

    def path(self, episode_id: str) -> Path | None:
        """The episode's MP4, or None when it has no stored frames (unknown, failed, camera-less)."""
        from warehouse.video import CONTROL_FPS, video_writer

        made = self._made.get(episode_id)
        if made is not None and made.exists():  # a Range request for a video made before: no catalog read, no lock
            return made
        family = self.catalog.query("SELECT t.family FROM episodes e JOIN task_families t USING (campaign, task_id) "
                                    "WHERE e.episode_id = ? LIMIT 1", [episode_id])
        fps = CONTROL_HZ.get(family[0][0], CONTROL_FPS) if family else CONTROL_FPS  # played at the family's rate
        path = self.folder / f"{hashlib.sha256(f'{episode_id}@{fps}'.encode()).hexdigest()[:24]}.mp4"
        with self._locks_lock:
            lock = self._locks.setdefault(episode_id, threading.Lock())
        with lock:
            if path.exists():
                self._made[episode_id] = path
                return path
            frames = episode_frames(self.catalog, episode_id)
            if not frames:
                return None
            partial = path.with_name(f".{path.name}.partial.mp4")
            writer = video_writer(partial, fps=fps)
            try:
                for blob in frames:
                    writer.append_data(_enlarged(decode_frame(blob)))
            finally:
                writer.close()
            partial.replace(path)
            self._made[episode_id] = path
            return path
