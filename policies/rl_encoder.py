"""The RL baselines' observation encoder: stable-baselines3's own (NatureCNN on the frames, the proprio
and instruction vectors flattened beside it), in bf16 autocast on batches where that pays on this CPU, as
`train.amp` decides for our policy (policies/precision.py).

Why: a SAC step takes a gradient step on 64 frames, five encoder passes and, as SB3 wrote it, three backward
ones, ~150 ms of a core in fp32 (docs/bench-rl.md), so the generalist's SAC agents trained for ~16-20 h each. One
of the backward passes is wasted (`skip_critic_encoder_in_actor_loss` skips it). Only the
encoder autocasts: its features come back in fp32, so the heads, losses, log-probabilities and entropy
terms compute as SB3 wrote them. Every batch autocasts, SAC's target critics' included (SB3 keeps them out of
training mode; in fp32 their pass was ~11% of a SAC step), its frames channels_last (oneDNN's AMX kernels take
that layout: 1.3x the encoder's bf16 pass and backward at batch 64); acting (one frame) stays fp32, where bf16's
casts would cost more than they save. SAC's update converts each batch's frames once
(`frames_converted_once`), not at each of its five encoder passes."""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import CombinedExtractor

from policies.precision import (autocast, cpu_bf16_may_pay, describe, image_layout, measured_bf16, probe_key,
                               uses_bf16, uses_channels_last)
from schemas.keys import digest_of

CPU = torch.device("cpu")


class AutocastExtractor(CombinedExtractor):
    """SB3's CombinedExtractor; while `bf16` is set, its pass over a batch of more than one observation
    (an update's, a target critic's) runs in bf16 autocast on channels_last frames and returns fp32
    features; one observation (acting) is fp32. Unset, it is CombinedExtractor exactly (the same
    parameters, drawn from the same seeds)."""

    bf16 = False

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        if not self.bf16 or len(next(iter(observations.values()))) == 1:
            return super().forward(observations)
        observations = {key: image_layout(value, CPU) if value.dim() == 4 else value
                        for key, value in observations.items()}
        with autocast(CPU, True):
            features = super().forward(observations)
        return features.float()


def skip_critic_encoder_in_actor_loss(agent) -> None:
    """SB3's SAC takes the actor's loss through the critic (after the critic's step), and that loss's backward
    pass runs on through the critic's own encoder, into gradients the critic's next `zero_grad` throws away:
    the actor's gradients do not depend on them (the encoder reads the frames, not the actor's action). Here
    the critic's encoder stops requiring gradients from the critic's step to the actor's, so that pass skips
    it: the same parameters after every update, bit for bit, ~13% less compute a SAC update (docs/bench-rl.md).
    PPO (one network, one loss) and a critic that shares the actor's encoder are left as they are. The hooks
    live on the agent's optimisers: call it on every agent made or loaded to train."""
    critic = getattr(agent, "critic", None)
    if critic is None or critic.share_features_extractor:
        return
    encoder = list(critic.features_extractor.parameters())

    def requiring(flag: bool):
        def hook(*_) -> None:
            for parameter in encoder:
                parameter.requires_grad_(flag)
        return hook

    critic.optimizer.register_step_post_hook(requiring(False))
    agent.actor.optimizer.register_step_post_hook(requiring(True))


@contextmanager
def frames_converted_once(agent) -> Iterator[None]:
    """While `agent` (SAC) updates: each batch its replay samples arrives with the frames as its encoders take
    them (uint8 to float / 255, as SB3's `preprocess_obs`; channels_last where they autocast), and the
    policy's own conversion is off. SB3 converts the batch at each encoder pass, five an update (the frames
    three times, the next frames twice), ~10% of a SAC step on AMX (py-spy, docs/bench-rl.md); here twice.
    The same numbers bit for bit; acting, outside the update, converts as before."""
    models = [module for module in agent.policy.modules() if isinstance(module, BaseModel)]
    normalised = [model.normalize_images for model in models]
    if not isinstance(agent.observation_space, gym.spaces.Dict):
        raise TypeError(f"expected a Dict observation space (MultiInputPolicy), got {agent.observation_space}")
    images = [key for key, space in agent.observation_space.spaces.items() if is_image_space(space)] \
        if normalised[0] else []
    layout = torch.channels_last if any(e.bf16 for e in extractors(agent)) and uses_channels_last(CPU) \
        else torch.contiguous_format
    buffer = agent.replay_buffer
    if "sample" in vars(buffer):  # converting twice would divide the frames by 255 twice
        raise RuntimeError("expected the replay buffer's own sample method, got one already wrapped")
    sample = buffer.sample

    def converted(observations: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {key: torch.empty(frames.shape, dtype=torch.float32, device=frames.device, memory_format=layout)
                .copy_(frames).div_(255.0) if key in images else frames for key, frames in observations.items()}

    def sample_converted(*args, **kwargs):
        batch = sample(*args, **kwargs)
        return batch._replace(observations=converted(batch.observations),
                              next_observations=converted(batch.next_observations))

    buffer.sample = sample_converted
    for model in models:
        model.normalize_images = False
    try:
        yield
    finally:
        del buffer.sample  # the buffer's own method again (a checkpoint pickles the buffer)
        for model, normalise in zip(models, normalised):
            model.normalize_images = normalise


def extractors(agent) -> list[AutocastExtractor]:
    return [module for module in agent.policy.modules() if isinstance(module, AutocastExtractor)]


def encoder_precision(agent, cache: Path, batch_size: int = 64) -> tuple[bool, str]:
    """bf16 for the agent's encoders during its updates, or fp32, and why (for the log): `train.amp`'s rule for
    this CPU (bf16 with AMX, fp32 without bf16 units); with AVX-512 BF16 alone, one update-sized pass
    and backward of the encoder measured both ways, once per host and encoder (`cache`: the workspace's
    precision choices), bf16 taken at >= 1.10x. Sets the agent's extractors accordingly."""
    found = extractors(agent)
    if not found:  # an agent saved before the encoder existed: SB3's own, fp32
        return False, "fp32 (an agent saved with SB3's own encoder)"
    if not cpu_bf16_may_pay(CPU):
        bf16, why = uses_bf16(CPU, True), describe(CPU, True)
    else:
        encoder = found[0]
        key = probe_key(digest_of(["sb3 CombinedExtractor", repr(agent.observation_space)]), batch_size)
        bf16, speedup = measured_bf16(_pass_timer(agent, encoder, batch_size), cache, key)
        why = f"{'bf16 autocast' if bf16 else 'fp32'}: bf16 measured at {speedup:.2f}x fp32's speed on this CPU"
    for extractor in found:
        extractor.bf16 = bf16
    return bf16, f"its encoder on batches: {why}"


def _pass_timer(agent, encoder: AutocastExtractor, batch_size: int):
    """Seconds of one forward and backward pass of a copy of `encoder` over `batch_size` sampled
    observations, in bf16 or fp32; the agent, its spaces' RNG and torch's as they were."""
    space = copy.deepcopy(agent.observation_space)
    space.seed(0)
    samples = [space.sample() for _ in range(batch_size)]
    batch = {key: torch.as_tensor(np.stack([s[key] for s in samples])) for key in samples[0]}
    probe = copy.deepcopy(encoder).train()

    def seconds(bf16: bool) -> float:
        probe.bf16 = bf16
        probe.zero_grad(set_to_none=True)
        started = time.perf_counter()
        agent.policy.extract_features(batch, probe).sum().backward()
        return time.perf_counter() - started

    return seconds
