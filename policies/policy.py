"""The trained policy as evaluation, exploration and the MLflow model use it: a raw observation
and an instruction in, an action and the policy's uncertainty about it out."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from envs.observation import DISCRETE_FAMILIES, Observation
from policies.model import ModelDims, VLAModel, mean_probabilities, pixels, uncertainty
from schemas.config import ModelConfig


@dataclass
class Normaliser:
    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, values: np.ndarray, width: int) -> Normaliser:
        """Per-component statistics over the values each component has (NaN: none); the identity when
        there are no values (e.g. no continuous actions)."""
        if len(values) == 0:
            return cls(np.zeros(width, np.float32), np.ones(width, np.float32))
        return cls(np.nanmean(values, 0).astype(np.float32), np.maximum(np.nanstd(values, 0), 1e-3).astype(np.float32))

    def encode(self, values: np.ndarray) -> np.ndarray:
        return ((values - self.mean) / self.std).astype(np.float32)

    def decode(self, values: np.ndarray) -> np.ndarray:
        return values * self.std + self.mean


def policy_state(members: list[VLAModel], action: Normaliser, proprio: Normaliser) -> dict:
    """What a policy checkpoint holds: enough to rebuild the model, or the ensemble of models trained
    alike on the same data (train.ensemble), without the config or warehouse."""
    return {
        "model_config": members[0].config.model_dump(),
        "dims": members[0].dims_dict(),
        "members": [{k: v.detach().cpu() for k, v in model.state_dict().items()} for model in members],
        "action": (action.mean, action.std),
        "proprio": (proprio.mean, proprio.std),
    }


def checkpoint_members(state: dict) -> list[dict]:
    """The members' weights; a checkpoint written before ensembles holds one model's as `state_dict`."""
    return state["members"] if "members" in state else [state["state_dict"]]


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
    """One model, or an ensemble whose members' means are averaged (their disagreement is part of
    the uncertainty: policies.model.uncertainty)."""

    def __init__(
        self, members: list[VLAModel], action: Normaliser, proprio: Normaliser,
        embeddings: dict[str, np.ndarray] | None = None,
    ):
        self.members = [model.eval() for model in members]
        self.action, self.proprio = action, proprio
        self._embeddings: dict[str, torch.Tensor] = {
            text: torch.as_tensor(vector).unsqueeze(0) for text, vector in (embeddings or {}).items()
        }
        self._fine_tuned: dict[tuple[int, str], torch.Tensor] = {}  # (member, instruction): its own encoder's

    @classmethod
    def load(cls, path: Path, embeddings: dict[str, np.ndarray] | None = None) -> Policy:
        """`embeddings`: the frozen encoder's, per instruction, as the warehouse caches them; an
        instruction without one is encoded on first use."""
        state = torch.load(path, map_location="cpu", weights_only=False)
        config, dims = ModelConfig(**state["model_config"]), ModelDims(**state["dims"])
        members = []
        for weights in checkpoint_members(state):
            model = VLAModel(config, dims)
            model.load_state_dict(weights)
            members.append(model)
        return cls(members, Normaliser(*state["action"]), Normaliser(*state["proprio"]), embeddings)

    @property
    def config(self) -> ModelConfig:
        return self.members[0].config

    @property
    def dims(self) -> ModelDims:
        return self.members[0].dims

    def _language(self, member: int, instruction: str) -> torch.Tensor:
        model = self.members[member]
        if model.text is not None:
            if (member, instruction) not in self._fine_tuned:
                self._fine_tuned[member, instruction] = model.text([instruction])
            return self._fine_tuned[member, instruction]
        if instruction not in self._embeddings:
            from policies.language import encode

            self._embeddings[instruction] = torch.from_numpy(encode(self.config.language_encoder, [instruction]))
        return self._embeddings[instruction]

    @torch.no_grad()
    def act(self, obs: Observation, instruction: str, family: str) -> Decision:
        """For one observation (its frame, depth map if the model reads RGB-D, and proprio): the
        members' mean Gaussian mean (clipped to the action bounds), or the discrete action their
        mean probabilities make most likely."""
        # copies: frames decoded from the warehouse are read-only buffers, which torch warns about sharing
        depth = None if self.dims.channels == 3 or obs.depth is None else torch.tensor(obs.depth)[None]
        image = pixels(torch.tensor(obs.image)[None], depth)
        proprio = torch.from_numpy(self.proprio.encode(obs.proprio)).unsqueeze(0)
        outputs = [model(image, self._language(i, instruction), proprio) for i, model in enumerate(self.members)]
        discrete = family in DISCRETE_FAMILIES
        if discrete:
            action = np.array([mean_probabilities(outputs)[0].argmax().item()], dtype=np.float32)
        else:
            mu = torch.stack([o.mu[0] for o in outputs]).mean(0)
            action = np.clip(self.action.decode(mu.numpy()), -1.0, 1.0).astype(np.float32)
        return Decision(action, float(uncertainty(outputs, discrete)[0]))
