"""The RL baselines' encoder: SB3's own exactly in fp32; in bf16 on batches (updates, target critics), its
features back in fp32 and near the fp32 ones, one observation (acting) in fp32; the precision chosen by
train.amp's rule for this CPU, once per host; the agents' optimisers fused Adam with SB3's settings."""

import json

import numpy as np
import pytest
import torch
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.torch_layers import CombinedExtractor

from envs.gym_env import InstructedTasksEnv
from envs.suite import generate_tasks
from policies.precision import uses_bf16
from policies.rl_agent import learn_with_checkpoints, new_agent
from policies.rl_encoder import AutocastExtractor, encoder_precision, extractors
from schemas.config import RandomiseConfig, RenderConfig, TasksConfig


@pytest.fixture(scope="module")
def env() -> InstructedTasksEnv:
    tasks = generate_tasks(TasksConfig(specs=["nav-room"], colours=["red", "green"]), seed=0)
    said = sorted({text for task in tasks for text in task.instructions})
    return InstructedTasksEnv(tasks, {text: np.full(8, i, dtype=np.float32) for i, text in enumerate(said)},
                              RenderConfig(image_size=48), RandomiseConfig())


def _batch(space, size: int = 16) -> dict[str, torch.Tensor]:
    """Sampled observations as the agent sees them (SB3 wraps the env: its frames channels-first)."""
    space.seed(1)
    samples = [space.sample() for _ in range(size)]
    return {key: torch.as_tensor(np.stack([s[key] for s in samples])) for key in samples[0]}


def test_unset_it_is_sb3s_extractor_exactly(env):
    space = new_agent("ppo", env, 600, 0).observation_space
    torch.manual_seed(0)
    ours = AutocastExtractor(space).train()
    torch.manual_seed(0)
    theirs = CombinedExtractor(space).train()
    observed = preprocess_obs(_batch(space), space)
    assert torch.equal(ours(observed), theirs(observed))


@pytest.mark.parametrize("mode", ["train", "eval"])  # an update's pass; a target critic's (SB3 keeps it in eval)
def test_bf16_on_batches_and_its_features_in_fp32(env, mode):
    agent = new_agent("ppo", env, 600, 0)
    found = extractors(agent)
    assert len(found) == 1  # PPO's actor and critic share it
    encoder, batch = getattr(found[0], mode)(), _batch(agent.observation_space)
    fp32 = agent.policy.extract_features(batch, encoder)
    encoder.bf16 = True
    bf16 = agent.policy.extract_features(batch, encoder)
    assert bf16.dtype == torch.float32 and not torch.equal(bf16, fp32)  # computed in bf16, handed on in fp32
    assert torch.allclose(bf16, fp32, rtol=0.05, atol=0.05)
    one = {key: value[:1] for key, value in batch.items()}  # acting: one frame, fp32 as SB3 computes it
    acting = agent.policy.extract_features(one, encoder)
    encoder.bf16 = False
    assert torch.equal(acting, agent.policy.extract_features(one, encoder))


@pytest.mark.parametrize("algorithm, eps", [("ppo", 1e-5), ("sac", 1e-8)])
def test_the_optimisers_are_fused_adam_with_sb3s_settings(request, algorithm, eps):
    agent = new_agent(algorithm, request.getfixturevalue("env" if algorithm == "ppo" else "lift"), 600, 0)
    optimisers = [agent.policy.optimizer] if algorithm == "ppo" else [agent.actor.optimizer, agent.critic.optimizer]
    for optimiser in optimisers:
        assert isinstance(optimiser, torch.optim.Adam)
        assert optimiser.defaults["fused"] is True and optimiser.defaults["eps"] == eps  # SB3's PPO eps, Adam's own for SAC


def test_the_choice_follows_the_cpu_and_is_measured_once_per_host(env, tmp_path, monkeypatch):
    """Where bf16 may pay without AMX (AVX-512 BF16), one pass each way is timed and kept per host and encoder;
    elsewhere the device's rule decides and nothing is measured. Both paths on any host: the CPU's answer is
    told, and the pass timed by a stand-in clock (bf16 1.5x fp32's speed, then 1.05x: under the 1.10 margin)."""
    import policies.rl_encoder as rl_encoder

    def timer(speedup: float, calls: list):
        def factory(agent, encoder, batch_size):
            def seconds(bf16: bool) -> float:
                calls.append(bf16)
                return 1.0 if bf16 else speedup
            return seconds
        return factory

    monkeypatch.setattr(rl_encoder, "cpu_bf16_may_pay", lambda device: True)
    calls: list = []
    monkeypatch.setattr(rl_encoder, "_pass_timer", timer(1.5, calls))
    cache = tmp_path / "precision.json"
    agent = new_agent("ppo", env, 600, 0)
    bf16, why = encoder_precision(agent, cache, batch_size=8)
    assert bf16 and all(e.bf16 for e in extractors(agent)) and "measured at 1.50x" in why and calls
    [measured] = json.loads(cache.read_text()).values()
    assert measured["speedup"] == 1.5
    calls.clear()  # the next agent on this host reads the choice back: nothing timed
    assert encoder_precision(new_agent("ppo", env, 600, 0), cache, batch_size=8)[0] is True and calls == []
    slow = tmp_path / "slow.json"
    monkeypatch.setattr(rl_encoder, "_pass_timer", timer(1.05, []))
    assert encoder_precision(new_agent("ppo", env, 600, 0), slow, batch_size=8)[0] is False  # under the margin

    monkeypatch.setattr(rl_encoder, "cpu_bf16_may_pay", lambda device: False)  # AMX, or no bf16 units: the rule
    ruled = tmp_path / "ruled.json"
    bf16, why = encoder_precision(new_agent("ppo", env, 600, 0), ruled, batch_size=8)
    assert bf16 == uses_bf16(torch.device("cpu"), True) and "measured at" not in why and not ruled.exists()


def test_a_training_with_the_cache_learns_and_saves_an_agent_that_loads(env, tmp_path):
    agent, _ = learn_with_checkpoints("ppo", env, 128, 0, tmp_path / "agent", 64,
                                      precision_cache=tmp_path / "precision.json")
    assert agent.num_timesteps >= 128
    agent.save(tmp_path / "agent.zip")
    from stable_baselines3 import PPO
    loaded = PPO.load(tmp_path / "agent.zip", device="cpu")
    assert extractors(loaded) and not any(e.bf16 for e in extractors(loaded))  # an execution choice, not saved


def test_sacs_actor_loss_skips_the_critics_encoder_and_updates_as_sb3_does(lift):
    """SAC's update as SB3 wrote it, its actor loss's backward pass through the critic's encoder, against ours: the
    same parameters after the same updates, bit for bit; ours builds a graph through that encoder once an
    update (the critic's loss), SB3's twice (the actor's loss too)."""
    from stable_baselines3 import SAC

    def trained(skip: bool) -> tuple[SAC, list[bool]]:
        agent = new_agent("sac", lift, 1_000, 3, sac_encoder="separate")
        if not skip:  # SB3's own update: the hooks new_agent put on the optimisers removed
            for optimizer in (agent.critic.optimizer, agent.actor.optimizer):
                optimizer._optimizer_step_post_hooks.clear()
        graphs: list[bool] = []
        agent.critic.features_extractor.register_forward_hook(lambda _m, _i, out: graphs.append(out.requires_grad))
        agent.learning_starts = 30
        agent.learn(total_timesteps=33)  # 30 random steps, then 3 updates of 64 samples (drawn with repeats)
        return agent, graphs

    (ours, our_graphs), (sb3, sb3_graphs) = trained(True), trained(False)
    assert our_graphs == [True, False] * 3 and sb3_graphs == [True, True] * 3
    assert all(torch.equal(a, b) for a, b in zip(ours.policy.state_dict().values(), sb3.policy.state_dict().values()))
    assert all(p.requires_grad for p in ours.critic.features_extractor.parameters())  # thawed by the actor's step
