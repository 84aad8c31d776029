"""A family's tasks as one instruction-conditioned gymnasium environment, for the RL baselines
(stable-baselines3): each episode draws a task and one of its training instructions, the agent
sees the frame, the proprio and the instruction's embedding, and is rewarded by the task's own
reward. The same adapters, render and randomisation as the campaign's rollouts.

An episode runs to its horizon, a success included, as MetaWorld's and robosuite's RL benchmarks run
theirs: their rewards are dense and pay nearly as much just short of success as at it (robosuite Lift
~0.56 a step holding the cube, 1 lifted; MetaWorld up to 10 a step near the goal, 10 at it), so an episode
ended at its first success pays an agent more for hovering than for succeeding (`end_on_success`: the
baselines before 2026-12-05)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from envs.observation import ACTION_DIM, DISCRETE_FAMILIES, NAVIGATION_ACTIONS, PROPRIO_DIM, Observation
from schemas.config import RandomiseConfig, RenderConfig
from schemas.tasks import TaskRecord


def agent_observation(obs: Observation, embedding: np.ndarray) -> dict[str, np.ndarray]:
    """What an RL agent reads at a step: the same for training and for evaluation."""
    return {"image": obs.image, "proprio": obs.proprio.astype(np.float32), "instruction": embedding.astype(np.float32)}


def adapter_action(action, family: str) -> np.ndarray:
    """An agent's action as the adapters take it: float32, navigation's index as [index]."""
    return np.asarray([action] if family in DISCRETE_FAMILIES else action, dtype=np.float32).reshape(-1)


def observation_space(image_size: int, embedding_dim: int, views: int = 1) -> gym.spaces.Dict:
    """`views`: square camera views side by side in a frame (render.views)."""
    return gym.spaces.Dict({
        "image": gym.spaces.Box(0, 255, (image_size, views * image_size, 3), np.uint8),
        "proprio": gym.spaces.Box(-np.inf, np.inf, (PROPRIO_DIM,), np.float32),
        "instruction": gym.spaces.Box(-np.inf, np.inf, (embedding_dim,), np.float32),
    })


def action_space(family: str) -> gym.Space:
    if family in DISCRETE_FAMILIES:
        return gym.spaces.Discrete(len(NAVIGATION_ACTIONS))
    return gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)


class InstructedTasksEnv(gym.Env):
    """Episodes over `tasks` (one family), each said with one of its training instructions."""

    metadata = {"render_modes": []}

    def __init__(self, tasks: list[TaskRecord], embeddings: dict[str, np.ndarray], render: RenderConfig,
                 randomise: RandomiseConfig, end_on_success: bool = False):
        families = {task.family for task in tasks}
        if len(families) != 1:
            raise ValueError(f"one family per environment, got {sorted(families)}")
        from envs.rollout import worker_env

        self.tasks, self.embeddings, self.randomise = tasks, embeddings, randomise
        self.end_on_success = end_on_success
        self.family = families.pop()
        self.render = render
        # an adapter per env name, asked for at each reset: a family with more env names than a worker
        # keeps scenes (SIM2ACT_SCENES_PER_WORKER) has the least recently used remade, not all held open
        self._env = worker_env(tasks[0], render)
        self.observation_space = observation_space(render.image_size, len(next(iter(embeddings.values()))),
                                                   render.views)
        self.action_space = action_space(self.family)
        self._task, self._embedding, self._steps, self._succeeded = tasks[0], None, 0, False
        self.episodes_finished, self.successes = 0, 0  # over the environment's life: what training achieved

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        from envs.randomisation import sample_randomisation
        from envs.rollout import worker_env

        super().reset(seed=seed)
        self._task = self.tasks[int(self.np_random.integers(len(self.tasks)))]
        instruction = self._task.instructions[int(self.np_random.integers(len(self._task.instructions)))]
        self._embedding = self.embeddings[instruction]
        env = self._env = worker_env(self._task, self.render)
        episode_seed = int(self.np_random.integers(2**31))
        obs = env.reset(self._task, episode_seed, sample_randomisation(self.randomise, episode_seed, env.RANDOMISES))
        self._steps, self._succeeded = 0, False
        return agent_observation(obs, self._embedding), {"task_id": self._task.task_id, "instruction": instruction}

    def step(self, action):
        obs, reward, success = self._env.step(adapter_action(action, self.family))
        self._steps += 1
        self._succeeded = self._succeeded or bool(success)
        terminated = bool(success) and self.end_on_success
        truncated = not terminated and self._steps >= self._task.horizon
        if terminated or truncated:
            self.episodes_finished += 1
            self.successes += self._succeeded  # an episode that succeeded at any step, as evaluation counts it
        return agent_observation(obs, self._embedding), float(reward), terminated, truncated, {"success": success}
