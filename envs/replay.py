"""replay: re-render a stored episode from the MuJoCo state its steps keep, with the render
settings it was explored with or another camera or image size, into an MP4.

The episode's environment is reset as exploration reset it (task colours, seed, the recorded
domain randomisation: light, camera pose, tint, sizes), then each step's state (qpos, qvel, act,
mocap, time: the state before that step's action) is set back and drawn as its observation was.
The state after the last action is not stored, so a replay has one frame per step: the episode's
final `next_image` is not among them.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from envs.observation import MujocoState
from envs.randomisation import Randomisation
from schemas.config import RenderConfig, recorded_render
from schemas.errors import Sim2ActError
from schemas.tasks import CONTROL_HZ, TaskRecord
from schemas.workspace import Workspace
from warehouse.catalog import Catalog



class ReplayError(Sim2ActError, ValueError):
    """A replay refused before anything is rendered; its message is one line."""


@dataclass(frozen=True)
class StoredEpisode:
    episode_id: str
    task: TaskRecord  # the task explore reset it as (a relabelled episode's intended one, not the one it is filed as)
    seed: int
    randomisation: Randomisation | None
    render: RenderConfig | None  # None: explored without a camera
    states: list[MujocoState]  # each step's, before its action, in step order


@dataclass(frozen=True)
class ReplayResult:
    path: Path
    frames: int
    render: RenderConfig


def load_episode(catalog: Catalog, episode_id: str) -> StoredEpisode:
    """An episode's row, task, render settings and step states, read from the catalog (read-only)."""
    from warehouse.tasks import find_task

    rows = catalog.query(
        "SELECT e.campaign, e.task_id, e.seed, e.randomisation, e.render, e.error, r.summary, "
        "json_extract_string(e.explorer_stats, '$.relabelled_from') FROM episodes e "
        "LEFT JOIN stage_runs r ON r.unit_key = e.shard_key WHERE e.episode_id = ?", [episode_id]
    )
    if not rows:
        raise ReplayError(f"replay: no episode {episode_id!r} in {catalog.path} "
                          "(`sim2act sql \"SELECT episode_id FROM episodes\"` lists them)")
    campaign, filed_as, seed, randomisation, render, error, summary, relabelled_from = rows[0]
    # a relabelled episode is filed as the task it ended doing; explore reset it as the one it set out for,
    # and the reset is what colours the objects
    task_id = relabelled_from or filed_as
    task = find_task(catalog, campaign, task_id)
    if task is None:
        raise ReplayError(f"replay: episode {episode_id!r}: its task {task_id!r} is not among campaign "
                          f"{campaign!r}'s tasks")
    states = _states(catalog, episode_id)
    if not states:
        failed = f" (its environment failed: {error})" if error else ""
        raise ReplayError(f"replay: episode {episode_id!r} has no steps to replay{failed}")
    return StoredEpisode(
        episode_id=episode_id, task=task, seed=seed,
        randomisation=Randomisation.model_validate(randomisation) if randomisation else None,
        render=RenderConfig.model_validate(recorded_render(render, json.loads(summary) if summary else {}))
        if render else None, states=states,
    )


def _states(catalog: Catalog, episode_id: str) -> list[MujocoState]:
    rows = catalog.query(
        "SELECT qpos, qvel, act, mocap, sim_time FROM steps WHERE episode_id = ? ORDER BY step", [episode_id]
    )
    if any(not qpos for qpos, *_ in rows):
        raise ReplayError(f"replay: episode {episode_id!r} stores no MuJoCo state in its steps")
    return [MujocoState(*(np.asarray(v or [], dtype=np.float64) for v in (qpos, qvel, act, mocap)), float(time))
            for qpos, qvel, act, mocap, time in rows]


def replay_render(episode: StoredEpisode, camera: str | None = None, size: int | None = None) -> RenderConfig:
    """The episode's render settings with `camera` and `size` (image side, pixels) in place of its own."""
    from envs.registry import cameras

    stored = episode.render or RenderConfig()
    camera = camera or stored.camera
    valid = cameras(episode.task.family, episode.task.env_name)
    if camera not in valid:
        raise ReplayError(f"replay: {episode.task.family} environment {episode.task.env_name} has no camera "
                          f"{camera!r} (valid: {', '.join(valid)})")
    try:
        return RenderConfig.model_validate(
            {**stored.model_dump(), "camera": camera, "image_size": stored.image_size if size is None else size})
    except ValidationError as exc:
        raise ReplayError(f"replay: --size {size}: {exc.errors()[0]['msg']}") from None


def replay_frames(episode: StoredEpisode, render: RenderConfig) -> Iterator[np.ndarray]:
    """One frame per step: the episode reset as explored, then each step's state drawn."""
    # explore's cache: one env per render settings per process, kept open between episodes (a scene
    # takes 1–4 s to make: replaying an episode per command or per video would pay it each time)
    from envs.rollout import worker_env

    env = worker_env(episode.task, render)
    env.reset(episode.task, episode.seed, episode.randomisation)
    for step, state in enumerate(episode.states):
        yield env.render_state(state, after_step=step > 0)


def default_video_path(episode_id: str, render: RenderConfig) -> Path:
    """In the current folder, named after the episode and the settings it is drawn with."""
    name = re.sub(r"[^A-Za-z0-9._-]", "_", episode_id)
    return Path(f"{name}_{render.camera}_{render.image_size}px.mp4")


def write_video(frames: Iterable[np.ndarray], path: Path, fps: int) -> int:
    """An MP4 of the frames, whole or not at all (written beside, then moved). -> frames written."""
    from warehouse.video import video_writer

    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    writer, count = video_writer(partial, fps), 0
    try:
        for frame in frames:
            writer.append_data(frame)
            count += 1
        writer.close()
        partial.replace(path)
    except BaseException:
        writer.close()
        partial.unlink(missing_ok=True)
        raise
    return count


def replay(workspace: Workspace, episode_id: str, camera: str | None = None, size: int | None = None,
           out: Path | None = None, fps: int | None = None) -> ReplayResult:
    """Re-render an episode into an MP4 at `out` (default: default_video_path). Everything is
    checked (episode, camera, size, fps, path) before anything is rendered."""
    if fps is not None and fps < 1:
        raise ReplayError(f"replay: --fps must be at least 1, got {fps}")
    if out is not None and out.suffix.lower() != ".mp4":
        raise ReplayError(f"replay: --out must name an .mp4 file, got {out}")
    catalog = Catalog(workspace.catalog)
    catalog.check_version()
    episode = load_episode(catalog, episode_id)
    render = replay_render(episode, camera, size)
    if render.image_size % 2:
        raise ReplayError(f"replay: --size must be even for an MP4 (yuv420p), got {render.image_size}")
    path = out or default_video_path(episode_id, render)
    frames = write_video(replay_frames(episode, render), path, CONTROL_HZ[episode.task.family] if fps is None else fps)
    return ReplayResult(path=path, frames=frames, render=render)
