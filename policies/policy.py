"""The trained policy as evaluation, exploration and the MLflow model use it: a raw observation
and an instruction in, an action and the policy's uncertainty about it out."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from envs.observation import DISCRETE_FAMILIES, Observation
from policies.model import ModelDims, VLAModel, pixels, uncertainty
from schemas.config import ModelConfig


@dataclass
class Normaliser:
    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, values: np.ndarray, width: int) -> Normaliser:
        """Per-component statistics; the identity when there are no values (e.g. no continuous actions)."""
        if len(values) == 0:
            return cls(np.zeros(width, np.float32), np.ones(width, np.float32))
        return cls(values.mean(0).astype(np.float32), np.maximum(values.std(0), 1e-3).astype(np.float32))

    def encode(self, values: np.ndarray) -> np.ndarray:
        return ((values - self.mean) / self.std).astype(np.float32)

    def decode(self, values: np.ndarray) -> np.ndarray:
        return values * self.std + self.mean


def policy_state(model: VLAModel, action: Normaliser, proprio: Normaliser) -> dict:
    """What a policy checkpoint holds: enough to rebuild the model without the config or warehouse."""
    return {
        "model_config": model.config.model_dump(),
        "dims": model.dims_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "action": (action.mean, action.std),
        "proprio": (proprio.mean, proprio.std),
    }


def save_atomically(path: Path, state: dict) -> None:
    """Whole or not at all: a kill while saving leaves the previous file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


@dataclass
class Decision:
    action: np.ndarray  # what the environment steps with: continuous components, or [index]
    uncertainty: float  # entropy (discrete) or log det Sigma (continuous), policies.model.uncertainty


class Policy:
    def __init__(
        self, model: VLAModel, action: Normaliser, proprio: Normaliser, embeddings: dict[str, np.ndarray] | None = None
    ):
        self.model = model.eval()
        self.action, self.proprio = action, proprio
        self._embeddings: dict[str, torch.Tensor] = {
            text: torch.as_tensor(vector).unsqueeze(0) for text, vector in (embeddings or {}).items()
        }

    @classmethod
    def load(cls, path: Path, embeddings: dict[str, np.ndarray] | None = None) -> Policy:
        """`embeddings`: the frozen encoder's, per instruction, as the warehouse caches them; an
        instruction without one is encoded on first use."""
        state = torch.load(path, map_location="cpu", weights_only=False)
        model = VLAModel(ModelConfig(**state["model_config"]), ModelDims(**state["dims"]))
        model.load_state_dict(state["state_dict"])
        return cls(model, Normaliser(*state["action"]), Normaliser(*state["proprio"]), embeddings)

    @property
    def language_encoder(self) -> str:
        return self.model.config.language_encoder

    def _embedding(self, instruction: str) -> torch.Tensor:
        if instruction not in self._embeddings:
            if self.model.text is not None:
                self._embeddings[instruction] = self.model.text([instruction])
            else:
                from policies.language import encode

                self._embeddings[instruction] = torch.from_numpy(encode(self.language_encoder, [instruction]))
        return self._embeddings[instruction]

    @torch.no_grad()
    def act(self, obs: Observation, instruction: str, family: str) -> Decision:
        """For one observation (its frame, depth map if the model reads RGB-D, and proprio): the
        Gaussian's mean (clipped to the action bounds) or the most likely discrete action."""
        # copies: frames decoded from the warehouse are read-only buffers, which torch warns about sharing
        depth = None if self.model.dims.channels == 3 or obs.depth is None else torch.tensor(obs.depth)[None]
        image = pixels(torch.tensor(obs.image)[None], depth)
        proprio = torch.from_numpy(self.proprio.encode(obs.proprio)).unsqueeze(0)
        output = self.model(image, self._embedding(instruction), proprio)
        discrete = family in DISCRETE_FAMILIES
        if discrete:
            action = np.array([output.logits[0].argmax().item()], dtype=np.float32)
        else:
            action = np.clip(self.action.decode(output.mu[0].numpy()), -1.0, 1.0).astype(np.float32)
        return Decision(action, float(uncertainty(output, discrete)[0]))
