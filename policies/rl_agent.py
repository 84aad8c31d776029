"""The RL-from-scratch baselines: stable-baselines3's PPO and SAC on a family's instruction-
conditioned environment (envs.gym_env), their settings, and acting with a saved one."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from envs.gym_env import adapter_action, agent_observation
from envs.observation import DISCRETE_FAMILIES, Observation

RL_ALGORITHMS = ("ppo", "sac")


def supports(algorithm: str, family: str) -> bool:
    """SAC acts in continuous spaces only; PPO in both."""
    return algorithm == "ppo" or family not in DISCRETE_FAMILIES


def new_agent(algorithm: str, env, env_steps: int, seed: int):
    """An untrained agent, SB3's defaults but for the sizes a small budget needs: PPO collects
    rollouts of at most 512 steps (its default 2,048 would be a whole small budget), sized so that
    whole rollouts pass the budget by less than one step each, minibatches of 64; SAC's replay
    holds the budget, learning starts after a tenth of it (at most 1,000 steps), batches of 64."""
    from stable_baselines3 import PPO, SAC

    common = {"policy": "MultiInputPolicy", "env": env, "seed": seed, "verbose": 0, "device": "cpu"}
    if algorithm == "ppo":
        rollouts = math.ceil(env_steps / 512)
        n_steps = math.ceil(env_steps / rollouts)
        return PPO(n_steps=n_steps, batch_size=min(64, n_steps), **common)
    return SAC(buffer_size=env_steps, learning_starts=min(1000, env_steps // 10), batch_size=64, **common)


class RLAgent:
    """A saved baseline, acting deterministically (PPO's most likely action, SAC's mean)."""

    def __init__(self, model, family: str):
        self.model, self.family = model, family

    @classmethod
    def load(cls, algorithm: str, path: Path, family: str) -> RLAgent:
        from stable_baselines3 import PPO, SAC

        return cls({"ppo": PPO, "sac": SAC}[algorithm].load(path, device="cpu"), family)

    def act(self, obs: Observation, embedding: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(agent_observation(obs, embedding), deterministic=True)
        return adapter_action(action, self.family)
