"""Probe (issue 11 item 1): re-run a workspace's expert-explored episodes in a fresh process and compare each one's
length and success with what the warehouse recorded. Same code, same CPU: every episode should come out the same
(an episode depends on its seed alone); a difference under another BLAS kernel (OPENBLAS_CORETYPE) says how a
marginal episode's outcome hangs on the last bits of the robot controller's small matrix products, which OpenBLAS
computes with the kernels of the CPU it finds (an AVX-512 host gets other kernels than an AVX2 one).

    python docs/quality/explore-rerun-probe.py --workspace W --preset generalist --set render.mesh_detail=0.1
    OPENBLAS_CORETYPE=Sandybridge python docs/quality/explore-rerun-probe.py --workspace W ...   # another kernel

Default: the failed expert episodes of iteration 0 whose task id starts with one of --tasks (robosuite's nut and
pick-and-place tasks, where the generalist's failures are). No camera: the experts act on state, so no frame is
drawn (the physics does not depend on it: the generalist's 55 failed episodes, explored with cameras, came out the same
from this probe on the exploring CPU's kernels). A one-off, not part of the product.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True, help="the campaign's workspace (read only)")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="as sim2act run's")
    parser.add_argument("--tasks", nargs="+", default=["nut-", "pick-place-"], help="task id prefixes to re-run")
    parser.add_argument("--all", action="store_true", help="every episode of those tasks, not only the failed")
    args = parser.parse_args()

    from envs.randomisation import sample_randomisation
    from envs.rollout import rollout, worker_env
    from schemas.config import load_config, parse_settings
    from schemas.workspace import Workspace
    from stages.explore import _explorer, plan_explore
    from stages.generate_tasks import campaign_tasks
    from warehouse.catalog import Catalog

    config = load_config(args.preset, None, parse_settings(args.set))
    workspace = Workspace.at(args.workspace)
    recorded = {episode_id: (steps, success) for episode_id, steps, success in Catalog(workspace.catalog).query(
        "SELECT episode_id, num_steps, success FROM episodes WHERE campaign = ? AND iteration = 0", [config.name])}
    tasks, _ = campaign_tasks(workspace, config)
    units = plan_explore(config, 0, tasks, None, {}, workspace)
    chosen = [(unit, plan) for unit in units if unit.task.task_id.startswith(tuple(args.tasks))
              for plan in unit.episodes if plan.episode_id in recorded and (args.all or not recorded[plan.episode_id][1])]
    if not chosen:
        print(f"expected recorded episodes of tasks starting with {args.tasks} in {args.workspace}, got none "
              "(another campaign's --preset/--set, or its iteration 0 not explored yet?)", file=sys.stderr)
        return 2
    kernel = os.environ.get("OPENBLAS_CORETYPE", "the CPU's")
    print(f"re-running {len(chosen)} episodes; OpenBLAS kernels: {kernel}")
    same, steps, start = 0, 0, time.time()
    for unit, plan in chosen:
        env = worker_env(unit.task, None)  # one camera-less scene per env, kept across episodes as a worker keeps it
        randomisation = sample_randomisation(unit.randomise, plan.seed, env.RANDOMISES)
        rows, _, success = rollout(env, unit.task, plan.seed, _explorer(unit, plan, None).act, randomisation)
        was, now = recorded[plan.episode_id], (len(rows), success)
        same += now == was
        steps += len(rows)
        if now != was:
            print(f"{plan.episode_id}: recorded {was[0]} steps, success {was[1]}; now {len(rows)} steps, success {success}")
    print(f"{same} of {len(chosen)} the same; {steps:,} steps in {time.time() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
