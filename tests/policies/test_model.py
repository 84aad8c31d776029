import math

import numpy as np
import pytest
import torch

from policies.model import ModelDims, ModelOutput, SpatialSoftmax, VLAModel, info_nce, uncertainty, vla_loss, vision_encoder
from schemas.config import ModelConfig

DIMS = ModelDims(image_size=84, proprio_dim=9, action_dim=7, discrete_actions=4, language_dim=384)
SMALL = ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=1)  # one action per sample: the batches below


def _batch(n: int = 16, discrete: int = 0):
    """n samples, the last `discrete` of them with a discrete action."""
    generator = torch.Generator().manual_seed(0)
    action = torch.randn(n, 7, generator=generator)
    index = torch.full((n,), -1, dtype=torch.long)
    if discrete:
        index[n - discrete:] = torch.arange(discrete) % 4
        action[n - discrete:] = 0.0
    return (
        torch.rand(n, 3, 84, 84, generator=generator),
        torch.randn(n, 384, generator=generator),
        torch.randn(n, 9, generator=generator),
        action,
        index,
    )


@pytest.mark.parametrize("vision", ["vit", "resnet18"])
def test_forward_shapes(vision):
    model = VLAModel(ModelConfig(dim=32, heads=4, vision=vision), DIMS)
    image, language, proprio, _, _ = _batch(5)
    out = model(image, language, proprio)
    assert out.z_ol.shape == (5, 32) and out.mu.shape == (5, 7) and out.log_std.shape == (5, 7)
    assert out.logits.shape == (5, 4)


def test_a_two_view_model_reads_each_view_with_its_own_encoder():
    """render.wrist_camera: frames (B, 3, H, 2H); the main view's tokens come from `vision`, the hand's
    from `wrist_vision`, each marked with its view; a one-view model keeps its parameters' names."""
    model = VLAModel(SMALL, ModelDims(**{**DIMS.__dict__, "views": 2})).eval()
    image, language, proprio, _, _ = _batch(3)
    frames = torch.cat([image, torch.rand(3, 3, 84, 84)], dim=3)
    with torch.no_grad():
        tokens = model.vision_tokens(frames)
        main = model.vision(frames[..., :84]) + model.view[0]
        assert torch.equal(tokens[:, : main.shape[1]], main)
        assert torch.equal(tokens[:, main.shape[1]:], model.wrist_vision(frames[..., 84:]) + model.view[1])
        assert model(frames, language, proprio).mu.shape == (3, 7)
        moved = frames.clone()
        moved[..., 84:] = torch.rand(3, 3, 84, 84)
        assert not torch.allclose(model(moved, language, proprio).mu, model(frames, language, proprio).mu)
    with pytest.raises(ValueError, match=r"reads frames of 2 square view\(s\) side by side .*got 84x84"):
        model(image, language, proprio)
    one_view = set(VLAModel(SMALL, DIMS).state_dict())
    assert not any(name.startswith(("wrist_vision", "view")) for name in one_view)
    assert one_view < set(model.state_dict())


def test_resnet18_has_the_paper_layout():
    model = VLAModel(ModelConfig(dim=32, heads=4, vision="resnet18", resnet_width=64, keypoints=0), DIMS)
    convs = [m for m in model.vision.features.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size != (1, 1)]
    assert len(convs) == 17  # the stem and 16 in the 8 basic blocks: 18 weight layers with the fc
    vision_parameters = sum(p.numel() for p in model.vision.parameters()) - 512 * 32 - 32 - model.vision.position.numel()
    assert abs(vision_parameters - 11.17e6) < 0.05e6  # torchvision's resnet18 less its fc layer


@pytest.mark.parametrize(("vision", "keypoints", "tokens"), [("hybrid", 0, 9), ("hybrid", 16, 10), ("resnet18", 8, 10)])
def test_keypoints_are_one_more_vision_token(vision, keypoints, tokens):
    encoder = vision_encoder(ModelConfig(dim=32, heads=4, vision=vision, keypoints=keypoints), 84)
    assert encoder(torch.rand(2, 3, 84, 84)).shape == (2, tokens, 32)


def test_spatial_softmax_finds_a_feature_where_it_is_and_follows_it():
    keypoints = SpatialSoftmax(channels=1, keypoints=1, height=11, width=11)
    with torch.no_grad():
        keypoints.project.weight.fill_(1.0), keypoints.project.bias.zero_(), keypoints.log_temperature.fill_(-3.0)

    def where(row: int, column: int) -> torch.Tensor:
        features = torch.zeros(1, 1, 11, 11)
        features[0, 0, row, column] = 1.0
        return keypoints(features)[0, 0]

    assert torch.allclose(where(5, 5), torch.zeros(2), atol=1e-3)  # the centre is (0, 0)
    assert torch.allclose(where(0, 10), torch.tensor([1.0, -1.0]), atol=1e-3)  # (x, y): right, top
    # a shifted feature moves its keypoint by as much: differences of keypoints survive a shifted frame
    assert torch.allclose(where(3, 7) - where(3, 4), torch.tensor([0.6, 0.0]), atol=1e-3)


def test_info_nce_prefers_matching_pairs():
    z = torch.randn(8, 16)
    assert info_nce(z, z, 0.1) < info_nce(z, torch.randn(8, 16), 0.1)


def test_loss_mixes_infonce_and_bc_by_lambda():
    torch.manual_seed(0)
    model = VLAModel(SMALL, DIMS)
    losses = vla_loss(model, *_batch(), contrastive_weight=0.25, temperature=0.1)
    t = losses.terms
    assert torch.allclose(losses.total.detach(), 0.25 * t["infonce"] + 0.75 * (t["action_mse"] + t["bc_nll"]))
    assert "discrete_ce" not in t and losses.counts["action_mse"] == 16


def test_bc_is_cross_entropy_for_discrete_samples_and_gaussian_for_continuous():
    torch.manual_seed(0)
    model = VLAModel(SMALL, DIMS)
    losses = vla_loss(model, *_batch(16, discrete=6), contrastive_weight=0.0, temperature=0.1)
    t, c = losses.terms, losses.counts
    assert c["discrete_ce"] == 6 and c["action_mse"] == 10
    expected = (6 * t["discrete_ce"] + 10 * (t["action_mse"] + t["bc_nll"])) / 16
    assert torch.allclose(losses.total.detach(), expected, atol=1e-5)


def test_action_error_is_reported_per_component_over_continuous_samples():
    torch.manual_seed(0)
    model = VLAModel(SMALL, DIMS).eval()
    image, language, proprio, _, index = _batch(16, discrete=6)
    with torch.no_grad():
        action = model(image, language, proprio).mu.clone()
    action[:, 1] += 2.0  # the lateral component alone is off, by 2 normalised units
    action[10:] = 0.0
    losses = vla_loss(model, image, language, proprio, action, index, contrastive_weight=0.0, temperature=0.1)
    t, c = losses.terms, losses.counts
    assert torch.isclose(t["action_mse_dy"], torch.tensor(4.0), atol=1e-4) and c["action_mse_dy"] == 10
    assert all(t[f"action_mse_{name}"] < 1e-8 for name in ("dx", "dz", "rx", "ry", "rz", "grip"))
    assert torch.isclose(t["action_mse"], t["action_mse_dy"] / 7)


def test_the_state_loss_counts_only_the_components_each_sample_has():
    torch.manual_seed(0)
    model = VLAModel(SMALL, ModelDims(**{**DIMS.__dict__, "state_dim": 5})).eval()
    image, language, proprio, action, index = _batch(4)
    with torch.no_grad():
        predicted = model(image, language, proprio).state
    present = torch.ones(4, 5)
    present[2:, 3:] = 0.0  # samples 2 and 3 come from a scene with a 3-component state
    target = predicted + 1.0
    target[2:, 3:] = 100.0  # padding: must not count
    batch = (image, language, proprio, action, index, 0.0, 0.1)
    plain = vla_loss(model, *batch)
    losses = vla_loss(model, *batch, state=(target, present), state_weight=0.5)
    assert torch.isclose(losses.terms["state_mse"], torch.tensor(1.0), atol=1e-5)
    assert torch.isclose(losses.total, plain.total + 0.5, atol=1e-5)
    assert "state_mse" not in plain.terms
    assert VLAModel(SMALL, DIMS)(image, language, proprio).state is None  # no head unless asked for


def test_training_fits_a_small_mixed_batch():
    torch.manual_seed(0)
    model = VLAModel(SMALL, DIMS)
    batch = _batch(16, discrete=8)
    optimiser = torch.optim.AdamW(model.parameters(), lr=3e-3)
    first = vla_loss(model, *batch, contrastive_weight=0.2, temperature=0.1).terms
    for _ in range(150):
        losses = vla_loss(model, *batch, contrastive_weight=0.2, temperature=0.1)
        optimiser.zero_grad()
        losses.total.backward()
        optimiser.step()
    assert losses.terms["action_mse"] < 0.35 * first["action_mse"]
    assert losses.terms["discrete_accuracy"] == 1.0 and losses.terms["infonce"] < first["infonce"]


def test_uncertainty_is_entropy_or_log_det_sigma():
    uniform = ModelOutput(torch.zeros(1, 8), torch.zeros(1, 1, 7), torch.full((1, 1, 7), -1.0), torch.zeros(1, 1, 4))
    assert uncertainty([uniform], discrete=True).item() == pytest.approx(math.log(4))
    assert uncertainty([uniform], discrete=False).item() == pytest.approx(2 * 7 * -1.0)
    sure = ModelOutput(torch.zeros(1, 8), torch.zeros(1, 1, 7), torch.full((1, 1, 7), -3.0), torch.tensor([[[20.0, 0, 0, 0]]]))
    assert uncertainty([sure], True) < uncertainty([uniform], True)
    assert uncertainty([sure], False) < uncertainty([uniform], False)


def test_an_ensembles_uncertainty_counts_its_members_disagreement():
    def member(mu: float, top: int) -> ModelOutput:
        logits = torch.zeros(1, 1, 4)
        logits[0, 0, top] = 20.0
        return ModelOutput(torch.zeros(1, 8), torch.full((1, 1, 7), mu), torch.full((1, 1, 7), -3.0), logits)

    agreeing, disagreeing = [member(0.5, 0), member(0.5, 0)], [member(0.0, 0), member(1.0, 1)]
    # equal means: the mixture is each member's own Gaussian; sure members that disagree: about
    # log 2 nats, and each component's variance exp(-6) + 0.5^2
    assert uncertainty(agreeing, False).item() == pytest.approx(2 * 7 * -3.0, abs=1e-4)
    assert uncertainty(disagreeing, False).item() == pytest.approx(7 * math.log(math.exp(-6.0) + 0.25), abs=1e-4)
    assert uncertainty(agreeing, True).item() == pytest.approx(0.0, abs=1e-4)
    assert uncertainty(disagreeing, True).item() == pytest.approx(math.log(2), abs=1e-4)


def test_fine_tuned_language_encoder_starts_from_the_pretrained_weights_and_learns():
    from policies.language import encode

    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, language_trainable=True, chunk=1), DIMS)
    texts = ["lift the red cube", "pick up the green block", "lift the red cube"]
    embedded = model.language_input(texts, cached=None)
    assert np.allclose(embedded.detach().numpy(), encode("all-MiniLM-L6-v2", texts), atol=1e-5)
    image, _, proprio, action, index = _batch(3)
    losses = vla_loss(model, image, embedded, proprio, action, index, 0.5, 0.1)
    losses.total.backward()
    gradients = [p.grad for p in model.text.parameters() if p.grad is not None]
    assert gradients and any(g.abs().sum() > 0 for g in gradients)
    with pytest.raises(ValueError, match="cached instruction embeddings"):
        VLAModel(SMALL, DIMS).language_input(texts, cached=None)
