"""SAC with the critic's encoder (policies/rl_sac.py): one encoder, which acting reads, only the critic's
loss trains (one backward pass through it an update, none from the actor's loss), three passes an update
against SB3's five; saved and loaded back as itself."""

import torch

from policies.rl_agent import agent_class, new_agent
from policies.rl_sac import CriticEncoderSAC


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
    actor_graphs = []
    agent.actor.features_extractor.register_forward_hook(
        lambda m, _i, out: actor_graphs.append(out.requires_grad) if m.training else None)
    critic_graphs, target_passes, critic_backward = _encoder_passes(agent)
    assert len(actor_graphs) + len(critic_graphs) + target_passes == 5 * 3
    assert critic_backward == 3 and sum(actor_graphs) == 3  # and the actor's own backward: two an update
