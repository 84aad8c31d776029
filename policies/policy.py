"""The trained policy as evaluation, exploration and the MLflow model use it: a raw observation
and an instruction in, an action and the policy's uncertainty about it out."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from envs.observation import DISCRETE_FAMILIES, Observation
from policies.model import ModelDims, VLAModel, pixels, uncertainty
from schemas.config import MODEL_LEGACY_VALUES, Acting, ModelConfig

if TYPE_CHECKING:
    from policies.chunking import EpisodeActor


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


def _cpu(weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    # contiguous: a channels_last training (policies/precision.py) loads into any model
    return {k: v.detach().cpu().contiguous() for k, v in weights.items()}


def policy_state(members: list[VLAModel], action: Normaliser, proprio: Normaliser,
                 averages: list[dict[str, torch.Tensor]] | None = None, ema: float | None = None) -> dict:
    """What a policy checkpoint holds: enough to rebuild the model, or the ensemble of models trained
    alike on the same data (train.ensemble), without the config or warehouse. With `averages` (the
    members' moving averages of their weights, decay `ema`), `members` are the averages, what gets
    evaluated, registered and explores; the last weights are kept as `final_members`."""
    final = [_cpu(model.state_dict()) for model in members]
    return {
        "model_config": members[0].config.model_dump(),
        "dims": members[0].dims_dict(),
        "members": final if averages is None else [_cpu(weights) for weights in averages],
        "weights": "final" if averages is None else f"ema {ema}",
        **({} if averages is None else {"final_members": final}),
        "action": (action.mean, action.std),
        "proprio": (proprio.mean, proprio.std),
    }


WEIGHTS = ("registered", "final")  # which weights Policy.load reads: the checkpoint's own choice, or the last


def checkpoint_members(state: dict, weights: str = "registered") -> list[dict]:
    """The members' weights: the ones the checkpoint registers (the moving average where training kept
    one), or `final`, the last weights. A checkpoint written before ensembles holds one model's as `state_dict`."""
    if weights not in WEIGHTS:
        raise ValueError(f"weights: expected one of {', '.join(WEIGHTS)}, got {weights!r}")
    if weights == "final" and "final_members" in state:
        return state["final_members"]
    return state["members"] if "members" in state else [state["state_dict"]]


def model_config_of(state: dict) -> ModelConfig:
    """A checkpoint's model config; one from before a model field existed was trained as that field's legacy value."""
    return ModelConfig(**{**MODEL_LEGACY_VALUES, **state["model_config"]})


def weights_of(state: dict, weights: str = "registered") -> str:
    """What `checkpoint_members(state, weights)` are, in words: `ema 0.999` or `final`."""
    return "final" if weights == "final" else state.get("weights", "final")


def save_atomically(path: Path, state: dict) -> None:
    """Whole or not at all: a kill while saving leaves the previous file; the bytes are on the disk
    before the name is (a power cut after a rename of unflushed bytes leaves an empty file under it)."""
    from warehouse.store import fsync_path

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    fsync_path(tmp)
    tmp.replace(path)
    fsync_path(path.parent)


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
        self.weights = "final"  # which weights act, in words (Policy.load: "ema 0.999" where averaged)
        self._acting: ModelConfig | None = None  # the members' config acting otherwise (acting_as)

    @classmethod
    def load(cls, path: Path, embeddings: dict[str, np.ndarray] | None = None, weights: str = "registered") -> Policy:
        """`embeddings`: the frozen encoder's, per instruction, as the warehouse caches them; an
        instruction without one is encoded on first use. `weights`: `registered` (the moving average
        where training kept one) or `final` (checkpoint_members)."""
        state = torch.load(path, map_location="cpu", weights_only=False)
        config = model_config_of(state)
        dims = ModelDims(**state["dims"])
        members = []
        for member in checkpoint_members(state, weights):
            model = VLAModel(config, dims)
            model.load_state_dict(member)
            members.append(model)
        policy = cls(members, Normaliser(*state["action"]), Normaliser(*state["proprio"]), embeddings)
        policy.weights = weights_of(state, weights)
        return policy

    @property
    def config(self) -> ModelConfig:
        return self._acting or self.members[0].config

    def acting_as(self, acting: Acting) -> Policy:
        """This policy turning its chunks into actions as `acting` says (execution, execute_steps,
        ensemble_decay) instead of as it was trained to; the weights are the same.
        Raises ValueError where `acting` does not fit the model (execute_steps above its chunk)."""
        self._acting = acting.applied_to(self.members[0].config)
        return self

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
    def predict(self, obs: Observation, instruction: str, family: str) -> tuple[np.ndarray, float]:
        """For one observation (its frame, depth map if the model reads RGB-D, and proprio): the chunk
        the members predict, (chunk, action_dim) mean Gaussian means in normalised units or (chunk,
        discrete actions) mean probabilities, and the uncertainty of this step's action."""
        # copies: frames decoded from the warehouse are read-only buffers, which torch warns about sharing
        depth = None if self.dims.channels == 3 or obs.depth is None else torch.tensor(obs.depth)[None]
        image = pixels(torch.tensor(obs.image)[None], depth)
        proprio = torch.from_numpy(self.proprio.encode(obs.proprio)).unsqueeze(0)
        outputs = [model(image, self._language(i, instruction), proprio) for i, model in enumerate(self.members)]
        discrete = family in DISCRETE_FAMILIES
        if discrete:
            chunk = torch.stack([o.chunk_logits[0].float().softmax(-1) for o in outputs]).mean(0)
        else:
            chunk = torch.stack([o.chunk_mu[0].float() for o in outputs]).mean(0)
        return chunk.numpy(), float(uncertainty(outputs, discrete)[0])

    def action_of(self, value: np.ndarray, family: str) -> np.ndarray:
        """What the environment steps with, from one chunk position's prediction: the most likely
        discrete action, or the Gaussian mean in the action's units, clipped to its bounds."""
        if family in DISCRETE_FAMILIES:
            return np.array([int(np.argmax(value))], dtype=np.float32)
        return np.clip(self.action.decode(value), -1.0, 1.0).astype(np.float32)

    def act(self, obs: Observation, instruction: str, family: str) -> Decision:
        """This step's action alone: the members' mean Gaussian mean (clipped to the action bounds),
        or the discrete action their mean probabilities make most likely. Stateless; an episode of a
        chunked policy acts through `episode()`."""
        chunk, unsure = self.predict(obs, instruction, family)
        return Decision(self.action_of(chunk[0], family), unsure)

    def episode(self, family: str) -> EpisodeActor:
        """A fresh actor for one episode: it keeps the chunks predicted so far (policies/chunking.py)."""
        from policies.chunking import EpisodeActor

        return EpisodeActor(self, family)
