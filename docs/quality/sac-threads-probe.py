"""SAC's training step (an environment step and one update on 64 frames) at 1 and at 2 torch threads, in turns, on
one family's seen tasks of the generalist (84 px, render.mesh_detail 0.1), the agent `new_agent("sac", ...)` builds
as the baselines stage does. Wall ms per training step, past 100 random steps and a warm-up; nothing else should
run (two threads on shared cores wait on each other). From the repository root:

    .venv/bin/python docs/quality/sac-threads-probe.py --family metaworld --steps 60
    .venv/bin/python docs/quality/sac-threads-probe.py --family robosuite --steps 40
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.rl import EMBEDDING_SIZE  # noqa: E402
from envs.gym_env import InstructedTasksEnv  # noqa: E402
from envs.rollout import close_envs  # noqa: E402
from envs.suite import generate_tasks  # noqa: E402
from policies.rl_agent import new_agent  # noqa: E402
from schemas.config import load_config  # noqa: E402
from stages.baselines import planned_agents, rl_budget, target_entropy  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", choices=["metaworld", "robosuite"], default="metaworld")
    parser.add_argument("--steps", type=int, default=60, help="training steps timed per turn")
    parser.add_argument("--turns", type=int, default=2, help="turns of (1 thread, 2 threads)")
    args = parser.parse_args()
    config = load_config("generalist", None, {"render": {"mesh_detail": 0.1}})
    tasks = generate_tasks(config.tasks, config.seed)
    [seen] = [seen for algorithm, family, seen in planned_agents(config, tasks)
              if (algorithm, family) == ("sac", args.family)]
    rng = np.random.default_rng(0)
    said = {text: rng.standard_normal(EMBEDDING_SIZE).astype(np.float32) for task in seen for text in task.instructions}
    env = InstructedTasksEnv(seen, said, config.render, config.randomise, config.baselines.end_on_success)
    budget = rl_budget({"metaworld": 382_023, "robosuite": 455_956}, args.family, {})  # the generalist's
    agent = new_agent("sac", env, budget, config.seed, config.baselines.replay_size, config.baselines.sac_encoder,
                      target_entropy("sac", args.family, config.baselines.sac_target_entropy))
    agent.learning_starts = 100
    torch.set_num_threads(1)
    agent.learn(total_timesteps=100 + args.steps // 4)  # its scenes built, its first updates
    print(f"sac on {args.family}, {len(seen)} seen tasks; wall ms per training step, {args.steps} steps a turn")
    for _ in range(args.turns):
        for threads in (1, 2):
            torch.set_num_threads(threads)
            started = time.monotonic()
            agent.learn(total_timesteps=args.steps, reset_num_timesteps=False)
            print(f"  {threads} thread(s): {(time.monotonic() - started) / args.steps * 1e3:.1f}", flush=True)
    env.close()
    close_envs()  # its scenes' GL contexts before the interpreter's exit ends their display


if __name__ == "__main__":
    main()
