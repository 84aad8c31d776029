"""Acting with action chunks: temporal ensembling and receding horizon on a known sequence of
predictions, the episode's state, and the moving average of the weights a training registers."""

from pathlib import Path

import numpy as np
import pytest
import torch

from envs.observation import Observation
from policies.chunking import EpisodeActor, temporal_ensemble
from policies.ema import WeightAverage, decay_at
from policies.model import ModelDims, VLAModel, vla_loss
from policies.policy import Normaliser, Policy, policy_state, save_atomically
from schemas.config import Acting, ModelConfig

OBS = Observation(np.zeros((84, 84, 3), np.uint8), np.zeros(9, np.float32), {})
IDENTITY = Normaliser(np.zeros(7, np.float32), np.ones(7, np.float32))
DIMS = ModelDims(image_size=84, proprio_dim=9, action_dim=7, discrete_actions=4, language_dim=384)


class ScriptedPolicy(Policy):
    """A policy whose chunk predicted at its n-th call is known: position j holds 10 n + j in every
    action component (normalised units, identity normaliser; clipped to [-1, 1] only when acted)."""

    def __init__(self, config: ModelConfig):
        self._config, self.calls, self.action = config, 0, Normaliser(np.zeros(7, np.float32), np.full(7, 0.01, np.float32))

    @property
    def config(self) -> ModelConfig:
        return self._config

    def predict(self, obs, instruction, family):
        chunk = np.repeat((10.0 * self.calls + np.arange(self._config.chunk))[:, None], 7, axis=1)
        self.calls += 1
        return chunk, 0.5


def _first_component(actor: EpisodeActor, steps: int, instruction: str = "go") -> list[float]:
    # the scripted values over the normaliser's std 0.01: value v acts as 0.01 v (clipped at 1)
    return [float(actor(OBS, instruction).action[0]) / 0.01 for _ in range(steps)]


def test_temporal_ensembling_averages_every_chunk_that_predicted_this_step_oldest_weighted_most():
    policy = ScriptedPolicy(ModelConfig(chunk=3, ensemble_decay=0.5))
    acted = _first_component(EpisodeActor(policy, "robosuite"), 4)
    w = np.exp(-0.5 * np.arange(3))
    # step 0: call 0's position 0; step 1: call 0's pos 1 and call 1's pos 0; from step 2 three chunks
    expected = [0.0, (w[0] * 1 + w[1] * 10) / w[:2].sum(), (w[0] * 2 + w[1] * 11 + w[2] * 20) / w.sum(),
                (w[0] * 12 + w[1] * 21 + w[2] * 30) / w.sum()]
    np.testing.assert_allclose(acted, expected, rtol=1e-5)
    assert policy.calls == 4  # a prediction every step
    assert temporal_ensemble([np.ones(2), 3 * np.ones(2)], 0.0).tolist() == [2.0, 2.0]


def test_receding_horizon_executes_part_of_each_chunk_then_predicts_again():
    policy = ScriptedPolicy(ModelConfig(chunk=4, execution="receding", execute_steps=3))
    acted = _first_component(EpisodeActor(policy, "robosuite"), 7)
    np.testing.assert_allclose(acted, [0, 1, 2, 10, 11, 12, 20], atol=1e-4)
    assert policy.calls == 3
    assert ModelConfig(chunk=8, execution="receding").steps_per_prediction == 4  # default: half the chunk
    with pytest.raises(ValueError, match="execute_steps: expected at most chunk"):
        ModelConfig(chunk=2, execute_steps=3)


def test_a_new_instruction_or_episode_starts_from_no_chunk():
    policy = ScriptedPolicy(ModelConfig(chunk=3, ensemble_decay=0.0))
    actor = EpisodeActor(policy, "robosuite")
    _first_component(actor, 2)
    # the next sub-goal: only the chunk predicted now speaks for this step
    np.testing.assert_allclose(_first_component(actor, 1, "next goal"), [20.0], atol=1e-4)
    np.testing.assert_allclose(_first_component(EpisodeActor(policy, "robosuite"), 1), [30.0], atol=1e-4)


def test_the_served_model_acts_each_episode_as_evaluation_does():
    """The registry's pyfunc model: rows with an episode id act through that episode's earlier chunks (as
    EpisodeActor acts in evaluation), episodes apart and across calls; rows without one, alone."""
    from collections import OrderedDict

    import pandas as pd

    from policies.mlflow_model import predict_frame
    from schemas.frames import encode_frame

    def rows(*episode_ids):
        return pd.DataFrame({"image": [encode_frame(OBS.image)] * len(episode_ids), "proprio": [[0.0] * 9] * len(episode_ids),
                             "instruction": ["go"] * len(episode_ids), "family": ["robosuite"] * len(episode_ids),
                             "episode_id": list(episode_ids)})

    def first(frame):
        return [round(action[0] / 0.01, 4) for action in frame["action"]]

    config = ModelConfig(chunk=4, execution="receding", execute_steps=3)
    episodes = OrderedDict()
    policy = ScriptedPolicy(config)
    served = first(predict_frame(policy, rows("a", "a", "b"), episodes)) + first(predict_frame(policy, rows("a", "a"), episodes))
    # a: predicted at call 0 (0..3), plays 0, 1, then 2 in the next frame and predicts again (call 2: 20..23);
    # b: its own first chunk (call 1)
    assert served == [0.0, 1.0, 10.0, 2.0, 20.0]
    alone = ScriptedPolicy(config)
    assert first(predict_frame(alone, rows(None, None))) == [0.0, 10.0]  # no episode: each row its chunk's first


def test_a_chunked_model_acts_through_its_episode_and_its_checkpoint_round_trips(tmp_path: Path):
    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=4), DIMS)
    path = tmp_path / "policy.pt"
    save_atomically(path, policy_state([model], IDENTITY, Normaliser(np.zeros(9, np.float32), np.ones(9, np.float32))))
    policy = Policy.load(path, {"go": np.ones(384, np.float32)})
    chunk, _ = policy.predict(OBS, "go", "robosuite")
    assert chunk.shape == (4, 7)
    actor = policy.episode("robosuite")
    first = actor(OBS, "go").action
    np.testing.assert_allclose(first, np.clip(chunk[0], -1, 1), atol=1e-6)  # step 0: the first chunk alone
    assert policy.act(OBS, "go", "robosuite").action.shape == (7,)
    probabilities, _ = policy.predict(OBS, "go", "navigation")
    assert probabilities.shape == (4, 4) and np.allclose(probabilities.sum(-1), 1.0, atol=1e-5)


def test_a_checkpoint_acts_otherwise_than_it_trained_when_told(tmp_path: Path):
    """Policy.acting_as (sim2act shadow --execution): the same weights and chunks, turned into actions
    another way; temporal ensembling mixes the chunk predicted a step ago into step 1, receding 1 does not."""
    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=4), DIMS)
    path = tmp_path / "policy.pt"
    save_atomically(path, policy_state([model], IDENTITY, Normaliser(np.zeros(9, np.float32), np.ones(9, np.float32))))
    ensembled = Policy.load(path, {"go": np.ones(384, np.float32)})
    chunk, _ = ensembled.predict(OBS, "go", "robosuite")  # the same observation every step: the same chunk
    actor = ensembled.episode("robosuite")
    steps = [actor(OBS, "go").action for _ in range(2)]
    np.testing.assert_allclose(steps[1], np.clip(temporal_ensemble([chunk[1], chunk[0]], 0.01), -1, 1), atol=1e-5)

    receding = Policy.load(path, {"go": np.ones(384, np.float32)}).acting_as(Acting(execution="receding", execute_steps=1))
    assert receding.config.execution == "receding" and receding.members[0].config.execution == "temporal_ensemble"
    actor = receding.episode("robosuite")
    for _ in range(3):  # every step: the chunk predicted now, its first action
        np.testing.assert_allclose(actor(OBS, "go").action, np.clip(chunk[0], -1, 1), atol=1e-5)
    assert Acting(execution="receding", execute_steps=1).describe() == "execution receding, execute_steps 1"
    with pytest.raises(ValueError, match="execute_steps: expected at most chunk"):
        Policy.load(path).acting_as(Acting(execution="receding", execute_steps=5))


def test_masked_chunk_positions_do_not_move_the_loss():
    torch.manual_seed(0)
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1, chunk=3), DIMS)
    image, language, proprio = torch.rand(4, 3, 84, 84), torch.randn(4, 384), torch.randn(4, 9)
    action, index = torch.randn(4, 3, 7), torch.full((4, 3), -1)
    mask = torch.tensor([[1.0, 1.0, 0.0]] * 4)
    changed = action.clone()
    changed[:, 2] += 5.0  # past the episodes' end: masked
    a = vla_loss(model, image, language, proprio, action, index, 0.0, 0.1, action_mask=mask)
    b = vla_loss(model, image, language, proprio, changed, index, 0.0, 0.1, action_mask=mask)
    assert a.terms["bc"].item() == pytest.approx(b.terms["bc"].item())
    c = vla_loss(model, image, language, proprio, changed, index, 0.0, 0.1)
    assert c.terms["bc"].item() > a.terms["bc"].item() + 1.0
    assert a.terms["action_mse"].item() == pytest.approx(((model(image, language, proprio).mu - action[:, 0]) ** 2)
                                                          .mean().item(), rel=1e-4)


def test_the_moving_average_warms_up_then_trails_the_weights():
    assert decay_at(0, 0.999) == pytest.approx(0.1) and decay_at(10_000, 0.999) == 0.999
    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    average = WeightAverage(model, 0.5)
    start = model[0].weight.detach().clone()
    with torch.no_grad():
        model[0].weight.add_(1.0)
    average.update(model, 1)  # decay 0.1 at the first step: mostly the new weights
    np.testing.assert_allclose(average.weights["0.weight"], start + 0.9, atol=1e-6)
    model(torch.randn(8, 2))  # the batch-norm counter moves: copied, not averaged
    average.update(model, 100)  # decay 0.5 from here
    np.testing.assert_allclose(average.weights["0.weight"], start + 0.95, atol=1e-6)
    assert int(average.weights["1.num_batches_tracked"]) == 1


def test_a_resumed_average_lives_on_its_models_device():
    """A checkpoint is loaded to the CPU; the average resumed from it must follow a model elsewhere
    (the meta device stands in for a GPU here), or its first update would mix devices."""
    model = torch.nn.Linear(2, 2)
    saved = WeightAverage(model, 0.5).weights  # on the CPU, as torch.load(map_location="cpu") gives it
    resumed = WeightAverage(model.to("meta"), 0.5, saved)
    assert {w.device.type for w in resumed.weights.values()} == {"meta"}


def test_a_checkpoint_registers_the_average_and_keeps_the_last_weights(tmp_path: Path):
    model = VLAModel(ModelConfig(dim=32, heads=4, vision_depth=1, fusion_depth=1), DIMS)
    average = {name: torch.zeros_like(value) for name, value in model.state_dict().items()}
    path = tmp_path / "policy.pt"
    proprio = Normaliser(np.zeros(9, np.float32), np.ones(9, np.float32))
    save_atomically(path, policy_state([model], IDENTITY, proprio, [average], 0.999))
    registered, final = Policy.load(path), Policy.load(path, weights="final")
    assert registered.weights == "ema 0.999" and final.weights == "final"
    assert float(registered.members[0].mu.weight.detach().abs().sum()) == 0.0
    assert torch.equal(final.members[0].mu.weight, model.mu.weight)
    with pytest.raises(ValueError, match="weights: expected one of registered, final"):
        Policy.load(path, weights="best")
