"""The baselines' SAC (policies/rl_sac.py): SB3's update on the fast path (each batch's frames converted once,
the same numbers; denormals flushed in the update alone); the critic's encoder variant: one encoder, which
acting reads, only the critic's loss trains (one backward pass through it an update, none from the actor's
loss), three passes an update against SB3's five; saved and loaded back as itself."""

import contextlib

import pytest
import torch
from stable_baselines3 import SAC

from policies.precision import cpu_can_flush_denormals, flushing_denormals
from policies.rl_agent import agent_class, new_agent
from policies.rl_encoder import extractors
from policies.rl_sac import CriticEncoderSAC, FastUpdateSAC


def _encoder_passes(agent, updates: int = 3) -> tuple[list[bool], int, int]:
    """Train `updates` updates past 30 random steps; (whether each training-mode pass of the online encoder
    built a graph, the target encoder's passes, backward passes through the online encoder's first layer)."""
    online, target = agent.critic.features_extractor, agent.critic_target.features_extractor
    graphs, target_passes, backward = [], [], []
    online.register_forward_hook(lambda m, _i, out: graphs.append(out.requires_grad) if m.training else None)
    target.register_forward_hook(lambda _m, _i, _o: target_passes.append(1))
    first = next(online.parameters())
    first.register_hook(lambda grad: backward.append(1))
    agent.learning_starts = 30
    agent.learn(total_timesteps=30 + updates)
    return graphs, len(target_passes), len(backward)


def test_one_encoder_that_the_critic_trains_and_the_actor_reads(lift, tmp_path):
    agent = new_agent("sac", lift, 1_000, 3, sac_encoder="critic")
    assert isinstance(agent, CriticEncoderSAC)
    encoder = agent.critic.features_extractor
    assert agent.actor.features_extractor is encoder  # acting reads it
    in_critic = {id(p) for group in agent.critic.optimizer.param_groups for p in group["params"]}
    in_actor = {id(p) for group in agent.actor.optimizer.param_groups for p in group["params"]}
    assert {id(p) for p in encoder.parameters()} <= in_critic - in_actor
    assert {id(p) for p in agent.actor.mu.parameters()} <= in_actor - in_critic

    before = [p.detach().clone() for p in encoder.parameters()]
    actor_before = [p.detach().clone() for p in agent.actor.mu.parameters()]
    graphs, target_passes, backward = _encoder_passes(agent)
    # an update: the next frames without a graph (the actor's next action), the frames with one (the critic)
    assert graphs == [False, True] * 3 and target_passes == 3
    assert backward == 3  # the critic's loss alone reaches it
    assert any(not torch.equal(a, b) for a, b in zip(before, encoder.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(actor_before, agent.actor.mu.parameters()))

    agent.save(tmp_path / "agent.zip")  # a checkpoint's agent, as learn_with_checkpoints loads it to resume
    loaded = agent_class("sac", "critic").load(tmp_path / "agent.zip", env=lift, device="cpu")
    assert isinstance(loaded, CriticEncoderSAC)
    assert loaded.actor.features_extractor is loaded.critic.features_extractor  # shared again
    assert len(loaded.critic.optimizer.state) == len(list(loaded.critic.parameters()))  # Adam's moments, encoder's too
    assert torch.equal(next(loaded.critic.features_extractor.parameters()), next(encoder.parameters()))


def test_sb3s_sac_takes_five_passes_and_two_backward_ones(lift):
    """The same count on SB3's own layout (an encoder each, the actor's loss through the critic's encoder
    skipped): the actor's encoder twice and backward once more, the critic's twice, the target's once."""
    agent = new_agent("sac", lift, 1_000, 3, sac_encoder="separate")
    assert agent.target_entropy == -7.0  # SB3's: minus the action dimensions
    assert new_agent("sac", lift, 1_000, 3, target_entropy=-4.0).target_entropy == -4.0  # baselines.sac_target_entropy
    actor_graphs = []
    agent.actor.features_extractor.register_forward_hook(
        lambda m, _i, out: actor_graphs.append(out.requires_grad) if m.training else None)
    critic_graphs, target_passes, critic_backward = _encoder_passes(agent)
    assert len(actor_graphs) + len(critic_graphs) + target_passes == 5 * 3
    assert critic_backward == 3 and sum(actor_graphs) == 3  # and the actor's own backward: two an update


@pytest.mark.parametrize("sac_encoder, passes", [("separate", 5), ("critic", 3)])
@pytest.mark.parametrize("bf16", [False, True])
def test_sac_converts_a_batchs_frames_once_and_updates_as_before(lift, monkeypatch, bf16, sac_encoder, passes):
    """An update's encoder passes (SB3's five; the critic's encoder's three) each converted the batch's frames;
    now the frames and the next frames are converted once each, to the same numbers: the same parameters after
    the same updates, bit for bit, in fp32 and in bf16 (channels_last frames); acting, outside the update,
    converts its frame as before. (Denormals are left as they are here: this compares the conversions.)"""
    def trained(ours: bool) -> tuple[SAC, list[set[int]]]:
        with monkeypatch.context() as patched:
            patched.setattr("policies.rl_sac.denormals_flushed", contextlib.nullcontext)
            if not ours:  # the update as it was: each pass converts
                patched.setattr(FastUpdateSAC, "train",
                                lambda agent, gradient_steps, batch_size=64: agent.update(gradient_steps, batch_size))
            agent = new_agent("sac", lift, 1_000, 3, sac_encoder=sac_encoder)
            for extractor in extractors(agent):
                extractor.bf16 = bf16
            frames: list[torch.Tensor] = []  # held, so that no two passes' frames can share memory by reuse
            for extractor in {id(e): e for e in extractors(agent)}.values():
                extractor.extractors["image"].register_forward_pre_hook(
                    lambda _m, args: frames.append(args[0]) if len(args[0]) > 1 else None)
            agent.learning_starts = 30
            agent.learn(total_timesteps=33)  # 30 random steps, then 3 updates of 64 samples
        assert len(frames) == passes * 3
        return agent, [{f.data_ptr() for f in frames[passes * i:passes * (i + 1)]} for i in range(3)]

    (ours, our_frames), (before, frames_before) = trained(True), trained(False)
    assert isinstance(ours, FastUpdateSAC)
    assert [len(update) for update in our_frames] == [2] * 3
    assert [len(update) for update in frames_before] == [passes] * 3
    assert all(torch.equal(a, b) for a, b in zip(ours.policy.state_dict().values(), before.policy.state_dict().values()))
    assert ours.policy.normalize_images and ours.actor.normalize_images  # acting converts its frame again
    assert "sample" not in vars(ours.replay_buffer)  # the buffer's own method, as a checkpoint pickles it


def test_a_failed_update_leaves_the_agent_as_it_was(lift, monkeypatch):
    agent = new_agent("sac", lift, 1_000, 3)

    def fails(_agent, _steps, _batch):
        assert flushing_denormals() or not cpu_can_flush_denormals()
        assert "sample" in vars(agent.replay_buffer) and not agent.critic_target.normalize_images
        raise RuntimeError("an update that fails")

    monkeypatch.setattr(FastUpdateSAC, "update", fails)
    with pytest.raises(RuntimeError, match="an update that fails"):
        agent.train(1, 64)
    assert "sample" not in vars(agent.replay_buffer)
    assert all(model.normalize_images for model in (agent.policy, agent.actor, agent.critic, agent.critic_target))
    assert not flushing_denormals()


@pytest.mark.skipif(not cpu_can_flush_denormals(), reason="this CPU cannot flush denormals (torch.set_flush_denormal)")
def test_sac_updates_with_denormals_flushed_and_steps_the_environment_without(lift, monkeypatch):
    """Adam's moments decay into denormals, ~20x an operation's cost: the update flushes them to zero; the
    simulation, acting and everything after the update compute with them as before."""
    agent = new_agent("sac", lift, 1_000, 3)
    in_updates, in_env = [], []
    agent.critic.features_extractor.register_forward_hook(lambda *_: in_updates.append(flushing_denormals()))
    step = type(lift).step
    monkeypatch.setattr(type(lift), "step",
                        lambda env, action: (in_env.append(flushing_denormals()), step(env, action))[1])
    agent.learning_starts = 30
    agent.learn(total_timesteps=33)
    assert in_updates and all(in_updates)
    assert len(in_env) == 33 and not any(in_env)
    assert not flushing_denormals()
