"""How a training step computes on its device: bf16 autocast where the hardware has bf16 matrix units,
channels_last on CPU. Numbers behind the choices are in docs/bench-train.md.

- bf16 on CPU pays only with AMX (bf16 matrix tiles): there a conv-trunk step ran ~2.5x faster. With
  AVX-512 BF16 alone (dot-product instructions, no tiles: an Intel Xeon) the default model ran 0.94x
  fp32's speed (743 vs 794 samples/s, both channels_last); with neither, oneDNN emulates bf16 and the
  step is ~10x *slower* (an AVX2-only AMD EPYC: 631 -> 65 samples/s). So `train.amp` asks for bf16 and
  gets it only where it helps: AMX on CPU.
- channels_last (NHWC) lets oneDNN pick its blocked convolution kernels without reordering every
  activation: 1.2-1.4x on the default model in fp32 on that same CPU; the conv trunk is ~60% of a step.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch
from torch import nn


def cpu_has_bf16_units() -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware tiles (AMX), where bf16 pays; AVX-512 BF16
    alone did not (module docstring)."""
    return bool(torch.cpu._is_amx_tile_supported())


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
        units = "" if device.type == "cuda" else " (CPU bf16 units: AMX)"
        return f"bf16 autocast{units}" + (", channels_last" if uses_channels_last(device) else "")
    why = "" if not amp or device.type != "cpu" else " (this CPU has no bf16 units (AMX): bf16 is slower here)"
    return "fp32" + (", channels_last" if uses_channels_last(device) else "") + why
