"""The baselines' PPO (policies/rl_ppo.py): SB3's, its update with denormals flushed, its rollout without."""

import pytest

from policies.precision import cpu_can_flush_denormals, flushing_denormals
from policies.rl_agent import new_agent
from policies.rl_ppo import FastUpdatePPO


@pytest.mark.skipif(not cpu_can_flush_denormals(), reason="this CPU cannot flush denormals (torch.set_flush_denormal)")
def test_ppo_updates_with_denormals_flushed_and_steps_the_environment_without(lift, monkeypatch):
    agent = new_agent("ppo", lift, 128, 3)
    assert isinstance(agent, FastUpdatePPO)
    in_updates, in_env = [], []
    agent.policy.features_extractor.register_forward_hook(
        lambda _m, args, _o: in_updates.append(flushing_denormals()) if len(args[0]["image"]) > 1 else None)
    step = type(lift).step
    monkeypatch.setattr(type(lift), "step",
                        lambda env, action: (in_env.append(flushing_denormals()), step(env, action))[1])
    agent.learn(total_timesteps=128)  # one rollout of 128 steps, then its update: minibatches of 64
    assert in_updates and all(in_updates)
    assert len(in_env) == 128 and not any(in_env)
    assert not flushing_denormals()
