import torch

from policies.model import ModelDims, VLAModel, info_nce, vla_loss
from schemas.config import ModelConfig

DIMS = ModelDims(image_size=84, proprio_dim=9, action_dim=7, language_dim=384)


def _batch(n: int = 16):
    generator = torch.Generator().manual_seed(0)
    return (
        torch.rand(n, 3, 84, 84, generator=generator),
        torch.randn(n, 384, generator=generator),
        torch.randn(n, 9, generator=generator),
        torch.randn(n, 7, generator=generator),
    )


def test_forward_shapes():
    model = VLAModel(ModelConfig(dim=32, heads=4), DIMS)
    image, language, proprio, _ = _batch(5)
    z, mu, log_std = model(image, language, proprio)
    assert z.shape == (5, 32) and mu.shape == (5, 7) and log_std.shape == (5, 7)


def test_info_nce_prefers_matching_pairs():
    z = torch.randn(8, 16)
    assert info_nce(z, z, 0.1) < info_nce(z, torch.randn(8, 16), 0.1)


def test_loss_mixes_infonce_and_bc_by_lambda():
    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4), DIMS)
    losses = vla_loss(model, *_batch(), contrastive_weight=0.25, temperature=0.1)
    expected = 0.25 * losses["infonce"] + 0.75 * (losses["action_mse"] + losses["bc_nll"])
    assert torch.allclose(losses["loss"], expected)


def test_training_fits_a_small_batch():
    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1), DIMS)
    batch = _batch(16)
    optimiser = torch.optim.AdamW(model.parameters(), lr=3e-3)
    first = None
    for _ in range(150):
        losses = vla_loss(model, *batch, contrastive_weight=0.2, temperature=0.1)
        optimiser.zero_grad()
        losses["loss"].backward()
        optimiser.step()
        first = first if first is not None else losses["action_mse"].item()
    assert losses["action_mse"].item() < 0.35 * first
