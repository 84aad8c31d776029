"""Acting with action chunks (train.model.chunk > 1): the model predicts this step's action and the
next chunk-1; an episode's actor turns those predictions into one action per step, as the model's
config says (`execution`):

- temporal_ensemble (ACT, Zhao et al. 2023): predict at every step; the action for step t is the
  weighted mean of every prediction made for t so far (the chunk predicted at t, at t-1, ... at
  t-chunk+1), weights exp(-m * i) with i = 0 the oldest. Smooth, and each step still sees the latest frame.
- receding (Diffusion Policy, Chi et al. 2023): predict, execute the first `execute_steps` actions
  open-loop, predict again. Fewer model calls; reacts only every execute_steps steps.

Predictions are averaged in the model's own space (normalised means, or probabilities over discrete
actions) and turned into an action after (Policy.action_of).
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from envs.observation import Observation

if TYPE_CHECKING:
    from policies.policy import Decision, Policy


def temporal_ensemble(predictions: list[np.ndarray], decay: float) -> np.ndarray:
    """The weighted mean of the predictions made for one step, oldest first: weights exp(-decay * i)."""
    weights = np.exp(-decay * np.arange(len(predictions)))
    return np.tensordot(weights / weights.sum(), np.stack(predictions), axes=1)


class EpisodeActor:
    """One episode of a policy: call it with each observation and the instruction in force. A changed
    instruction (a curriculum's next sub-goal) forgets the chunks predicted under the last one."""

    def __init__(self, policy: Policy, family: str):
        self.policy, self.family = policy, family
        config = policy.config
        self.chunk, self.execution = config.chunk, config.execution
        self.decay, self.per_prediction = config.ensemble_decay, config.steps_per_prediction
        self.instruction: str | None = None
        self.step = 0
        self.chunks: deque[tuple[int, np.ndarray]] = deque()  # (step predicted at, chunk), oldest first
        self.uncertainty = 0.0

    def _restart(self, instruction: str) -> None:
        self.instruction, self.step = instruction, 0
        self.chunks.clear()

    def __call__(self, obs: Observation, instruction: str) -> Decision:
        from policies.policy import Decision

        if self.chunk == 1:
            return self.policy.act(obs, instruction, self.family)
        if instruction != self.instruction:
            self._restart(instruction)
        due = self.execution == "temporal_ensemble" or not self.chunks or \
            self.step - self.chunks[-1][0] >= self.per_prediction
        if due:
            chunk, self.uncertainty = self.policy.predict(obs, instruction, self.family)
            self.chunks.append((self.step, chunk))
        while self.step - self.chunks[0][0] >= self.chunk:  # chunks that say nothing about this step
            self.chunks.popleft()
        if self.execution == "temporal_ensemble":
            value = temporal_ensemble([chunk[self.step - start] for start, chunk in self.chunks], self.decay)
        else:
            start, chunk = self.chunks[-1]
            value = chunk[self.step - start]
        self.step += 1
        return Decision(self.policy.action_of(value, self.family), self.uncertainty)
