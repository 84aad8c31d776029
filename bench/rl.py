"""`sim2act bench rl`: what one environment step of an RL baseline costs, so the baselines stage's
hours are known before it runs.

For each RL agent a campaign's `baselines.agents` trains (stable-baselines3's PPO and SAC, built by
`policies.rl_agent.new_agent` as the stage builds them) and each family with seen tasks, in a fresh
process on one core as a baselines worker runs: the family's instruction-conditioned environment
over its seen tasks (random actions: the environment's own step), then the agent training, its
updates included (SAC past its learning start: a gradient step per environment step). CPU seconds
of the process, so that other work on the machine does not inflate them; wall seconds beside.
With a workspace that holds the campaign's exploration, the agent's budget (the stage's: the
environment steps explored per family) and the hours it makes on one core.
"""

from __future__ import annotations

import datetime
import tempfile
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from bench.tables import table
from schemas.config import CampaignConfig
from schemas.tasks import TaskRecord

EMBEDDING_SIZE = 384  # MiniLM's: random vectors of its size cost what its own do


class RLCase(BaseModel):
    algorithm: str
    family: str
    tasks: list[TaskRecord]  # the family's seen tasks
    config: CampaignConfig  # render, randomise, baselines.replay_size, seed
    steps: int  # timed training steps
    budget: int | None  # the stage's env steps for this agent, when the workspace knows them


class RLStepCost(BaseModel):
    algorithm: str
    family: str
    tasks: int
    steps: int
    env_ms: float  # the environment's own step (random actions), CPU ms
    cpu_ms: float  # a training step, the agent's updates included, CPU ms
    wall_ms: float
    budget: int | None
    precision: str  # its encoder's on batches (train.amp: policies/rl_encoder.py)
    sac_encoder: str | None = None  # SAC's: the critic's shared, or one each (baselines.sac_encoder); PPO: None

    @property
    def agent(self) -> str:
        return self.algorithm if self.sac_encoder is None else f"{self.algorithm} ({self.sac_encoder} encoder)"

    @property
    def budget_hours(self) -> float | None:
        """Hours of one core the agent's budget takes at this cost."""
        return None if self.budget is None else self.budget * self.cpu_ms / 3.6e6


def measure_agent(case: RLCase) -> RLStepCost:
    """Worker: the environment's step, then `case.steps` training steps past the agent's warm-up
    (SAC's random steps before learning starts; PPO's first rollout and update are timed: they are
    what every rollout costs)."""
    from envs.gym_env import InstructedTasksEnv
    from policies.rl_agent import new_agent
    from policies.rl_encoder import encoder_precision
    from stages.baselines import target_entropy

    rng = np.random.default_rng(0)
    said = {text: rng.standard_normal(EMBEDDING_SIZE).astype(np.float32)
            for task in case.tasks for text in task.instructions}
    env = InstructedTasksEnv(case.tasks, said, case.config.render, case.config.randomise,
                             case.config.baselines.end_on_success)
    env.action_space.seed(0)
    env.reset(seed=0)
    env_steps = max(1, case.steps // 2)
    started = time.process_time()
    for _ in range(env_steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    env_ms = (time.process_time() - started) / env_steps * 1e3
    agent = new_agent(case.algorithm, env, case.budget or 400_000, case.config.seed, case.config.baselines.replay_size,
                      case.config.baselines.sac_encoder,
                      target_entropy(case.algorithm, case.family, case.config.baselines.sac_target_entropy))
    precision = "fp32"
    if case.config.train.amp:  # as the stage decides it, measured afresh (a throwaway cache)
        with tempfile.TemporaryDirectory() as scratch:
            precision = encoder_precision(agent, Path(scratch) / "precision.json")[1]
    warmup = getattr(agent, "learning_starts", 0)
    if warmup:
        agent.learning_starts = warmup = min(warmup, 100)  # the budget's start is random steps: only a few here
        agent.learn(total_timesteps=warmup)
    cpu, wall = time.process_time(), time.monotonic()
    agent.learn(total_timesteps=case.steps, reset_num_timesteps=False)
    taken = agent.num_timesteps - warmup  # PPO's whole rollouts may pass the steps asked
    env.close()
    return RLStepCost(algorithm=case.algorithm, family=case.family, tasks=len(case.tasks), steps=taken, env_ms=env_ms,
                      cpu_ms=(time.process_time() - cpu) / taken * 1e3, wall_ms=(time.monotonic() - wall) / taken * 1e3,
                      budget=case.budget, precision=precision,
                      sac_encoder=case.config.baselines.sac_encoder if case.algorithm == "sac" else None)


def rl_cases(config: CampaignConfig, tasks: list[TaskRecord], steps: int, budgets: dict[str, int],
             sac_encoders: list[str] | None = None) -> list[RLCase]:
    """One case per RL agent the campaign's baselines stage would train (an algorithm on a family it
    acts in); SAC's once per `sac_encoders` (baselines.sac_encoder's values; default: the config's),
    side by side."""
    from stages.baselines import planned_agents, rl_budget

    cases = []
    for algorithm, family, seen in planned_agents(config, tasks):
        budget = rl_budget(config.baselines.env_steps, family, budgets) or None
        for encoder in (sac_encoders or [config.baselines.sac_encoder]) if algorithm == "sac" else [None]:
            variant = config if encoder is None else config.model_copy(
                update={"baselines": config.baselines.model_copy(update={"sac_encoder": encoder})})
            cases.append(RLCase(algorithm=algorithm, family=family, tasks=seen, config=variant, steps=steps,
                                budget=budget))
    return cases


def bench_rl(cases: list[RLCase]) -> list[RLStepCost]:
    from envs.pool import run_in_pool

    costs = []
    for case in cases:  # one fresh process per agent, one at a time
        for _, cost, _ in run_in_pool(measure_agent, [case], workers=1):
            costs.append(cost)
    return costs


def markdown(costs: list[RLStepCost], campaign: str, command: str) -> str:
    rows = [[c.agent, c.family, c.tasks, f"{c.env_ms:.1f}", f"{c.cpu_ms:.1f}", f"{c.wall_ms:.1f}",
             f"{1e3 / c.cpu_ms:,.0f}", "–" if c.budget is None else f"{c.budget:,}",
             "–" if c.budget_hours is None else f"{c.budget_hours:.1f}", c.precision] for c in costs]
    lines = [
        "# What an RL baseline's environment step costs",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()} for campaign `{campaign}`: one process on one "
        "core per agent, one at a time; CPU milliseconds of the process per environment step (the environment's "
        "own with random actions, then training with the agent's updates), wall beside them.",
        "",
        *table(["agent", "family", "seen tasks", "env step ms", "training step ms", "wall ms", "steps/s",
                "budget (env steps)", "budget hours, one core", "precision"], rows),
    ]
    return "\n".join(lines) + "\n"
