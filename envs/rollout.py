"""The rollout worker's library: one environment per (family, env, render settings) per worker process,
reused across units (at most SIM2ACT_SCENES_PER_WORKER of them, the least recently used closed beyond),
and one episode rolled out with whoever acts (and, for DAgger, whoever labels).
The explore, evaluate, expert-table and replay stages and the gym adapter all run episodes through it.
"""

from __future__ import annotations

import atexit
import os
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from envs.observation import Observation
from envs.pool import at_worker_exit
from envs.robosuite_control import STOCK_CONTROL
from schemas.config import RenderConfig
from schemas.settings import scenes_per_worker
from schemas.tasks import TaskRecord

_ENVS: OrderedDict[tuple[str, str, str, str], object] = OrderedDict()  # least recently used first
_hooked = False  # close_envs registered to run at exit


def close_envs() -> None:
    """Free GL contexts while the process can still do so cleanly (not in interpreter teardown). A
    pool worker runs it when told to stop (`envs.pool.at_worker_exit`), the test session when it
    finishes; elsewhere it is an atexit hook, registered after the first environment, so it runs
    before the GL libraries' exit hooks that environment's construction registered — but not before
    one registered at a later first draw (MuJoCo's EGL display, made when a MetaWorld environment
    first renders): then the contexts are gone with the display, and the process is ending anyway."""
    while _ENVS:
        _close(_ENVS.popitem()[1])


def _close(env) -> None:
    try:
        env.close()  # each adapter frees its GL objects in its own context (envs/gl.py)
    except Exception:
        pass


def worker_env(task: TaskRecord, render: RenderConfig | None):
    """One environment per (family, env, render settings) per worker process, reused across units.
    Hold it for one unit or episode, not longer: a later call may close it to make room (the least
    recently used beyond SIM2ACT_SCENES_PER_WORKER; a scene is ~0.1–0.3 GB, remade in ~1 s (MetaWorld) to
    2–4 s (robosuite))."""
    from envs.registry import make_env

    # robosuite's controller path is chosen when an environment is made (envs/robosuite_control.py)
    key = (task.family, task.env_name, render.model_dump_json() if render else "no camera",
           os.environ.get(STOCK_CONTROL, ""))
    if key in _ENVS:
        _ENVS.move_to_end(key)
        return _ENVS[key]
    capacity = scenes_per_worker()
    while len(_ENVS) >= capacity:
        _close(_ENVS.popitem(last=False)[1])  # closing one leaves the others' frames as they were (tests/envs)
    _ENVS[key] = make_env(task.family, task.env_name, render)  # the GL libraries register their exit hooks
    global _hooked
    if not _hooked:  # after them (atexit runs the last registered first), once per process
        _hooked = True
        atexit.register(close_envs)
        at_worker_exit(close_envs)
    return _ENVS[key]


Act = Callable[[Observation], np.ndarray]


def rollout(
    env, task: TaskRecord, seed: int, act: Act, randomisation=None, label: Act | None = None,
    steps: int | None = None, placements: str = "benchmark",
) -> tuple[list[dict], Observation, bool]:
    """Run one episode until success or the horizon. -> (step rows, final observation, success).
    `label`, if given, is asked for its action at every state the explorer visits (DAgger); `steps`,
    if given, ends it sooner (explore.policy_steps): its last row is `done`, unsuccessful unless it was.
    `placements="fresh"`: a MetaWorld task's placement drawn from its seed (evaluate.metaworld_placements)."""
    obs = env.reset(task, seed, randomisation) if placements == "benchmark" else \
        env.reset(task, seed, randomisation, placements=placements)
    rows, success = [], False
    last = task.horizon if steps is None else min(steps, task.horizon)
    for step in range(last):
        state = env.mujoco_state()
        action = np.asarray(act(obs), dtype=np.float32)
        expert_action = None if label is None else np.asarray(label(obs), dtype=np.float32).tolist()
        next_obs, reward, success = env.step(action)
        done = success or step == last - 1
        rows.append(
            {
                "step": step, "image": obs.image, "depth": obs.depth, "proprio": obs.proprio.tolist(), "action": action.tolist(),
                "reward": reward, "done": done, "success": success,
                "qpos": state.qpos.tolist(), "qvel": state.qvel.tolist(), "act": state.act.tolist(),
                "mocap": state.mocap.tolist(), "sim_time": state.time, "expert_action": expert_action,
            }
        )
        obs = next_obs
        if done:
            break
    return rows, obs, success


@dataclass(frozen=True)
class Explorer:
    """Who acts in one episode, and what it reports about it (the expert its noise level, a VLM
    its counters): the episode's explorer_stats."""

    act: Act
    stats: Callable[[], dict[str, float]] | None = None
