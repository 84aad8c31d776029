"""The trained policy as evaluation and redeployment use it: raw observation in, action out."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from policies.model import ModelDims, VLAModel
from schemas.config import ModelConfig


@dataclass
class Normaliser:
    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, values: np.ndarray) -> Normaliser:
        return cls(values.mean(0).astype(np.float32), np.maximum(values.std(0), 1e-3).astype(np.float32))

    def encode(self, values: np.ndarray) -> np.ndarray:
        return ((values - self.mean) / self.std).astype(np.float32)

    def decode(self, values: np.ndarray) -> np.ndarray:
        return values * self.std + self.mean


def save_checkpoint(path: Path, model: VLAModel, action: Normaliser, proprio: Normaliser, encoder: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "model_config": model.config.model_dump(),
            "dims": model.dims_dict(),
            "state_dict": model.state_dict(),
            "action": (action.mean, action.std),
            "proprio": (proprio.mean, proprio.std),
            "language_encoder": encoder,
        },
        tmp,
    )
    tmp.replace(path)


class Policy:
    def __init__(self, model: VLAModel, action: Normaliser, proprio: Normaliser, language_encoder: str):
        self.model = model.eval()
        self.action, self.proprio = action, proprio
        self.language_encoder = language_encoder

    @classmethod
    def load(cls, path: Path) -> Policy:
        state = torch.load(path, map_location="cpu", weights_only=False)
        model = VLAModel(ModelConfig(**state["model_config"]), ModelDims(**state["dims"]))
        model.load_state_dict(state["state_dict"])
        return cls(model, Normaliser(*state["action"]), Normaliser(*state["proprio"]), state["language_encoder"])

    @torch.no_grad()
    def act(self, image: np.ndarray, proprio: np.ndarray, instruction_embedding: np.ndarray) -> np.ndarray:
        """Mean action for one (H, W, 3) uint8 frame; clipped to the action bounds."""
        pixels = torch.from_numpy(image).permute(2, 0, 1).unsqueeze(0).float() / 255.0
        _, mu, _ = self.model(
            pixels,
            torch.from_numpy(instruction_embedding).unsqueeze(0),
            torch.from_numpy(self.proprio.encode(proprio)).unsqueeze(0),
        )
        return np.clip(self.action.decode(mu[0].numpy()), -1.0, 1.0)
