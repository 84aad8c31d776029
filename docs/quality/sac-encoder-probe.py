"""SAC's two encoder layouts (baselines.sac_encoder) on a pixel reach whose target only the frame shows: does the
agent learn to read it, and how well per environment step? A point starts at random in the unit square and moves by
0.1 x the action (2-D, in [-1, 1]) for 30 steps; the target, a 4-pixel red square in a 36 px frame, is drawn anew
each episode; the reward is minus the distance. Reported: the mean final distance over 30 held-out episodes, acting
deterministically (a policy that ignores the frame and goes to the centre ends 0.38 away on average, the mean
distance of a uniform point from the square's centre), and CPU ms per training step. One process, one thread; from the repository root:

    .venv/bin/python docs/quality/sac-encoder-probe.py                           # 3 seeds x both layouts, 10,000 steps
    .venv/bin/python docs/quality/sac-encoder-probe.py --seeds 0 --steps 4000 --encoders critic
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from policies.rl_agent import new_agent  # noqa: E402


class PixelReach(gym.Env):
    def __init__(self, size: int = 36):
        self.size = size
        self.observation_space = gym.spaces.Dict({
            "image": gym.spaces.Box(0, 255, (size, size, 3), np.uint8),
            "proprio": gym.spaces.Box(-1, 2, (2,), np.float32)})
        self.action_space = gym.spaces.Box(-1, 1, (2,), np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        frame = np.zeros((self.size, self.size, 3), np.uint8)
        x, y = (self.target * (self.size - 4)).astype(int)
        frame[y:y + 4, x:x + 4, 0] = 255
        return {"image": frame, "proprio": self.position.astype(np.float32)}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.target, self.position, self.t = self.np_random.uniform(0, 1, 2), self.np_random.uniform(0, 1, 2), 0
        return self._obs(), {}

    def step(self, action):
        self.position = np.clip(self.position + 0.1 * np.asarray(action), 0, 1)
        self.t += 1
        distance = np.linalg.norm(self.position - self.target)
        return self._obs(), -float(distance), False, self.t >= 30, {}


def final_distance(agent, episodes: int = 30) -> float:
    env, finals = PixelReach(), []
    for episode in range(episodes):
        obs, _ = env.reset(seed=10_000 + episode)
        done = False
        while not done:
            action, _ = agent.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
        finals.append(-reward)
    return float(np.mean(finals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=10_000, help="environment steps per training")
    parser.add_argument("--encoders", nargs="+", choices=["critic", "separate"], default=["critic", "separate"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    for seed in args.seeds:
        for encoder in args.encoders:  # side by side, seed by seed
            agent = new_agent("sac", PixelReach(), args.steps, seed, sac_encoder=encoder)
            started = time.process_time()
            agent.learn(total_timesteps=args.steps)
            ms = (time.process_time() - started) / args.steps * 1e3
            print(f"{encoder} seed {seed}: final distance {final_distance(agent):.3f}, {ms:.1f} CPU ms/step", flush=True)


if __name__ == "__main__":
    main()
