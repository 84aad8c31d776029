"""The CPU precision path: bf16 autocast only where the CPU has bf16 units, channels_last on CPU, and a
training step that runs (and learns) in bf16 on CPU when asked."""

import json

import pytest
import torch

from policies import precision
from policies.model import ModelDims, VLAModel, vla_loss
from schemas.config import ModelConfig

DIMS = ModelDims(image_size=84, proprio_dim=9, action_dim=7, discrete_actions=4, language_dim=384)
CPU, CUDA = torch.device("cpu"), torch.device("cuda")


@pytest.mark.parametrize("units", [True, False])
def test_amp_on_cpu_means_bf16_only_with_bf16_units(monkeypatch, units):
    monkeypatch.setattr(precision, "cpu_has_bf16_units", lambda: units)
    assert precision.uses_bf16(CPU, True) is units and precision.uses_bf16(CPU, False) is False
    assert precision.uses_bf16(CUDA, True) is True  # every GPU it trains on has bf16 (Ampere on)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)
    described = precision.describe(CPU, True)
    assert described.startswith("bf16 autocast (CPU bf16 units: AMX)" if units else "fp32, channels_last (this CPU has no")
    if not units:  # AVX-512 BF16 alone: bf16 may pay, and the line says it was not measured, not that it is slower
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
        assert "not measured" in precision.describe(CPU, True)


def test_bf16_units_on_cpu_means_amx_tiles(monkeypatch):
    # AVX-512 BF16 without AMX trained the default model slower in bf16 than in fp32 (docs/bench-train.md)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    assert precision.cpu_has_bf16_units() is False
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: True)
    assert precision.cpu_has_bf16_units() is True


def test_on_cpu_the_model_and_its_frames_are_channels_last():
    model = precision.to_device_layout(VLAModel(ModelConfig(dim=32, heads=4), DIMS), CPU)
    stem = model.vision.stem.features[0].weight
    assert stem.is_contiguous(memory_format=torch.channels_last) and not stem.is_contiguous()
    image = precision.image_layout(torch.rand(2, 3, 84, 84), CPU)
    assert image.is_contiguous(memory_format=torch.channels_last)
    assert precision.image_layout(torch.rand(2, 3, 84, 84), CPU, channels_last=False).is_contiguous()


def test_a_bf16_training_step_on_cpu_computes_in_bf16_and_learns():
    torch.manual_seed(0)
    # the patch ViT: cheap where bf16 is emulated (a CPU without bf16 units runs this test too)
    model = precision.to_device_layout(
        VLAModel(ModelConfig(dim=32, heads=4, vision="vit", vision_depth=1, fusion_depth=1, chunk=1), DIMS), CPU)
    optimiser = torch.optim.AdamW(model.parameters(), lr=3e-3)
    image = precision.image_layout(torch.rand(8, 3, 84, 84), CPU)
    language, proprio, action = torch.randn(8, 384), torch.randn(8, 9), torch.randn(8, 7)
    index = torch.full((8,), -1)
    losses = []
    for _ in range(60):
        with precision.autocast(CPU, True):
            out = model(image, language, proprio)
            loss = vla_loss(model, image, language, proprio, action, index, 0.2, 0.1)
        optimiser.zero_grad()
        loss.total.backward()
        optimiser.step()
        losses.append(loss.terms["action_mse"].item())
    assert out.z_ol.dtype == torch.bfloat16  # the matmuls ran in bf16
    assert all(p.dtype == torch.float32 for p in model.parameters())  # the weights stay fp32
    assert losses[-1] < 0.6 * losses[0]


def test_where_bf16_may_pay_a_training_measures_once_and_takes_it_only_when_it_wins_clearly(tmp_path, monkeypatch):
    """AVX-512 BF16 without AMX: 1.32x on one CPU, 0.94x on another (docs/bench-train.md): measured, kept."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    assert precision.cpu_bf16_may_pay(CPU) and not precision.cpu_bf16_may_pay(CUDA)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: True)
    assert not precision.cpu_bf16_may_pay(CPU)  # AMX: bf16 without asking (uses_bf16)

    calls = []

    def timed(seconds):
        def step(bf16: bool) -> float:
            calls.append(bf16)
            return seconds[bf16] * (2.0 if len(calls) <= 2 else 1.0)  # the first step of each builds its kernels
        return step

    cache = tmp_path / "models" / "precision.json"
    assert precision.measured_bf16(timed({False: 1.0, True: 0.75}), cache, "host, batch 256") == (True, 1.0 / 0.75)
    assert calls == [False, True] + [False, True] * 3  # a warm-up of each, then turns
    assert precision.measured_bf16(timed({False: 1.0, True: 9.0}), cache, "host, batch 256") == (True, 1.0 / 0.75)
    assert len(calls) == 8  # kept: the resumed training and the next iteration's take the same without measuring
    bf16, speedup = precision.measured_bf16(timed({False: 1.0, True: 0.95}), cache, "host, batch 64")
    assert not bf16 and speedup == pytest.approx(1.0 / 0.95)  # a 5% win is within timing noise: fp32
    assert sorted(json.loads(cache.read_text())) == ["host, batch 256", "host, batch 64"]
    assert not list(cache.parent.glob("*.tmp"))
