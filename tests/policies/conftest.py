"""Fixtures of the RL baselines' tests."""

import numpy as np
import pytest

from envs.gym_env import InstructedTasksEnv
from envs.suite import generate_tasks
from schemas.config import RandomiseConfig, RenderConfig, TasksConfig


@pytest.fixture(scope="module")
def lift() -> InstructedTasksEnv:
    tasks = generate_tasks(TasksConfig(specs=["lift"], colours=["red"], horizon={"lift": 40}), seed=0)
    said = sorted({text for task in tasks for text in task.instructions})
    return InstructedTasksEnv(tasks, {text: np.full(8, i, dtype=np.float32) for i, text in enumerate(said)},
                              RenderConfig(image_size=48), RandomiseConfig())
