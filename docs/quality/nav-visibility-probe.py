"""Probe (issue 11 item 4, navigation): how often a navigation evaluation episode starts with its goal out of the
agent's egocentric view, and where the agent then is. The scripted expert plans from the goal's position
(privileged); the policy sees its own 84 px frame and pose alone, so where the goal is out of view it cannot know
which way to go unless the room it stands in says so (in an end room every other room lies one way; in the middle
room it is a guess). No frame is rendered: MuJoCo's ray casting says what the ego camera's pyramid could show.

    python docs/quality/nav-visibility-probe.py                        # the generalist's navigation cases, at start
    python docs/quality/nav-visibility-probe.py --workspace W --model train-...   # and that model's success by class

With --model, each canonical case's evaluation (the campaign's own seeds: stages/evaluate.py) is read back from the
warehouse and its episodes' successes counted per class. A one-off, not part of the product.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter, defaultdict
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.navigation_env import ROOM_SIZE, ROOMS, NavigationEnv, NavigationExpert, room_of  # noqa: E402
from envs.randomisation import sample_randomisation  # noqa: E402
from schemas.keys import derive_seed  # noqa: E402

CLASSES = ("in view", "out of view, its own room", "out of view, one way (an end room)",
           "out of view, either way (the middle room)")


def _seen(env: NavigationEnv, point: np.ndarray, geom: int) -> bool:
    """Whether `point` lies in the ego camera's view pyramid and the first geom a ray meets on the way is `geom`."""
    camera = env.model.camera("ego").id
    origin, frame = env.data.cam_xpos[camera], env.data.cam_xmat[camera].reshape(3, 3)
    towards = point - origin
    local = frame.T @ towards  # camera frame: x right, y up, looking along -z
    half = np.tan(np.deg2rad(env.model.cam_fovy[camera]) / 2)
    if local[2] >= 0 or abs(local[0]) > half * -local[2] or abs(local[1]) > half * -local[2]:
        return False
    hit = np.array([-1], dtype=np.int32)
    mujoco.mj_ray(env.model, env.data, origin, towards, None, 1, env.model.body("agent").id, hit)
    return int(hit[0]) == geom


def goal_in_view(env: NavigationEnv) -> bool:
    kind, colour = env._goals()[env.stage]
    if kind == "room":  # any of a grid of points on the room's floor
        room = env.room_colours.index(colour)
        floor = env.model.geom(f"floor_{room}").id
        return any(_seen(env, np.array([(room + fx) * ROOM_SIZE, fy * ROOM_SIZE, -0.001]), floor)
                   for fx in (0.1, 0.3, 0.5, 0.7, 0.9) for fy in (0.1, 0.3, 0.5, 0.7, 0.9))
    index = [c for (shape, c) in env.objects if shape == kind].index(colour)
    geom = env.model.geom(f"{kind}_{index}_geom").id
    centre = env.data.geom_xpos[geom]
    return any(_seen(env, centre + offset, geom) for offset in ([0, 0, 0], [0, 0, 0.15], [0, 0, -0.15]))


def start_class(env: NavigationEnv) -> str:
    if goal_in_view(env):
        return CLASSES[0]
    here, there = room_of(env.data.qpos[0]), room_of(env.goal_point()[0])
    if here == there:
        return CLASSES[1]
    return CLASSES[2] if here in (0, ROOMS - 1) else CLASSES[3]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, help="a workspace whose evaluations of --model are read")
    parser.add_argument("--model", help="a model key evaluated on the generalist's cases")
    parser.add_argument("--campaign", default="generalist", help="the campaign the evaluation seeds derive from")
    args = parser.parse_args()
    from schemas.config import CampaignConfig, preset_dict

    config = CampaignConfig.model_validate(preset_dict("generalist"))
    from envs.suite import generate_tasks

    tasks = [t for t in generate_tasks(config.tasks, config.seed) if t.family == "navigation"]
    outcomes: dict[tuple[str, str], list[bool]] = {}
    if args.model:
        from warehouse.catalog import Catalog
        from schemas.workspace import Workspace

        catalog = Catalog(Workspace(args.workspace).catalog)
        rows = catalog.query("SELECT task_id, split, episode_successes FROM evaluations WHERE model_key = ? "
                             "AND family = 'navigation' AND split IN ('seen', 'unseen')", [args.model])
        outcomes = {(task_id, split): list(successes) for task_id, split, successes in rows}
    counts: dict[str, Counter] = defaultdict(Counter)
    wins: dict[str, Counter] = defaultdict(Counter)
    tried: dict[str, Counter] = defaultdict(Counter)
    steps: dict[str, Counter] = defaultdict(Counter)  # the noiseless expert's steps from each start, by class
    envs: dict[str, NavigationEnv] = {}
    for task in tasks:
        env = envs.setdefault(task.env_name, NavigationEnv(task.env_name, None))
        for episode in range(config.evaluate.episodes_per_task):
            seed = derive_seed(args.campaign, config.seed, "evaluate", task.task_id, episode)
            env.reset(task, seed, sample_randomisation(config.randomise, seed, env.RANDOMISES))
            kind = start_class(env)
            obs, expert = env._observation(), NavigationExpert(0.0, np.random.default_rng(seed))
            for _ in range(task.horizon):
                now = start_class(env)
                steps[task.spec][now] += 1
                steps["all"][now] += 1
                obs, _, success = env.step(expert.act(obs))
                if success:
                    break
            counts[task.spec][kind] += 1
            counts["all"][kind] += 1
            result = outcomes.get((task.task_id, task.split))
            if result is not None and episode < len(result):
                for group in (task.spec, "all"):
                    tried[group][kind] += 1
                    wins[group][kind] += bool(result[episode])
    print("| spec | " + " | ".join(CLASSES) + " |")
    print("|---|" + "---|" * len(CLASSES))
    for group in sorted(counts, key=lambda g: (g == "all", g)):
        cells = []
        for kind in CLASSES:
            cell = f"{counts[group][kind]}/{sum(counts[group].values())}"
            if tried[group][kind]:
                cell += f", success {wins[group][kind]}/{tried[group][kind]} = {wins[group][kind] / tried[group][kind]:.0%}"
            cells.append(cell)
        print(f"| {group} | " + " | ".join(cells) + " |")
    print("\nThe noiseless expert's steps from the same starts, by what the agent could see at each:\n")
    print("| spec | " + " | ".join(CLASSES) + " |")
    print("|---|" + "---|" * len(CLASSES))
    for group in sorted(steps, key=lambda g: (g == "all", g)):
        total = sum(steps[group].values())
        print(f"| {group} | " + " | ".join(f"{steps[group][kind]:,} ({steps[group][kind] / total:.0%})"
                                          for kind in CLASSES) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
