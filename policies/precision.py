"""How a training step computes on its device: bf16 autocast where the hardware has bf16 matrix units,
channels_last on CPU. Numbers behind the choices are in docs/bench-train.md.

- bf16 on CPU pays only with native bf16 units (AMX tiles, or AVX-512 BF16): there a conv-trunk step
  ran ~2.5x faster. Without them oneDNN emulates bf16 and the same step is ~15x *slower* (an AVX2-only
  AMD EPYC: 533 -> 34 samples/s on the default model), so `train.amp` asks for bf16 and gets it only
  where it helps.
- channels_last (NHWC) lets oneDNN pick its blocked convolution kernels without reordering every
  activation: 1.2-1.4x on the default model in fp32 on that same CPU; the conv trunk is ~60% of a step.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch
from torch import nn


def cpu_has_bf16_units() -> bool:
    """Whether this CPU computes bf16 matrix products natively (AMX tiles or AVX-512 BF16)."""
    return bool(torch.cpu._is_amx_tile_supported() or torch.cpu._is_avx512_bf16_supported())


def uses_bf16(device: torch.device, amp: bool) -> bool:
    """`train.amp` on this device: bf16 autocast on cuda, and on a CPU with bf16 units; fp32 elsewhere."""
    return amp and (device.type == "cuda" or (device.type == "cpu" and cpu_has_bf16_units()))


def uses_channels_last(device: torch.device) -> bool:
    return device.type == "cpu"


def autocast(device: torch.device, bf16: bool) -> AbstractContextManager:
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)


def to_device_layout(model: nn.Module, device: torch.device, channels_last: bool | None = None) -> nn.Module:
    """The model on `device`, its 4-d weights channels_last where that is faster (None: this device's choice)."""
    model = model.to(device)
    wanted = uses_channels_last(device) if channels_last is None else channels_last
    return model.to(memory_format=torch.channels_last) if wanted else model


def image_layout(image: torch.Tensor, device: torch.device, channels_last: bool | None = None) -> torch.Tensor:
    """A batch of frames (B, C, H, W) in the layout the model's weights have (None: this device's choice)."""
    wanted = uses_channels_last(device) if channels_last is None else channels_last
    return image.contiguous(memory_format=torch.channels_last) if wanted else image


def describe(device: torch.device, amp: bool) -> str:
    """For the training's log line: what the step computes in, and why."""
    if uses_bf16(device, amp):
        units = "" if device.type == "cuda" else " (CPU bf16 units)"
        return f"bf16 autocast{units}" + (", channels_last" if uses_channels_last(device) else "")
    why = "" if not amp or device.type != "cpu" else " (this CPU has no bf16 units: emulated bf16 is slower)"
    return "fp32" + (", channels_last" if uses_channels_last(device) else "") + why
