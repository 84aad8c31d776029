"""A rollout worker's memory as it asks for more scenes than it keeps (SIM2ACT_SCENES_PER_WORKER):
one process resets one task of each of a family's scenes in the generalist's specs in turn, `--rounds`
times over, and prints its RSS every `--every` scenes asked. From the repository root:

    .venv/bin/python docs/quality/scene-memory.py                 # MetaWorld's 48, the default cap (16)
    SIM2ACT_SCENES_PER_WORKER=64 .venv/bin/python docs/quality/scene-memory.py --rounds 1   # none closed
    .venv/bin/python docs/quality/scene-memory.py --family robosuite --rounds 1 --every 1   # its 9 scenes
    .venv/bin/python docs/quality/scene-memory.py --family all --rounds 1                  # all 61, capped
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from envs.rollout import _ENVS, close_envs, worker_env  # noqa: E402
from envs.suite import generate_tasks  # noqa: E402
from schemas.config import load_config  # noqa: E402


def rss_mb() -> float:
    """Resident memory in MiB (the docs' "MB" and "GB" are MiB and GiB)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2, help="times over the family's scenes")
    parser.add_argument("--mesh-detail", type=float, default=0.1, help="render.mesh_detail, as the generalist ran")
    parser.add_argument("--family", default="metaworld", choices=["metaworld", "robosuite", "navigation", "all"],
                        help="all: every family's scenes, family after family (what a kept worker meets)")
    parser.add_argument("--every", type=int, default=8, help="print the RSS every this many scenes asked")
    args = parser.parse_args()
    config = load_config("generalist", overrides={"render": {"mesh_detail": args.mesh_detail}})
    scenes = {}
    for task in generate_tasks(config.tasks, seed=config.seed):
        if args.family in (task.family, "all"):
            scenes.setdefault((task.family, task.env_name), task)
    render, started = config.render, time.monotonic()
    print(f"{len(scenes)} {args.family} scenes, {args.rounds} round(s), RSS {rss_mb():.0f} MB at the start")
    for asked, task in enumerate(list(scenes.values()) * args.rounds, 1):
        worker_env(task, render).reset(task, asked)
        if asked % args.every == 0:
            print(f"{asked} scenes asked, {len(_ENVS)} open, RSS {rss_mb():.0f} MB, {time.monotonic() - started:.0f} s",
                  flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    print(f"{asked} scenes asked, {len(_ENVS)} open, RSS {rss_mb():.0f} MB, peak {peak:.0f} MB")
    close_envs()


if __name__ == "__main__":
    main()
