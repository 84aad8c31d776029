"""The frozen encoder's plain-torch path gives sentence-transformers' embeddings, and a model it does
not compute goes to sentence-transformers."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from policies.frozen_bert import FrozenBert, is_frozen_bert
from policies.language import ENCODERS

TEXTS = [
    "pick up the red block",
    "go",
    "hoist the blue block into the air, then set it down gently beside the green one",
    "Open the DRAWER!  (and close it again)",
    "déplace le cube vert",  # accents and a word the vocabulary splits into pieces
    " ".join(["stack the yellow cube on the red cube"] * 40),  # 320+ tokens: truncated at 256
]


def test_the_plain_torch_encoder_equals_sentence_transformers():
    from sentence_transformers import SentenceTransformer

    folder = Path(ENCODERS["all-MiniLM-L6-v2"].weights())
    assert is_frozen_bert(folder)
    ours = FrozenBert(folder)
    reference = SentenceTransformer(str(folder), device="cpu").encode(
        TEXTS, batch_size=64, normalize_embeddings=True, convert_to_numpy=True)
    together = ours.encode(TEXTS)
    assert together.dtype == np.float32 and together.shape == (len(TEXTS), 384)
    assert np.abs(together - reference).max() < 3e-6
    # padding to a batch's longest text changes nothing: one at a time gives the same rows
    alone = np.concatenate([ours.encode([text]) for text in TEXTS])
    assert np.abs(alone - together).max() < 3e-6
    assert ours.encode([]).shape == (0, 384)


def test_a_model_of_another_shape_is_not_taken_for_a_frozen_bert(tmp_path):
    folder = Path(ENCODERS["all-MiniLM-L6-v2"].weights())
    copy = tmp_path / "cls-pooled"
    shutil.copytree(folder, copy)
    pooling = copy / "1_Pooling" / "config.json"
    settings = json.loads(pooling.read_text())
    pooling.write_text(json.dumps({**settings, "pooling_mode_cls_token": True, "pooling_mode_mean_tokens": False}))
    assert not is_frozen_bert(copy)
    assert not is_frozen_bert(tmp_path / "nothing-here")
