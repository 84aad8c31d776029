"""The VLA model of the proposal: ViT vision encoder, pretrained language embedding, cross-modal
fusion transformer, a Gaussian action head, an action encoder, and lambda*InfoNCE + (1-lambda)*BC."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from schemas.config import ModelConfig

LOG_STD_RANGE = (-5.0, 2.0)


@dataclass(frozen=True)
class ModelDims:
    image_size: int
    proprio_dim: int
    action_dim: int
    language_dim: int


def _transformer(dim: int, depth: int, heads: int) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(dim, heads, dim_feedforward=4 * dim, dropout=0.0, batch_first=True, norm_first=True)
    return nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)


class ViTEncoder(nn.Module):
    """Patch embedding + learned positions + transformer: (B, 3, H, W) in [0, 1] -> (B, patches, dim)."""

    def __init__(self, image_size: int, patch_size: int, dim: int, depth: int, heads: int):
        super().__init__()
        if image_size % patch_size:
            raise ValueError(f"image_size {image_size} is not a multiple of patch_size {patch_size}")
        patches = (image_size // patch_size) ** 2
        self.patchify = nn.Conv2d(3, dim, kernel_size=patch_size, stride=patch_size)
        self.position = nn.Parameter(torch.randn(1, patches, dim) * 0.02)
        self.blocks = _transformer(dim, depth, heads)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        tokens = self.patchify(image * 2.0 - 1.0).flatten(2).transpose(1, 2)
        return self.blocks(tokens + self.position)


class VLAModel(nn.Module):
    def __init__(self, config: ModelConfig, dims: ModelDims):
        super().__init__()
        self.config, self.dims = config, dims
        d = config.dim
        self.vision = ViTEncoder(dims.image_size, config.patch_size, d, config.vision_depth, config.heads)
        self.language = nn.Linear(dims.language_dim, d)
        self.proprio = nn.Linear(dims.proprio_dim, d)
        self.cls = nn.Parameter(torch.zeros(1, 1, d))
        self.modality = nn.Parameter(torch.randn(4, d) * 0.02)  # cls, language, proprio, vision
        self.fusion = _transformer(d, config.fusion_depth, config.heads)
        self.norm = nn.LayerNorm(d)
        self.mu = nn.Linear(d, dims.action_dim)
        self.log_std = nn.Linear(d, dims.action_dim)
        self.action_encoder = nn.Sequential(nn.Linear(dims.action_dim, d), nn.GELU(), nn.Linear(d, d))
        self.joint_projection = nn.Linear(d, d)

    def forward(
        self, image: torch.Tensor, language: torch.Tensor, proprio: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """-> (z_ol, mu, log_std); actions are in normalised units."""
        batch = image.shape[0]
        tokens = torch.cat(
            [
                self.cls.expand(batch, -1, -1) + self.modality[0],
                (self.language(language) + self.modality[1]).unsqueeze(1),
                (self.proprio(proprio) + self.modality[2]).unsqueeze(1),
                self.vision(image) + self.modality[3],
            ],
            dim=1,
        )
        joint = self.norm(self.fusion(tokens)[:, 0])
        log_std = self.log_std(joint).clamp(*LOG_STD_RANGE)
        return self.joint_projection(joint), self.mu(joint), log_std

    def dims_dict(self) -> dict[str, int]:
        return asdict(self.dims)


def info_nce(z_ol: torch.Tensor, z_a: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE: each (observation, language) embedding should pick out its own action."""
    logits = F.normalize(z_ol, dim=-1) @ F.normalize(z_a, dim=-1).T / temperature
    targets = torch.arange(len(logits), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, targets) + F.cross_entropy(logits.T, targets))


def gaussian_nll(action: torch.Tensor, mu: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    return (0.5 * ((action - mu) / log_std.exp()) ** 2 + log_std).sum(-1).mean()


def vla_loss(
    model: VLAModel,
    image: torch.Tensor,
    language: torch.Tensor,
    proprio: torch.Tensor,
    action: torch.Tensor,
    contrastive_weight: float,
    temperature: float,
) -> dict[str, torch.Tensor]:
    z_ol, mu, log_std = model(image, language, proprio)
    contrastive = info_nce(z_ol, model.action_encoder(action), temperature)
    # mu learns from the squared error and Sigma from the NLL around a detached mu: trained jointly,
    # the NLL shrinks Sigma on easy dimensions faster than it fits mu, and mu barely moves.
    mse = F.mse_loss(mu, action)
    nll = gaussian_nll(action, mu.detach(), log_std)
    bc = mse + nll
    total = contrastive_weight * contrastive + (1.0 - contrastive_weight) * bc
    return {"loss": total, "infonce": contrastive, "bc": bc, "bc_nll": nll, "action_mse": mse}
