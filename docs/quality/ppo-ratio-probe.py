"""PPO acts in fp32 (one frame a step) and updates its encoder in bf16 autocast (batches of 64, where
`encoder_precision` takes bf16): how far is the first epoch's importance ratio from 1, against the clip range
(0.2)? Before each update the rollout's actions are scored again by the unchanged policy, in minibatches of
64 as the update does, under bf16 and under fp32: |ratio - 1| per sample, its mean, 99th percentile and max,
and the share outside the clip range (clipped from the first step on). The environment is a pixel reach at
84 px (the baselines' frame size) whose frame holds a textured background and the target; 7-D actions like the
manipulation families'. One process, one thread; from the repository root:

    .venv/bin/python docs/quality/ppo-ratio-probe.py                  # 3 seeds, 8 rollouts of 512 steps
    .venv/bin/python docs/quality/ppo-ratio-probe.py --seeds 0 --rollouts 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from policies.rl_agent import new_agent  # noqa: E402
from policies.rl_encoder import extractors  # noqa: E402


class TexturedReach(gym.Env):
    """A point in the unit square moved by 0.1 x the action's first two components for 50 steps toward a red
    square drawn on a fixed noisy texture; the other five components do nothing (the arm's rotation, grip)."""

    def __init__(self, size: int = 84):
        self.size = size
        self.texture = np.random.default_rng(0).integers(0, 160, (size, size, 3), dtype=np.uint8)
        self.observation_space = gym.spaces.Dict({
            "image": gym.spaces.Box(0, 255, (size, size, 3), np.uint8),
            "proprio": gym.spaces.Box(-1, 2, (2,), np.float32)})
        self.action_space = gym.spaces.Box(-1, 1, (7,), np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        frame = self.texture.copy()
        x, y = (self.target * (self.size - 8)).astype(int)
        frame[y:y + 8, x:x + 8] = (255, 0, 0)
        return {"image": frame, "proprio": self.position.astype(np.float32)}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.target, self.position, self.t = self.np_random.uniform(0, 1, 2), self.np_random.uniform(0, 1, 2), 0
        return self._obs(), {}

    def step(self, action):
        self.position = np.clip(self.position + 0.1 * np.asarray(action[:2]), 0, 1)
        self.t += 1
        return self._obs(), -float(np.linalg.norm(self.position - self.target)), False, self.t >= 50, {}


def ratio_deviation(agent, bf16: bool) -> np.ndarray:
    """|ratio - 1| of every sample of the agent's rollout buffer, scored in minibatches of 64 with its
    extractors in bf16 or fp32, against the log-probabilities its rollout stored."""
    for extractor in extractors(agent):
        extractor.bf16 = bf16
    deviations = []
    with torch.no_grad():
        for batch in agent.rollout_buffer.get(64):
            _, log_prob, _ = agent.policy.evaluate_actions(batch.observations, batch.actions)
            deviations.append((torch.exp(log_prob - batch.old_log_prob) - 1).abs().numpy())
    return np.concatenate(deviations)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--rollouts", type=int, default=8, help="rollouts of 512 steps per training")
    args = parser.parse_args()
    torch.set_num_threads(1)
    clip = 0.2
    print("| seed | rollout | policy std | precision | mean abs(ratio-1) | p99 | max | outside the clip |")
    print("|---:|---:|---:|---|---:|---:|---:|---:|")
    for seed in args.seeds:
        agent = new_agent("ppo", TexturedReach(), 512 * args.rollouts, seed)
        assert agent.n_steps == 512 and agent.clip_range(1.0) == clip
        update = agent.train

        def probed_update(agent=agent, update=update, seed=seed, count=[0]) -> None:
            count[0] += 1
            std = float(torch.exp(agent.policy.log_std.detach()).mean())
            for bf16 in (True, False):
                deviation = ratio_deviation(agent, bf16)
                print(f"| {seed} | {count[0]} | {std:.2f} | {'bf16' if bf16 else 'fp32'} | {deviation.mean():.2e} | "
                      f"{np.percentile(deviation, 99):.2e} | {deviation.max():.2e} | {(deviation > clip).mean():.1%} |",
                      flush=True)
            for extractor in extractors(agent):
                extractor.bf16 = True  # the update's precision where bf16 is taken
            update()

        agent.train = probed_update
        agent.learn(total_timesteps=512 * args.rollouts)


if __name__ == "__main__":
    main()
