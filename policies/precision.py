"""How a training step computes on its device: bf16 autocast where the hardware has bf16 matrix units,
channels_last on CPU. Numbers behind the choices are in docs/bench-train.md.

- bf16 on CPU pays only with AMX (bf16 matrix tiles): there a conv-trunk step ran ~2.5x faster. With
  AVX-512 BF16 alone (dot-product instructions, no tiles: an Intel Xeon) the default model ran 0.94x
  fp32's speed (743 vs 794 samples/s, both channels_last); with neither, oneDNN emulates bf16 and the
  step is ~10x *slower* (an AVX2-only AMD EPYC: 631 -> 65 samples/s). So `train.amp` asks for bf16 and
  gets it only where it helps: AMX on CPU.
- AVX-512 BF16 without AMX is a toss-up that depends on the core and the batch: 1.32x fp32 at batch 256
  on an AMD Zen 4, 0.97x there at batch 64, 0.94x at 256 on an Intel Xeon. So there a long training
  measures both on its own model and batch once (`measured_bf16`) and takes bf16 only if it wins clearly.
- channels_last (NHWC) lets oneDNN pick its blocked convolution kernels without reordering every
  activation: 1.2-1.4x on the default model in fp32 on that same CPU; the conv trunk is ~60% of a step.
- Denormal floats (below 1.2e-38) cost x86 cores ~20x an operation. Adam's moments of parameters whose
  gradients are zero (a dead ReLU's weights) decay into them: in the generalist's SAC agents at 15,000 steps
  25-27% of them, and fused Adam over SAC-sized parameters took 36 ms a step there against 1.5 (docs/bench-rl.md).
  `denormals_flushed` rounds them to zero for an update.
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import torch
from torch import nn

# bf16 is taken where it is measured only if it beats fp32 by this much: a choice that flips on timing
# noise would make two trainings of one recipe compute differently for nothing
BF16_MARGIN = 1.10
# a shorter training does not measure (the probe, a batch read and 8 steps: seconds, would not pay back): it takes
# the choice a longer one measured for its model and batch on this host, else fp32
PROBE_MIN_SAMPLES = 500_000


@contextmanager
def denormals_flushed() -> Iterator[None]:
    """Inside: this thread's float operations read and write denormals (below 1.2e-38) as zero, at full speed
    (module docstring). For an RL agent's update, whose values that small are rounding residue (an Adam
    moment of 1e-39 moves its parameter by ~1e-35); not for simulation, which runs outside it bit for bit as
    before. torch's intra-op threads are not switched: the RL workers run one thread each. A CPU that cannot
    flush (torch's `set_flush_denormal` says so) computes as before."""
    before = flushing_denormals()
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(before)


def cpu_can_flush_denormals() -> bool:
    """Whether torch can flush denormals on this CPU (x86 with SSE3: every one these runs meet)."""
    with denormals_flushed():
        return flushing_denormals()


def flushing_denormals() -> bool:
    """Whether this thread writes a denormal result as zero now (inside `denormals_flushed`)."""
    return (torch.tensor([1e-38]) / 100).item() == 0.0


def cpu_has_bf16_units() -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware tiles (AMX), where bf16 pays; AVX-512 BF16
    alone did not (module docstring)."""
    return bool(torch.cpu._is_amx_tile_supported())


def uses_bf16(device: torch.device, amp: bool) -> bool:
    """`train.amp` on this device: bf16 autocast on cuda, and on a CPU with bf16 units; fp32 elsewhere."""
    return amp and (device.type == "cuda" or (device.type == "cpu" and cpu_has_bf16_units()))


def cpu_bf16_may_pay(device: torch.device) -> bool:
    """AVX-512 BF16 dot products without AMX tiles: only a measurement on the model and batch tells."""
    return device.type == "cpu" and not cpu_has_bf16_units() and bool(torch.cpu._is_avx512_bf16_supported())


def cpu_name() -> str:
    """The CPU's model name (/proc/cpuinfo), else the machine type."""
    try:
        with open("/proc/cpuinfo") as info:
            return next(line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.machine()


def probe_key(model_digest: str, batch_size: int) -> str:
    """What a measured choice holds for: this host's CPU and torch, the threads, the model and the batch."""
    return (f"{cpu_name()} ({torch.backends.cpu.get_cpu_capability()}), torch {torch.__version__}, "
            f"{torch.get_num_threads()} threads, batch {batch_size}, model {model_digest}")


def measured_bf16(step_seconds: Callable[[bool], float], cache: Path, key: str, trials: int = 3) -> tuple[bool, float]:
    """Whether bf16 autocast beats fp32 by BF16_MARGIN on `step_seconds(bf16)` (one training step, timed),
    measured once per `key` (probe_key) and kept in `cache`, so a resumed training and the next
    iteration's compute as this one. A warm-up step of each, then `trials` of each in turns; the
    fastest of each counts (the least disturbed by other load). Returns (bf16, bf16's speed-up)."""
    choices = json.loads(cache.read_text()) if cache.exists() else {}
    if key not in choices:
        step_seconds(False), step_seconds(True)  # oneDNN builds each precision's kernels on its first step
        fastest = _in_turns(step_seconds, trials)
        choices[key] = {"fp32_s": fastest[False], "bf16_s": fastest[True], "speedup": fastest[False] / fastest[True]}
        cache.parent.mkdir(parents=True, exist_ok=True)
        partial = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
        partial.write_text(json.dumps(choices, indent=1, sort_keys=True))
        partial.replace(cache)
    speedup = choices[key]["speedup"]
    return speedup >= BF16_MARGIN, speedup


def known_bf16(cache: Path, key: str) -> bool:
    """Whether `cache` already holds a measured choice for `key`: a training too short to measure one
    takes it (the same host, threads, model and batch) instead of staying in fp32."""
    return cache.exists() and key in json.loads(cache.read_text())


def _in_turns(step_seconds: Callable[[bool], float], trials: int) -> dict[bool, float]:
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(trials):
        for bf16 in (False, True):
            times[bf16].append(step_seconds(bf16))
    return {bf16: min(seconds) for bf16, seconds in times.items()}


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
    if not amp or device.type != "cpu":
        why = ""
    elif cpu_bf16_may_pay(device):  # a training too short to measure, none measured before (stages/train.py)
        why = " (AVX-512 BF16 without AMX: bf16 not measured on this CPU for this model and batch)"
    else:
        why = " (this CPU has no bf16 units: bf16 would be emulated, ~10x slower)"
    return "fp32" + (", channels_last" if uses_channels_last(device) else "") + why
