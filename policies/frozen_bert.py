"""A frozen BERT sentence encoder in plain torch: the forward pass of a sentence-transformers
model made of a BERT transformer, mean pooling and (optionally) normalisation, from the same
weights and tokenizer files.

Why not sentence-transformers itself: importing it (transformers, scikit-learn, scipy) takes ~7 s
on this CPU, more than embedding every instruction of a campaign; this module needs torch,
`tokenizers` and `safetensors` (~0.3 s past torch). Its embeddings equal sentence-transformers'
within 3e-7 (tests/policies/test_language.py). The trainable encoder (`policies.language.TextEncoder`)
and models of another shape still load through sentence-transformers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

MAX_TOKENS = 256  # sentence-transformers' max_seq_length for MiniLM (sentence_bert_config.json) when absent
BATCH = 64  # instructions per forward pass: bounds memory for a generalist's thousands of instructions


def is_frozen_bert(folder: Path) -> bool:
    """True when the sentence-transformers model in `folder` is exactly what this module computes:
    a BERT with absolute positions, then mean pooling, then nothing or normalisation."""
    try:
        config = json.loads((folder / "config.json").read_text())
        modules = [m["type"].rsplit(".", 1)[-1] for m in json.loads((folder / "modules.json").read_text())]
        pooling = json.loads((folder / "1_Pooling" / "config.json").read_text())
    except (OSError, KeyError, ValueError):
        return False
    only_mean = pooling.get("pooling_mode_mean_tokens") and not any(
        value for key, value in pooling.items() if key.startswith("pooling_mode_") and key != "pooling_mode_mean_tokens")
    return (config.get("model_type") == "bert" and config.get("position_embedding_type", "absolute") == "absolute"
            and config.get("hidden_act") == "gelu" and modules in (["Transformer", "Pooling"],
                                                                   ["Transformer", "Pooling", "Normalize"])
            and bool(only_mean) and (folder / "model.safetensors").exists() and (folder / "tokenizer.json").exists())


class FrozenBert:
    """`encode(texts)` -> (n, hidden) float32 embeddings, L2-normalised, as sentence-transformers'
    `encode(..., normalize_embeddings=True)` gives them."""

    def __init__(self, folder: Path):
        from safetensors.torch import load_file
        from tokenizers import Tokenizer

        config = json.loads((folder / "config.json").read_text())
        settings_file = folder / "sentence_bert_config.json"
        settings = json.loads(settings_file.read_text()) if settings_file.exists() else {}
        self.weights = load_file(str(folder / "model.safetensors"))
        self.layers, self.heads = config["num_hidden_layers"], config["num_attention_heads"]
        self.eps = config["layer_norm_eps"]
        self.tokenizer = Tokenizer.from_file(str(folder / "tokenizer.json"))
        self.tokenizer.enable_truncation(int(settings.get("max_seq_length") or MAX_TOKENS))
        self.tokenizer.enable_padding(pad_id=config.get("pad_token_id", 0))  # to the batch's longest

    def _norm(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return F.layer_norm(x, x.shape[-1:], self.weights[f"{name}.weight"], self.weights[f"{name}.bias"], self.eps)

    def _linear(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return F.linear(x, self.weights[f"{name}.weight"], self.weights[f"{name}.bias"])

    def _forward(self, ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        w, (n, length) = self.weights, ids.shape
        x = (w["embeddings.word_embeddings.weight"][ids] + w["embeddings.position_embeddings.weight"][:length]
             + w["embeddings.token_type_embeddings.weight"][0])
        x = self._norm(x, "embeddings.LayerNorm")
        # padding keys get the most negative float, as transformers' BERT masks them
        bias = torch.zeros(n, 1, 1, length).masked_fill(mask[:, None, None, :] == 0, torch.finfo(torch.float32).min)
        for i in range(self.layers):
            layer = f"encoder.layer.{i}"
            q, k, v = (self._linear(x, f"{layer}.attention.self.{part}").view(n, length, self.heads, -1).transpose(1, 2)
                       for part in ("query", "key", "value"))
            attended = F.scaled_dot_product_attention(q, k, v, attn_mask=bias).transpose(1, 2).reshape(n, length, -1)
            x = self._norm(self._linear(attended, f"{layer}.attention.output.dense") + x,
                           f"{layer}.attention.output.LayerNorm")
            hidden = F.gelu(self._linear(x, f"{layer}.intermediate.dense"))
            x = self._norm(self._linear(hidden, f"{layer}.output.dense") + x, f"{layer}.output.LayerNorm")
        weights = mask[..., None].to(x.dtype)  # mean over the real tokens
        return F.normalize((x * weights).sum(1) / weights.sum(1).clamp(min=1e-9), dim=1)

    def encode(self, texts: list[str]) -> np.ndarray:
        out = []
        with torch.inference_mode():
            for start in range(0, len(texts), BATCH):
                batch = self.tokenizer.encode_batch(texts[start:start + BATCH])
                ids = torch.tensor([b.ids for b in batch], dtype=torch.long)
                mask = torch.tensor([b.attention_mask for b in batch], dtype=torch.long)
                out.append(self._forward(ids, mask))
        hidden = self.weights["embeddings.word_embeddings.weight"].shape[1]
        return torch.cat(out).numpy().astype(np.float32) if out else np.zeros((0, hidden), np.float32)
