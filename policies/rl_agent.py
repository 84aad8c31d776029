"""The RL-from-scratch baselines: stable-baselines3's PPO and SAC on a family's instruction-
conditioned environment (envs.gym_env), their settings, training them with resumable checkpoints,
and acting with a saved one."""

from __future__ import annotations

import json
import logging
import math
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from envs.gym_env import adapter_action, agent_observation
from warehouse.store import fsync_path
from envs.observation import DISCRETE_FAMILIES, Observation
from schemas.workspace import read_json_written

RL_ALGORITHMS = ("ppo", "sac")
log = logging.getLogger("sim2act.policies.rl_agent")


def supports(algorithm: str, family: str) -> bool:
    """SAC acts in continuous spaces only; PPO in both."""
    return algorithm == "ppo" or family not in DISCRETE_FAMILIES


CHECKPOINT, PREVIOUS, WRITING = "checkpoint", "checkpoint.old", "checkpoint.tmp"  # folders beside agent.zip


def agent_class(algorithm: str, sac_encoder: str = "separate"):
    """SB3's PPO (policies/rl_ppo.py: its update with denormals flushed); SAC with the critic's encoder shared
    (policies/rl_sac.py) or SB3's own, an encoder each, both updating on the fast path (`FastUpdateSAC`)."""
    from policies.rl_ppo import FastUpdatePPO
    from policies.rl_sac import CriticEncoderSAC, FastUpdateSAC

    if algorithm == "ppo":
        return FastUpdatePPO
    return {"critic": CriticEncoderSAC, "separate": FastUpdateSAC}[sac_encoder]


def new_agent(algorithm: str, env, env_steps: int, seed: int, replay_size: int | None = None,
              sac_encoder: str = "separate", target_entropy: float | None = None):
    """An untrained agent, SB3's defaults but for the sizes a small budget needs: PPO collects
    rollouts of at most 512 steps (its default 2,048 would be a whole small budget), sized so that
    whole rollouts pass the budget by less than one step each, minibatches of 64; SAC's replay
    holds the budget (at most `replay_size` transitions: each keeps two frames), learning starts
    after a tenth of it (at most 1,000 steps), batches of 64. The encoder is SB3's own
    (policies/rl_encoder.py: in bf16 on batches once `encoder_precision` says so), its optimisers torch's fused
    Adam (SB3's hyperparameters); SAC's actor
    loss skips the critic's encoder (`skip_critic_encoder_in_actor_loss`: the same updates, less work), or,
    with `sac_encoder="critic"`, the actor reads the critic's one encoder (`policies.rl_sac`: less still).
    `target_entropy`: SAC's entropy target (None: SB3's, minus the action dimensions)."""
    from policies.rl_encoder import AutocastExtractor, skip_critic_encoder_in_actor_loss

    def common(adam_eps: float) -> dict:
        # SB3's own encoder, bf16 where it pays; torch's fused Adam: SB3's per-tensor Adam's update rule
        # in one kernel, ~5x faster over SAC's ~2M parameters on a CPU core (docs/bench-rl.md); SB3's Adam eps
        # per algorithm (it sets PPO's 1e-5 only where no optimizer_kwargs are given)
        return {"policy": "MultiInputPolicy", "env": env, "seed": seed, "verbose": 0, "device": "cpu",
                "policy_kwargs": {"features_extractor_class": AutocastExtractor,
                                  "optimizer_kwargs": {"eps": adam_eps, "fused": True}}}
    if algorithm == "ppo":
        rollouts = math.ceil(env_steps / 512)
        n_steps = math.ceil(env_steps / rollouts)
        return without_log_folder(agent_class("ppo")(n_steps=n_steps, batch_size=min(64, n_steps), **common(1e-5)))
    agent = agent_class("sac", sac_encoder)(buffer_size=replay_buffer_size(env_steps, replay_size),
                                            learning_starts=min(1000, env_steps // 10), batch_size=64,
                                            target_entropy="auto" if target_entropy is None else target_entropy,
                                            **common(1e-8))
    skip_critic_encoder_in_actor_loss(agent)
    return without_log_folder(agent)


def without_log_folder(agent):
    """`agent` with a logger of our own that writes nothing: SB3's default (`configure()` with no
    folder) makes an empty folder /tmp/SB3-<time> at every `learn()`, i.e. at every start, resume and
    benchmark. A loaded agent needs it again (SB3 does not save its logger)."""
    from stable_baselines3.common.logger import Logger

    agent.set_logger(Logger(folder=None, output_formats=[]))
    return agent


def replay_buffer_size(env_steps: int, replay_size: int | None) -> int:
    """SAC's replay: the whole budget, or `replay_size` transitions where that is smaller."""
    return env_steps if replay_size is None else min(env_steps, replay_size)


def last_checkpoint(folder: Path) -> Path | None:
    """The last whole checkpoint in `folder` (an agent's models/<key>/): a save is written aside and
    swapped in by renames, so a kill at any moment leaves the new one or the one before."""
    for name in (CHECKPOINT, PREVIOUS):
        if (folder / name / "state.json").exists():
            return folder / name
    return None


def checkpoint_state(folder: Path) -> tuple[dict, float] | None:
    """The last whole checkpoint's counters in `folder` ({"num_timesteps", "episodes", "successes"})
    and when it was written (epoch seconds); None where the agent has none. Safe beside a training
    saving its next one (another process: `sim2act report`)."""
    for _ in range(3):
        last = last_checkpoint(folder)
        if last is None:
            return None
        state = read_json_written(last / "state.json")  # an open file outlives the save's renames and removals
        if state is not None:
            return state
        # swapped out between the look and the open: look again
    return None


def save_checkpoint(agent, env, folder: Path) -> None:
    """The agent (weights, optimisers, step count), SAC's replay buffer, and the environment's
    counters of training episodes, swapped in whole (`last_checkpoint`)."""
    writing, current, previous = folder / WRITING, folder / CHECKPOINT, folder / PREVIOUS
    shutil.rmtree(writing, ignore_errors=True)
    writing.mkdir(parents=True)
    agent.save(writing / "agent.zip")
    if hasattr(agent, "save_replay_buffer"):
        agent.save_replay_buffer(writing / "replay.pkl")
    (writing / "state.json").write_text(json.dumps(
        {"num_timesteps": agent.num_timesteps, "episodes": env.episodes_finished, "successes": env.successes}))
    # on disk before the swap: a machine that stops (not only the process) right after a save must not find a
    # renamed-in checkpoint of empty or cut files with the one before already removed
    for path in (*writing.iterdir(), writing):
        fsync_path(path)
    if current.exists():  # else a kill between renames left `previous` the only whole one: kept until replaced
        shutil.rmtree(previous, ignore_errors=True)
        current.rename(previous)
    writing.rename(current)
    fsync_path(folder)  # the renames themselves
    shutil.rmtree(previous, ignore_errors=True)


def remove_checkpoints(folder: Path) -> None:
    for name in (CHECKPOINT, PREVIOUS, WRITING):
        shutil.rmtree(folder / name, ignore_errors=True)


def learn_with_checkpoints(
    algorithm: str, env, env_steps: int, seed: int, folder: Path, every: int, replay_size: int | None = None,
    on_progress: Callable[[int, int], None] | None = None, precision_cache: Path | None = None,
    sac_encoder: str = "separate", target_entropy: float | None = None,
):
    """Train an agent to `env_steps` environment steps, from the last checkpoint in `folder` where a
    kill interrupted an earlier run, saving one every `every` steps at the start of a rollout (after
    the previous rollout's update: nothing learned is lost, only the steps since the checkpoint).

    A resumed agent's later episodes are seeded by (seed, the step it resumed at): a run killed at
    the same steps repeats itself, though not the unbroken run's episodes. `on_progress(done,
    resumed_at)` is called at every rollout's start. With `precision_cache` (the workspace's precision
    choices) the encoder's updates take bf16 where it pays on this CPU (policies/rl_encoder.py), decided
    anew at every start; without it, fp32. `sac_encoder`: `agent_class`'s.

    Returns:
        (agent, the step it resumed at: 0 when it started afresh)."""
    from stable_baselines3.common.callbacks import BaseCallback

    last = last_checkpoint(folder)
    if last is None:
        agent, resumed = new_agent(algorithm, env, env_steps, seed, replay_size, sac_encoder, target_entropy), 0
    else:
        agent = without_log_folder(agent_class(algorithm, sac_encoder).load(last / "agent.zip", env=env, device="cpu"))
        if algorithm == "sac":
            from policies.rl_encoder import skip_critic_encoder_in_actor_loss

            agent.load_replay_buffer(last / "replay.pkl")
            skip_critic_encoder_in_actor_loss(agent)
        state = json.loads((last / "state.json").read_text())
        env.episodes_finished, env.successes = state["episodes"], state["successes"]
        resumed = agent.num_timesteps
        agent.set_random_seed(seed + resumed)
    if precision_cache is not None:
        from policies.rl_encoder import encoder_precision

        log.info("%s: %s", algorithm, encoder_precision(agent, precision_cache)[1])

    class Checkpoints(BaseCallback):
        due = resumed + every

        def _on_rollout_start(self) -> None:
            if self.num_timesteps >= self.due and self.num_timesteps < env_steps:
                save_checkpoint(self.model, env, folder)
                self.due = self.num_timesteps + every
            if on_progress is not None:
                on_progress(self.num_timesteps, resumed)

        def _on_step(self) -> bool:
            return True

    agent.learn(total_timesteps=env_steps - resumed, reset_num_timesteps=resumed == 0, callback=Checkpoints())
    return agent, resumed


class RLAgent:
    """A saved baseline, acting deterministically (PPO's most likely action, SAC's mean)."""

    def __init__(self, model, family: str):
        self.model, self.family = model, family

    @classmethod
    def load(cls, algorithm: str, path: Path, family: str) -> RLAgent:
        from stable_baselines3 import PPO, SAC

        return cls({"ppo": PPO, "sac": SAC}[algorithm].load(path, device="cpu"), family)

    def act(self, obs: Observation, embedding: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(agent_observation(obs, embedding), deterministic=True)
        return adapter_action(action, self.family)
