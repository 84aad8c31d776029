"""The RL baselines' view of a family's tasks: a real gymnasium environment over the adapters."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as check_sb3_env

from envs.gym_env import InstructedTasksEnv
from envs.suite import generate_tasks
from schemas.config import RandomiseConfig, RenderConfig, TasksConfig


def _env(specs: list[str], colours: list[str], **render) -> InstructedTasksEnv:
    tasks = generate_tasks(TasksConfig(specs=specs, colours=colours), seed=0)
    said = sorted({text for task in tasks for text in task.instructions})
    embeddings = {text: np.full(8, i, dtype=np.float32) for i, text in enumerate(said)}  # one vector per instruction
    return InstructedTasksEnv(tasks, embeddings, RenderConfig(image_size=48, **render), RandomiseConfig())


def test_with_the_wrist_camera_the_space_holds_both_views():
    env = _env(["lift"], ["red"], wrist_camera=True)
    check_sb3_env(env, warn=True)  # SB3's own check: the observations it gets fit the declared space
    obs, _ = env.reset(seed=3)
    assert obs["image"].shape == env.observation_space["image"].shape == (48, 96, 3)


@pytest.mark.parametrize("specs", [["lift"], ["nav-room"]])
def test_a_family_is_a_valid_gymnasium_and_sb3_environment(specs):
    env = _env(specs, ["red", "green"])
    check_env(env, skip_render_check=True)  # spaces, seeding, reset/step types
    check_sb3_env(env, warn=True)
    obs, info = env.reset(seed=3)
    assert obs["image"].shape == (48, 48, 3) and obs["image"].dtype == np.uint8 and obs["image"].std() > 0
    assert obs["proprio"].shape == (9,)
    task = next(t for t in env.tasks if t.task_id == info["task_id"])
    assert info["instruction"] in task.instructions  # training instructions only: the held-out ones stay held out
    assert obs["instruction"][0] == env.embeddings[info["instruction"]][0]


def test_episodes_draw_tasks_and_end_at_the_horizon_counted():
    env = _env(["lift"], ["red", "green", "blue"])
    drawn, steps = set(), 0
    for episode in range(6):
        _, info = env.reset(seed=episode)
        drawn.add(info["task_id"])
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(np.zeros(7, dtype=np.float32))  # stand still: never succeeds
            steps += 1
            done = terminated or truncated
        assert not terminated
    assert len(drawn) > 1
    assert steps == 6 * env.tasks[0].horizon
    assert (env.episodes_finished, env.successes) == (6, 0)


@pytest.mark.parametrize("end_on_success", [False, True])
def test_a_success_ends_the_episode_only_when_told_and_counts_once(end_on_success):
    """By default an episode runs to its horizon past its success (dense rewards: ended there, hovering would
    pay more); `end_on_success` ends it at the first. Either way it counts as one success."""
    env = _env(["nav-room"], ["red"])
    env.end_on_success = end_on_success
    env.reset(seed=1)
    adapter_step, steps = env._env.step, []

    def succeeding_at_three(action):
        obs, reward, _ = adapter_step(action)
        steps.append(1)
        return obs, reward, len(steps) >= 3  # the goal reached at the third step, and stayed at

    env._env.step = succeeding_at_three
    try:
        done, ends = False, []
        while not done:
            _, _, terminated, truncated, info = env.step(0)
            done = terminated or truncated
            ends.append((terminated, truncated))
    finally:
        env._env.step = adapter_step
    horizon = env.tasks[0].horizon
    assert ends[-1] == ((True, False) if end_on_success else (False, True))
    assert len(ends) == (3 if end_on_success else horizon) and info["success"]
    assert (env.episodes_finished, env.successes) == (1, 1)


def test_a_family_with_more_scenes_than_a_worker_keeps_still_runs_its_episodes(monkeypatch):
    from envs.rollout import _ENVS, close_envs
    from schemas.settings import SCENES_PER_WORKER_ENV

    monkeypatch.setenv(SCENES_PER_WORKER_ENV, "1")
    close_envs()  # none cached by other tests: each reset that changes scene must remake one
    env = _env(["nav-room", "nav-ball"], ["red"])  # two env names, one scene at a time: remade as drawn
    drawn = set()
    for episode in range(6):
        obs, info = env.reset(seed=episode)
        drawn.add(info["task_id"])
        for _ in range(3):
            obs, *_ = env.step(np.int64(0))
        assert obs["image"].std() > 0 and len(_ENVS) == 1
    assert drawn == {"nav-room-red", "nav-ball-red"}
