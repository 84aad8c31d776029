"""An exponential moving average of a model's weights (train.ema), the weights a training registers:
Diffusion Policy keeps one, and on small data a single training's last weights vary with the last
few batches it saw. Batch-norm statistics are averaged with the parameters (they belong to them),
counters copied."""

from __future__ import annotations

import torch
from torch import nn

WARMUP = 10  # the decay at step t is at most (1 + t) / (WARMUP + t): early steps are not remembered for long


def decay_at(step: int, decay: float) -> float:
    return min(decay, (1 + step) / (WARMUP + step))


class WeightAverage:
    """The average of `model`'s state (parameters and floating buffers), updated after each optimiser step."""

    def __init__(self, model: nn.Module, decay: float, state: dict[str, torch.Tensor] | None = None):
        self.decay = decay
        # on the model's device: a resumed average is read from a checkpoint loaded to the CPU, and updating it
        # from a GPU model's weights would mix devices
        devices = {name: value.device for name, value in model.state_dict().items()}
        self.weights = {name: value.detach().clone().to(devices.get(name, value.device))
                        for name, value in (state or model.state_dict()).items()}

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> None:
        """After optimiser step `step` (1 the first)."""
        keep = decay_at(step - 1, self.decay)
        for name, value in model.state_dict().items():
            average = self.weights[name]
            if average.is_floating_point():
                average.lerp_(value.detach().to(average.dtype), 1.0 - keep)
            else:
                average.copy_(value)
