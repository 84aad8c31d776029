"""The baselines' PPO: stable-baselines3's, its update with denormal floats flushed to zero
(`policies.precision.denormals_flushed`), as SAC's (policies/rl_sac.py): Adam's moments of parameters whose
gradients are zero decay into them, at ~20x an operation's cost on x86 (docs/bench-rl.md). The rollout (the
environment's steps, acting) runs outside it as before."""

from __future__ import annotations

from stable_baselines3 import PPO

from policies.precision import denormals_flushed


class FastUpdatePPO(PPO):
    """SB3's PPO whose update runs with denormals flushed (module docstring)."""

    def train(self) -> None:
        with denormals_flushed():
            super().train()
