"""The policy wrapper over one model or an ensemble: what it acts on, what it saves and loads."""

from pathlib import Path

import numpy as np
import torch

from envs.observation import Observation
from policies.model import ModelDims, VLAModel, pixels
from policies.policy import Normaliser, Policy, policy_state, save_atomically
from schemas.config import ModelConfig

DIMS = ModelDims(image_size=84, proprio_dim=9, action_dim=7, discrete_actions=4, language_dim=384)
SMALL = ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=1)  # one action per sample
IDENTITY_ACTION, IDENTITY_PROPRIO = Normaliser(np.zeros(7, np.float32), np.ones(7, np.float32)), \
    Normaliser(np.zeros(9, np.float32), np.ones(9, np.float32))


def _member(seed: int) -> VLAModel:
    torch.manual_seed(seed)
    model = VLAModel(SMALL, DIMS)
    with torch.no_grad():  # mean heads that differ clearly, inside the action bounds
        model.mu.bias.normal_(0.0, 0.15)
        model.logits.bias.copy_(torch.eye(4)[seed % 4] * 5.0)
    return model


def _policy(members: list[VLAModel]) -> Policy:
    return Policy(members, IDENTITY_ACTION, IDENTITY_PROPRIO, {"lift the red cube": np.ones(384, np.float32)})


OBS = Observation(np.full((84, 84, 3), 128, np.uint8), np.zeros(9, np.float32), {})


def test_an_ensemble_acts_on_its_members_mean_and_is_less_sure_where_they_disagree():
    a, b = _member(0), _member(1)
    alone_a, alone_b = _policy([a]).act(OBS, "lift the red cube", "robosuite"), \
        _policy([b]).act(OBS, "lift the red cube", "robosuite")
    both = _policy([a, b]).act(OBS, "lift the red cube", "robosuite")
    with torch.no_grad():
        mu = [m.eval()(pixels(torch.tensor(OBS.image)[None]), torch.ones(1, 384), torch.zeros(1, 9)).mu[0] for m in (a, b)]
    np.testing.assert_allclose(both.action, np.clip(((mu[0] + mu[1]) / 2).numpy(), -1, 1), atol=1e-5)
    assert both.uncertainty > max(alone_a.uncertainty, alone_b.uncertainty)  # their means differ: spread added
    twins = _policy([a, _member(0)]).act(OBS, "lift the red cube", "robosuite")
    assert abs(twins.uncertainty - alone_a.uncertainty) < 1e-4  # identical members: the model alone

    # discrete: members sure of different actions; the ensemble's entropy is about log 2
    nav = _policy([a, b]).act(OBS, "lift the red cube", "navigation")
    assert nav.action[0] in (0, 1) and abs(nav.uncertainty - np.log(2)) < 0.1


def test_an_ensemble_checkpoint_loads_every_member(tmp_path: Path):
    members = [_member(0), _member(1), _member(2)]
    path = tmp_path / "policy.pt"
    save_atomically(path, policy_state(members, IDENTITY_ACTION, IDENTITY_PROPRIO))
    loaded = Policy.load(path, {"lift the red cube": np.ones(384, np.float32)})
    assert len(loaded.members) == 3
    expected = _policy(members).act(OBS, "lift the red cube", "robosuite")
    np.testing.assert_allclose(loaded.act(OBS, "lift the red cube", "robosuite").action, expected.action, atol=1e-6)


def test_a_checkpoint_from_before_ensembles_loads_as_one_model(tmp_path: Path):
    model = _member(0)
    state = policy_state([model], IDENTITY_ACTION, IDENTITY_PROPRIO)
    state["state_dict"] = state.pop("members")[0]  # the layout checkpoints had before train.ensemble
    for field in ("chunk", "execution", "execute_steps", "ensemble_decay"):  # nor had they action chunks
        del state["model_config"][field]
    path = tmp_path / "old.pt"
    torch.save(state, path)
    loaded = Policy.load(path, {"lift the red cube": np.ones(384, np.float32)})
    assert len(loaded.members) == 1 and loaded.config.chunk == 1  # as trained, not today's default
    np.testing.assert_allclose(loaded.act(OBS, "lift the red cube", "robosuite").action,
                               _policy([model]).act(OBS, "lift the red cube", "robosuite").action, atol=1e-6)
