"""The VLA model of the proposal: a vision encoder (ViT, or ResNet-18 for the ablation), a
pretrained language encoder (frozen: its cached embedding; or fine-tuned inside the model), a
cross-modal fusion transformer giving z_ol, a Gaussian head over continuous actions, a softmax
head over discrete ones, an action encoder giving z_a, and lambda*InfoNCE + (1-lambda)*BC; plus,
for training only, a head predicting the simulator state from z_ol and its weighted error.

Actions come in two kinds, told apart per sample by `action_index`: -1 for a continuous action
(manipulation: ACTION_DIM normalised components in `action`), else the index of a discrete
action (navigation). One model trains on both.

With `config.chunk` = k > 1 the heads predict a chunk: this step's action and the next k-1 of the
episode (ACT, Zhao et al. 2023; Diffusion Policy, Chi et al. 2023), and z_a embeds the whole chunk;
targets then come as (B, k, ...) with a mask of the positions the episode still has.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from envs.observation import ACTION_COMPONENTS
from schemas.config import ModelConfig

LOG_STD_RANGE = (-5.0, 2.0)
# An RGB-D model's fourth channel is inverse depth, min(1, NEAR / depth): it keeps resolution where
# the work is (tabletop cameras see 0.5-2 m: 1 to 0.25) and needs no far limit (rooms; 0: nothing hit).
INVERSE_DEPTH_NEAR_M = 0.5


@dataclass(frozen=True)
class ModelDims:
    image_size: int
    proprio_dim: int
    action_dim: int  # continuous components
    discrete_actions: int  # size of the discrete action set
    language_dim: int
    channels: int = 3  # 4: RGB-D, for campaigns that record depth (render.depth)
    state_dim: int = 0  # the simulator state the auxiliary head predicts (train.state_weight); 0: no head
    views: int = 1  # square camera views side by side in a frame: 2 with the hand's camera (render.wrist_camera)


@dataclass
class ModelOutput:
    z_ol: torch.Tensor  # (B, dim) joint observation-language embedding
    chunk_mu: torch.Tensor  # (B, chunk, action_dim) Gaussian means, normalised units, this step's first
    chunk_log_std: torch.Tensor  # (B, chunk, action_dim) diagonal: Sigma = diag(exp(2 log_std))
    chunk_logits: torch.Tensor  # (B, chunk, discrete_actions)
    state: torch.Tensor | None = None  # (B, state_dim) the simulator state, normalised; models with the head

    @property
    def mu(self) -> torch.Tensor:
        """(B, action_dim): this step's action."""
        return self.chunk_mu[:, 0]

    @property
    def log_std(self) -> torch.Tensor:
        return self.chunk_log_std[:, 0]

    @property
    def logits(self) -> torch.Tensor:
        return self.chunk_logits[:, 0]


def _transformer(dim: int, depth: int, heads: int) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(dim, heads, dim_feedforward=4 * dim, dropout=0.0, batch_first=True, norm_first=True)
    return nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)


def split_views(image: torch.Tensor, views: int) -> torch.Tensor:
    """(B, C, H, views*H) frames -> (B*views, C, H, H): each square view its own image, a frame's views adjacent."""
    if views == 1:
        return image
    return image.unflatten(3, (views, image.shape[2])).permute(0, 3, 1, 2, 4).flatten(0, 1)


def join_views(image: torch.Tensor, views: int) -> torch.Tensor:
    """The inverse of `split_views`."""
    if views == 1:
        return image
    return image.unflatten(0, (-1, views)).permute(0, 2, 3, 1, 4).flatten(3, 4)


def pixels(image: torch.Tensor, depth: torch.Tensor | None = None) -> torch.Tensor:
    """The vision input (B, C, H, W) in [0, 1]: uint8 frames (B, H, W, 3), and for an RGB-D model
    their depth maps (B, H, W) in metres as a fourth channel of inverse depth."""
    rgb = image.permute(0, 3, 1, 2).float().div_(255.0)
    if depth is None:
        return rgb
    inverse = torch.where(depth > 0, INVERSE_DEPTH_NEAR_M / depth.float().clamp_min(1e-6), 0.0).clamp_max(1.0)
    return torch.cat([rgb, inverse.unsqueeze(1)], dim=1)


class ViTEncoder(nn.Module):
    """Patch embedding + learned positions + transformer: (B, C, H, W) in [0, 1] -> (B, patches, dim)."""

    def __init__(self, image_size: int, patch_size: int, dim: int, depth: int, heads: int, channels: int = 3):
        super().__init__()
        if image_size % patch_size:
            raise ValueError(f"train.model.patch_size: {patch_size} does not divide render.image_size {image_size}")
        patches = (image_size // patch_size) ** 2
        self.patchify = nn.Conv2d(channels, dim, kernel_size=patch_size, stride=patch_size)
        self.position = nn.Parameter(torch.randn(1, patches, dim) * 0.02)
        self.blocks = _transformer(dim, depth, heads)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        tokens = self.patchify(image * 2.0 - 1.0).flatten(2).transpose(1, 2)
        return self.blocks(tokens + self.position)


class _BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(out)) + self.shortcut(x))


class SpatialSoftmax(nn.Module):
    """Keypoints (Levine et al. 2016): for each channel of a learned 1x1 projection of a feature map,
    the softmax-weighted mean image position, in [-1, 1]: where a feature is, to a fraction of a cell,
    and differences of keypoints survive a shifted frame. (B, C, H, W) -> (B, keypoints, 2) as (x, y)."""

    def __init__(self, channels: int, keypoints: int, height: int, width: int):
        super().__init__()
        self.project = nn.Conv2d(channels, keypoints, 1)
        self.log_temperature = nn.Parameter(torch.zeros(()))
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.flatten(), ys.flatten()], -1), persistent=False)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        weights = (self.project(features).flatten(2).float() / self.log_temperature.exp()).softmax(-1)
        return (weights @ self.grid).to(features.dtype)


# Keypoints come from the feature map after this many ResNet stages (stride 8: 11x11 cells at 84 px),
# fine enough to place a 4 px object; the last stage's 32 px cells are not.
KEYPOINT_STAGE = 2


class ResNet18Encoder(nn.Module):
    """ResNet-18 (He et al. 2016: stem, four stages of two basic blocks) at a chosen width, from
    scratch; its last feature map becomes tokens, plus one token of `keypoints` spatial-softmax
    keypoints where asked: (B, C, H, W) in [0, 1] -> (B, tokens, dim)."""

    def __init__(self, image_size: int, width: int, dim: int, keypoints: int = 0, in_channels: int = 3):
        super().__init__()
        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, width, 7, 2, 3, bias=False), nn.BatchNorm2d(width), nn.ReLU(), nn.MaxPool2d(3, 2, 1),
        ]
        channels = width
        for stage, stride in enumerate((1, 2, 2, 2)):
            out = width * 2**stage
            layers += [_BasicBlock(channels, out, stride), _BasicBlock(out, out, 1)]
            channels = out
        self.features = nn.Sequential(*layers, nn.Conv2d(channels, dim, 1))
        self.tap = 4 + 2 * KEYPOINT_STAGE  # layers up to the keypoints' feature map: stem, two blocks a stage
        with torch.no_grad():
            probe = torch.zeros(1, in_channels, image_size, image_size)
            tapped = self.features[: self.tap](probe)
            cells = self.features[self.tap:](tapped).flatten(2).shape[-1]
        self.position = nn.Parameter(torch.randn(1, cells, dim) * 0.02)
        self.keypoints = nn.Sequential(  # the keypoints' (x, y), all of them, as one token
            SpatialSoftmax(tapped.shape[1], keypoints, *tapped.shape[2:]), nn.Flatten(), nn.Linear(2 * keypoints, dim)
        ) if keypoints else None

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        tapped = self.features[: self.tap](image * 2.0 - 1.0)
        tokens = self.features[self.tap:](tapped).flatten(2).transpose(1, 2) + self.position
        if self.keypoints is None:
            return tokens
        return torch.cat([tokens, self.keypoints(tapped).unsqueeze(1)], dim=1)


class HybridViTEncoder(nn.Module):
    """ViT-hybrid (Dosovitskiy et al. 2021, section 3.1): the transformer's patches are the cells of a
    ResNet-18 trunk's feature map instead of linearly embedded pixels -> (B, cells, dim)."""

    def __init__(self, stem: ResNet18Encoder, dim: int, depth: int, heads: int):
        super().__init__()
        self.stem = stem
        self.blocks = _transformer(dim, depth, heads)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.blocks(self.stem(image))


def vision_encoder(config: ModelConfig, image_size: int, channels: int = 3) -> nn.Module:
    if config.vision == "vit":
        return ViTEncoder(image_size, config.patch_size, config.dim, config.vision_depth, config.heads, channels)
    trunk = ResNet18Encoder(image_size, config.resnet_width, config.dim, config.keypoints, channels)
    if config.vision == "hybrid":
        return HybridViTEncoder(trunk, config.dim, config.vision_depth, config.heads)
    return trunk


class VLAModel(nn.Module):
    def __init__(self, config: ModelConfig, dims: ModelDims):
        super().__init__()
        self.config, self.dims = config, dims
        d = config.dim
        self.vision = vision_encoder(config, dims.image_size, dims.channels)
        # the hand's view (render.wrist_camera) through an encoder of its own, as robomimic gives each camera one;
        # its tokens and the main view's told apart by a learnt embedding (absent with one view: old checkpoints load)
        self.wrist_vision = vision_encoder(config, dims.image_size, dims.channels) if dims.views == 2 else None
        self.view = nn.Parameter(torch.randn(dims.views, d) * 0.02) if dims.views > 1 else None
        if config.language_trainable:
            from policies.language import TextEncoder

            self.text = TextEncoder(config.language_encoder)
        else:
            self.text = None
        self.language = nn.Linear(dims.language_dim, d)
        self.proprio = nn.Linear(dims.proprio_dim, d)
        self.cls = nn.Parameter(torch.zeros(1, 1, d))
        self.modality = nn.Parameter(torch.randn(4, d) * 0.02)  # cls, language, proprio, vision
        self.fusion = _transformer(d, config.fusion_depth, config.heads)
        self.norm = nn.LayerNorm(d)
        k = self.chunk = config.chunk
        self.mu = nn.Linear(d, k * dims.action_dim)
        self.log_std = nn.Linear(d, k * dims.action_dim)
        self.logits = nn.Linear(d, k * dims.discrete_actions)
        self.state = nn.Linear(d, dims.state_dim) if dims.state_dim else None  # a training aid, unread when acting
        self.action_encoder = nn.Sequential(nn.Linear(k * dims.action_dim, d), nn.GELU(), nn.Linear(d, d))
        self.discrete_action_encoder = nn.Embedding(dims.discrete_actions, d)
        # a chunk of discrete actions: its k embeddings, in order, projected to one (absent at k = 1: old checkpoints load)
        self.discrete_chunk_projection = nn.Linear(k * d, d) if k > 1 else None
        self.joint_projection = nn.Linear(d, d)

    def language_input(self, instructions: list[str], cached: torch.Tensor | None) -> torch.Tensor:
        """The instruction embeddings the model reads: its own encoder's when fine-tuned, else the
        frozen encoder's cached ones."""
        if self.text is not None:
            return self.text(instructions)
        if cached is None:
            raise ValueError("a model with a frozen language encoder needs the cached instruction embeddings")
        return cached

    def forward(self, image: torch.Tensor, language: torch.Tensor, proprio: torch.Tensor) -> ModelOutput:
        """image (B, C, H, W) in [0, 1] (`pixels`; W = views * H); language (B, language_dim); proprio normalised."""
        if image.shape[1] != self.dims.channels:
            kind = "RGB-D (a campaign with render.depth)" if self.dims.channels == 4 else "RGB"
            raise ValueError(f"this model reads {kind} frames, got {image.shape[1]} channels")
        if image.shape[3] != self.dims.views * image.shape[2]:
            raise ValueError(f"this model reads frames of {self.dims.views} square view(s) side by side "
                             f"(render.wrist_camera), got {image.shape[2]}x{image.shape[3]}")
        batch = image.shape[0]
        tokens = torch.cat(
            [
                self.cls.expand(batch, -1, -1) + self.modality[0],
                (self.language(language) + self.modality[1]).unsqueeze(1),
                (self.proprio(proprio) + self.modality[2]).unsqueeze(1),
                self.vision_tokens(image) + self.modality[3],
            ],
            dim=1,
        )
        joint = self.norm(self.fusion(tokens)[:, 0])
        return ModelOutput(
            z_ol=self.joint_projection(joint),
            chunk_mu=self.mu(joint).unflatten(-1, (self.chunk, -1)),
            chunk_log_std=self.log_std(joint).clamp(*LOG_STD_RANGE).unflatten(-1, (self.chunk, -1)),
            chunk_logits=self.logits(joint).unflatten(-1, (self.chunk, -1)),
            state=None if self.state is None else self.state(joint),
        )

    def vision_tokens(self, image: torch.Tensor) -> torch.Tensor:
        """(B, tokens, dim): the main view's tokens, then the hand's, each marked with its view."""
        if self.wrist_vision is None:
            return self.vision(image)
        main, wrist = image.chunk(2, dim=3)
        return torch.cat([self.vision(main) + self.view[0], self.wrist_vision(wrist) + self.view[1]], dim=1)

    def encode_action(self, action: torch.Tensor, action_index: torch.Tensor) -> torch.Tensor:
        """z_a: continuous actions (B, k, action_dim) through an MLP, discrete ones (B, k) through an
        embedding (a chunk's k embeddings projected to one); a single step's (B, action_dim), (B,) too."""
        action, action_index = action.reshape(len(action), self.chunk, -1), action_index.reshape(len(action), self.chunk)
        embedded = self.discrete_action_encoder(action_index.clamp(min=0))  # (B, k, d)
        embedded = embedded[:, 0] if self.discrete_chunk_projection is None else \
            self.discrete_chunk_projection(embedded.flatten(1))
        discrete = (action_index[:, 0] >= 0).unsqueeze(-1)
        return torch.where(discrete, embedded, self.action_encoder(action.flatten(1)))

    def dims_dict(self) -> dict[str, int]:
        return asdict(self.dims)


def mean_probabilities(outputs: Sequence[ModelOutput]) -> torch.Tensor:
    """The members' mean probabilities over discrete actions: what an ensemble picks from, and whose
    entropy is its uncertainty."""
    return torch.stack([o.logits.float().softmax(-1) for o in outputs]).mean(0)


def uncertainty(outputs: Sequence[ModelOutput], discrete: bool) -> torch.Tensor:
    """Per sample, of the members' mixture (one member: the model alone): the entropy of their mean
    probabilities over discrete actions (nats), or log det of the mixture's diagonal covariance,
    the members' mean Sigma plus the spread of their mu (the law of total variance: ensemble
    disagreement), for continuous ones (normalised units). Higher: less sure."""
    if discrete:
        probabilities = mean_probabilities(outputs)
        return -(probabilities * probabilities.clamp_min(1e-12).log()).sum(-1)
    mu = torch.stack([o.mu.float() for o in outputs])
    variance = torch.stack([(2.0 * o.log_std.float()).exp() for o in outputs]).mean(0) + mu.var(0, unbiased=False)
    return variance.log().sum(-1)


def info_nce(z_ol: torch.Tensor, z_a: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE: each (observation, language) embedding should pick out its own action."""
    logits = F.normalize(z_ol.float(), dim=-1) @ F.normalize(z_a.float(), dim=-1).T / temperature
    targets = torch.arange(len(logits), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, targets) + F.cross_entropy(logits.T, targets))


@dataclass
class Losses:
    total: torch.Tensor
    terms: dict[str, torch.Tensor]  # detached, each a mean over `counts[name]` samples
    counts: dict[str, int]


def vla_loss(
    model: VLAModel,
    image: torch.Tensor,
    language: torch.Tensor,
    proprio: torch.Tensor,
    action: torch.Tensor,
    action_index: torch.Tensor,
    contrastive_weight: float,
    temperature: float,
    state: tuple[torch.Tensor, torch.Tensor] | None = None,
    state_weight: float = 0.0,
    action_mask: torch.Tensor | None = None,
) -> Losses:
    """lambda * InfoNCE(z_ol, z_a) + (1 - lambda) * BC, BC per sample: for continuous actions the
    squared error of mu plus the Gaussian NLL, for discrete ones the cross-entropy; of a chunked
    model, the mean over the chunk's positions `action_mask` marks as the episode's (targets
    (B, k, action_dim) and (B, k); a single step's (B, action_dim) and (B,) where k = 1). With `state`
    (normalised simulator states (B, state_dim) and the mask of the components each sample has),
    plus state_weight * the state head's squared error over those components. The action error
    metrics are of this step's action (position 0), comparable across chunk sizes."""
    out = model(image, language, proprio)
    batch, k = len(action), model.chunk
    action, action_index = action.reshape(batch, k, -1), action_index.reshape(batch, k)
    mask = torch.ones(batch, k, device=action.device) if action_mask is None else action_mask.reshape(batch, k).float()
    contrastive = info_nce(out.z_ol, model.encode_action(action, action_index), temperature)
    discrete = action_index[:, 0] >= 0
    mu, log_std = out.chunk_mu.float(), out.chunk_log_std.float()
    # mu learns from the squared error and Sigma from the NLL around a detached mu: trained jointly,
    # the NLL shrinks Sigma on easy dimensions faster than it fits mu, and mu barely moves.
    squared = (mu - action) ** 2  # (B, k, A)
    mse = squared.mean(-1)
    nll = (0.5 * ((action - mu.detach()) / log_std.exp()) ** 2 + log_std).sum(-1)
    cross_entropy = F.cross_entropy(out.chunk_logits.float().flatten(0, 1), action_index.clamp(min=0).flatten(),
                                    reduction="none").view(batch, k)
    per_position = torch.where(discrete[:, None], cross_entropy, mse + nll)
    bc = ((per_position * mask).sum(1) / mask.sum(1).clamp_min(1)).mean()
    total = contrastive_weight * contrastive + (1.0 - contrastive_weight) * bc
    n, n_discrete = batch, int(discrete.sum())
    terms = {"loss": total, "infonce": contrastive, "bc": bc}
    counts = {"loss": n, "infonce": n, "bc": n}
    if n_discrete < n:
        continuous = ~discrete
        terms.update(action_mse=mse[continuous, 0].mean(), bc_nll=nll[continuous, 0].mean())
        counts.update(action_mse=n - n_discrete, bc_nll=n - n_discrete)
        # Per component, in normalised units (about 1 - R^2 over the selection): a training that never learns
        # one component (the lateral dy of a small cube, in half the seeds) hides in the mean of seven.
        for name, error in zip(ACTION_COMPONENTS, squared[continuous, 0].mean(0)):
            terms[f"action_mse_{name}"], counts[f"action_mse_{name}"] = error, n - n_discrete
        if k > 1:  # over the whole chunk, the positions the episodes have
            weights = mask[continuous]
            terms["action_mse_chunk"] = (mse[continuous] * weights).sum() / weights.sum().clamp_min(1)
            counts["action_mse_chunk"] = n - n_discrete
    if state is not None and out.state is not None:
        target, present = state
        # scenes differ in state length: a sample's missing components are padding, left out
        state_mse = (((out.state.float() - target) ** 2) * present).sum() / present.sum().clamp_min(1)
        total = total + state_weight * state_mse
        terms["state_mse"], counts["state_mse"] = state_mse, n
    if n_discrete:
        hit = (out.logits.argmax(-1) == action_index[:, 0])[discrete].float()
        terms.update(discrete_ce=cross_entropy[discrete, 0].mean(), discrete_accuracy=hit.mean())
        counts.update(discrete_ce=n_discrete, discrete_accuracy=n_discrete)
    terms["loss"] = total  # with the state term where there is one
    return Losses(total, {k: v.detach() for k, v in terms.items()}, counts)
