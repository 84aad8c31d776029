"""A worker's scenes (envs.rollout.worker_env): reused across units, at most SIM2ACT_SCENES_PER_WORKER
of them, the least recently used closed to make room — without touching the others' frames."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from envs import registry
from envs.rollout import _ENVS, close_envs, worker_env
from envs.suite import generate_tasks
from schemas.config import RenderConfig, TasksConfig
from schemas.settings import SCENES_PER_WORKER_ENV


def test_beyond_its_scenes_a_worker_closes_the_least_recently_used_and_the_rest_draw_the_same(monkeypatch):
    monkeypatch.setenv(SCENES_PER_WORKER_ENV, "2")
    close_envs()  # from a known cache: the other tests' scenes are remade when they ask again
    tasks = {t.task_id: t for t in generate_tasks(TasksConfig(specs=["nav-room", "nav-ball", "mw-reach"],
                                                              colours=["red"]), seed=0)}
    room, ball, reach = tasks["nav-room-red"], tasks["nav-ball-red"], next(t for t in tasks.values() if t.family == "metaworld")
    render = RenderConfig(image_size=48)
    made, make_env = [], registry.make_env
    monkeypatch.setattr(registry, "make_env", lambda family, name, how: made.append(name) or make_env(family, name, how))

    def frame(task):
        env = worker_env(task, render)
        env.reset(task, 7)
        return env, env.render_state(env.mujoco_state(), after_step=False).copy()

    room_env, room_frame = frame(room)
    reach_frame = frame(reach)[1]  # MetaWorld's GL context beside ours
    assert worker_env(room, render) is room_env  # reused, and now the most recently used
    ball_frame = frame(ball)[1]  # a third scene: MetaWorld's, the least recently used, is closed ...
    gc.collect()  # ... and collected while ball's context is current: nothing of it may be freed there
    assert len(_ENVS) == 2 and worker_env(room, render) is room_env
    assert np.array_equal(frame(room)[1], room_frame) and np.array_equal(frame(ball)[1], ball_frame)
    assert np.array_equal(frame(reach)[1], reach_frame)  # made again, drawing what the closed one drew
    del room_env
    gc.collect()  # room, closed for it, collected likewise (in MetaWorld's context)
    assert np.array_equal(frame(ball)[1], ball_frame) and len(_ENVS) == 2
    assert made == [t.env_name for t in (room, reach, ball, reach)]  # each scene made once while kept


def test_a_family_without_an_adapter_is_refused_by_name():
    """make_env fell through to MetaWorld for any family it had no branch for (a family added to the types
    but not to the registry built MetaWorld scenes of its env names)."""
    from envs.registry import make_env

    with pytest.raises(ValueError, match=r"expected a family of robosuite, metaworld, navigation, got 'maze' \(Maze-v0\)"):
        make_env("maze", "Maze-v0", None)
