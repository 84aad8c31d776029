"""The baselines' SAC: stable-baselines3's, its update on this CPU's fast path (`FastUpdateSAC`), and a variant
with one encoder, the critic's (`CriticEncoderSAC`).

`FastUpdateSAC` computes SB3's update (the same losses, optimisers, targets, schedules) with each batch's frames
converted once, not at each of the five encoder passes (`policies.rl_encoder.frames_converted_once`: the same
numbers bit for bit), and denormal floats flushed to zero (`policies.precision.denormals_flushed`: Adam's
moments decay into them, at ~20x an operation's cost). Side by side: 1.08-1.09x a step, and 1.23-1.25x an
update from checkpoints at 15,000 steps (docs/bench-rl.md). Acting and the environment's step run outside it as before.

`CriticEncoderSAC`: SAC with one encoder, the critic's: the pixel-SAC design of SAC-AE and DrQ.

SB3's SAC gives the actor and the critic an encoder each (its `share_features_extractor=False` default),
and each update runs five encoder passes over the batch and two backward ones (`skip_critic_encoder_in_actor_loss`
already saves a third): ~100 ms of a core at 84 px, so the generalist's SACs trained for ~14-18 h each
(docs/bench-rl.md). SB3's own shared option trains the one encoder through the actor's loss, the choice
SAC-AE found to hurt on pixels. Here, as in SAC-AE and DrQ, the actor reads the critic's encoder with its
gradients stopped, and only the critic's loss trains it:

1. the next frames through the encoder and through the target's copy, without gradients: the actor's next
   action and the target Q-values (SB3's, as it computes them);
2. the batch's frames through the encoder once, with gradients: the critic's Q-values, its loss, its step
   (encoder included);
3. the actor and the entropy temperature on the features of step 2, detached: no encoder pass at all (SAC-AE
   and DrQ encode the frames once more after the critic's step; the features one step older save that pass).

Three passes and one backward a update, SB3's losses, optimisers, targets and schedules otherwise. Acting
goes through the same encoder (the actor's `features_extractor` is the critic's).

Not the baselines' default (`baselines.sac_encoder=critic` asks for it): a step 1.36-1.48x faster at 84 px, but on
a pixel probe it learned less per environment step than SB3's layout at each of 3 seeds, and the baselines are
compared with our policy at the same environment steps (docs/bench-rl.md)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN, MultiInputPolicy

from policies.precision import denormals_flushed
from policies.rl_encoder import frames_converted_once


class FastUpdateSAC(SAC):
    """SB3's SAC whose update (`update`: SB3's own, or a subclass's) runs with each batch's frames converted
    once and denormals flushed (module docstring)."""

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        with frames_converted_once(self), denormals_flushed():
            self.update(gradient_steps, batch_size)

    def update(self, gradient_steps: int, batch_size: int) -> None:
        super().train(gradient_steps, batch_size)


class CriticEncoderPolicy(MultiInputPolicy):
    """SB3's SAC policy with one encoder shared by the actor and the critic, in the critic's optimiser
    and not the actor's (SB3's `share_features_extractor=True` has it the other way round)."""

    def __init__(self, *args, **kwargs):
        kwargs["share_features_extractor"] = True
        super().__init__(*args, **kwargs)

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)
        encoder = {id(p) for p in self.actor.features_extractor.parameters()}
        self.actor.optimizer = self.optimizer_class(
            [p for p in self.actor.parameters() if id(p) not in encoder], lr=lr_schedule(1), **self.optimizer_kwargs)
        self.critic.optimizer = self.optimizer_class(
            self.critic.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)


class CriticEncoderSAC(FastUpdateSAC):
    """SB3's SAC whose update follows the module docstring's three steps (on the fast path:
    `FastUpdateSAC`); `policy` is always `CriticEncoderPolicy` (a saved one loads back as this class)."""

    def __init__(self, policy=CriticEncoderPolicy, *args, **kwargs):
        super().__init__(CriticEncoderPolicy, *args, **kwargs)
        if self.use_sde:
            raise ValueError("expected use_sde=False for CriticEncoderSAC (its update draws no exploration noise), got True")

    def _actor_on(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SB3's `Actor.action_log_prob`, from features already encoded."""
        actor = self.actor
        latent = actor.latent_pi(features)
        log_std = torch.clamp(actor.log_std(latent), LOG_STD_MIN, LOG_STD_MAX)
        actions, log_prob = actor.action_dist.log_prob_from_params(actor.mu(latent), log_std)
        return actions, log_prob.reshape(-1, 1)

    @staticmethod
    def _q_values(critic, features: torch.Tensor, actions: torch.Tensor) -> list[torch.Tensor]:
        return [q(torch.cat([features, actions], dim=1)) for q in critic.q_networks]

    def update(self, gradient_steps: int, batch_size: int) -> None:
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        critic, target, encoder = self.critic, self.critic_target, self.critic.features_extractor
        ent_coefs, ent_coef_losses, actor_losses, critic_losses = [], [], [], []

        for gradient_step in range(gradient_steps):
            batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            discounts = batch.discounts if batch.discounts is not None else self.gamma
            ent_coef = torch.exp(self.log_ent_coef.detach()) if self.ent_coef_optimizer is not None \
                else self.ent_coef_tensor
            ent_coefs.append(ent_coef.item())

            # 1. the TD target, without gradients: the actor's next action through the online encoder, Q through the target's
            with torch.no_grad():
                next_actions, next_log_prob = self._actor_on(critic.extract_features(batch.next_observations, encoder))
                target_features = target.extract_features(batch.next_observations, target.features_extractor)
                next_q = torch.min(torch.cat(self._q_values(target, target_features, next_actions), dim=1),
                                   dim=1, keepdim=True)[0] - ent_coef * next_log_prob
                target_q = batch.rewards + (1 - batch.dones) * discounts * next_q

            # 2. the critic, encoder included, from one pass over the batch's frames
            features = critic.extract_features(batch.observations, encoder)
            critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in self._q_values(critic, features, batch.actions))
            critic_losses.append(critic_loss.item())
            critic.optimizer.zero_grad()
            critic_loss.backward()
            critic.optimizer.step()

            # 3. the temperature and the actor on those features, detached: the encoder is the critic's to train
            actions_pi, log_prob = self._actor_on(features.detach())
            if self.ent_coef_optimizer is not None:
                ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
                ent_coef_losses.append(ent_coef_loss.item())
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
            min_q_pi = torch.min(torch.cat(self._q_values(critic, features.detach(), actions_pi), dim=1),
                                 dim=1, keepdim=True)[0]
            actor_loss = (ent_coef * log_prob - min_q_pi).mean()
            actor_losses.append(actor_loss.item())
            self.actor.optimizer.zero_grad()
            actor_loss.backward()  # its gradients on the critic's heads are cleared by the critic's next zero_grad
            self.actor.optimizer.step()

            if gradient_step % self.target_update_interval == 0:
                polyak_update(critic.parameters(), target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", np.mean(ent_coefs))
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if ent_coef_losses:
            self.logger.record("train/ent_coef_loss", np.mean(ent_coef_losses))
