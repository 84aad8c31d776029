"""`sim2act bench rollout`: rollout speed of our explore stage against a plain robosuite loop.

Side by side, in one run, the same task, resolution, policy, horizon and episodes (the same
episode seeds, so the same expert noise draws):

- (a) a plain robosuite loop with an 84x84 camera observation, what a user writes by hand:
  `robosuite.make` with its defaults otherwise (hard reset, shadows, reflections, multisampling);
- (b) the same loop without renderer or camera: robosuite's physics, the floor of any wrapper;
- (c) our explore stage end to end (`run_explore`: pool start, env creation, rollouts, Parquet
  shards, catalog registration) on a fresh workspace, with 1 worker and with 2;
- (d) (c) with 1 worker at `render.mesh_detail` < 1: the visual meshes decimated (envs/mesh_detail.py),
  the same physics, hence the same episodes and successes, different pixels.

The policy is the task's scripted expert with the campaign's action noise; in (a) and (b) it
reads robosuite's raw observation through the adapter's own `observe`. (a) and (b) each run in
a fresh process, one after the other; their clock starts at `robosuite.make` (imports and
process start are not counted), (c)'s at the stage call (everything counted).
"""

from __future__ import annotations

import datetime
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from bench.tables import Ratio, cores, ratio_table, table
from envs.pool import run_in_pool
from schemas.config import CampaignConfig, ExploreConfig, RenderConfig, TasksConfig
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace

POLICY = "scripted expert"


class RolloutSizes(BaseModel):
    spec: str = "lift"  # its first task (one colour)
    episodes: int = 48  # enough that the workers' start (~5 s each, in parallel) is a campaign's share of it
    episodes_per_shard: int = 4  # the campaign default
    horizon: int | None = None  # None: the spec's own; episodes also end on success
    image_size: int = 84
    mesh_detail: float = 0.1  # (d)'s render.mesh_detail: the fraction of visual mesh faces drawn


# seconds, for tests and a smoke check; the figures mean little at these sizes
QUICK = RolloutSizes(episodes=2, episodes_per_shard=1, horizon=6)


class LoopCase(BaseModel):
    """One plain robosuite loop, (a) with a camera or (b) without."""

    task: TaskRecord
    camera: str | None
    image_size: int
    noise: float
    seeds: list[int]


class RolloutRow(BaseModel):
    case: str  # a, b, c1, c2, d
    name: str
    workers: int
    episodes: int
    successes: int
    steps: int
    wall_s: float
    cpu_s: float  # user + system time of every process involved
    steps_per_s: float
    steps_per_s_per_core: float  # steps/s over the worker processes (one core each)
    other_load: float  # cores other processes of the machine kept busy meanwhile: above ~0.1 the figures suffer
    note: str = ""


class RolloutBench(BaseModel):
    task_id: str
    env: str
    image_size: int
    horizon: int
    episodes: int
    policy: str
    expert_noise: float
    rows: list[RolloutRow]
    ratios: list[Ratio]


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _machine_busy_s() -> float:
    """CPU seconds all processes of the machine have used since boot (Linux; 0 elsewhere)."""
    try:
        user, nice, system, _, _, irq, softirq = map(int, Path("/proc/stat").read_text().split(maxsplit=8)[1:8])
    except (OSError, ValueError):
        return 0.0
    return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")


class LoadMeter:
    """Wall, our CPU (this process and its reaped children) and the machine's, from creation on."""

    def __init__(self) -> None:
        self.wall, self.machine = time.perf_counter(), _machine_busy_s()
        self.self_cpu, self.children_cpu = time.process_time(), _cpu(resource.RUSAGE_CHILDREN)

    def ours(self) -> float:
        return time.process_time() - self.self_cpu + _cpu(resource.RUSAGE_CHILDREN) - self.children_cpu

    def other_load(self) -> float:
        """Cores the machine's other processes used on average since; call once ours are reaped."""
        return max(0.0, (_machine_busy_s() - self.machine - self.ours()) / (time.perf_counter() - self.wall))


def run_loop(case: LoopCase) -> dict:
    """Worker: the loop a user writes, driving the scripted expert from robosuite's observation."""
    from envs.registry import make_expert
    from envs.robosuite_env import ROBOSUITE_SCENES, finger_bodies, observe  # quiets robosuite's logging too

    import robosuite

    task = case.task
    camera = {"has_offscreen_renderer": False, "use_camera_obs": False} if case.camera is None else {
        "has_offscreen_renderer": True, "use_camera_obs": True, "camera_names": case.camera,
        "camera_heights": case.image_size, "camera_widths": case.image_size,
    }
    started, cpu = time.perf_counter(), time.process_time()
    env = robosuite.make(task.env_name, robots="Panda", has_renderer=False, **camera)
    scene, fingers = ROBOSUITE_SCENES[task.env_name], finger_bodies(env)
    steps = successes = 0
    reset_s = 0.0
    for seed in case.seeds:
        act = make_expert(task, case.noise, np.random.default_rng(seed))
        reset_started = time.perf_counter()
        raw = env.reset()
        reset_s += time.perf_counter() - reset_started
        for _ in range(task.horizon):
            raw, _, _, _ = env.step(act(observe(env, scene, raw, None, fingers)))
            steps += 1
            if env._check_success():
                successes += 1
                break
    wall_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu
    env.close()
    return {"steps": steps, "successes": successes, "wall_s": wall_s, "cpu_s": cpu_s, "reset_s": reset_s}


def _row(case: str, name: str, workers: int, episodes: int, successes: int, steps: int, wall_s: float,
         cpu_s: float, other_load: float, note: str) -> RolloutRow:
    rate = steps / wall_s
    return RolloutRow(case=case, name=name, workers=workers, episodes=episodes, successes=successes, steps=steps,
                      wall_s=wall_s, cpu_s=cpu_s, steps_per_s=rate, steps_per_s_per_core=rate / workers,
                      other_load=other_load, note=note)


def _config(sizes: RolloutSizes, workers: int, mesh_detail: float = 1.0) -> CampaignConfig:
    return CampaignConfig(
        name="bench-rollout", tasks=_tasks_config(sizes),
        render=RenderConfig(image_size=sizes.image_size, mesh_detail=mesh_detail),
        explore=ExploreConfig(episodes_per_task=sizes.episodes, episodes_per_shard=sizes.episodes_per_shard,
                              workers=workers),
    )


def _tasks_config(sizes: RolloutSizes) -> TasksConfig:
    return TasksConfig(specs=[sizes.spec], horizon={sizes.spec: sizes.horizon} if sizes.horizon else {})


def run_stage(task: TaskRecord, sizes: RolloutSizes, workers: int, root: Path, mesh_detail: float = 1.0) -> RolloutRow:
    """(c) and (d): the explore stage on a fresh workspace, timed from the call to its return."""
    from stages.explore import run_explore
    from warehouse.catalog import Catalog

    workspace = Workspace.at(root / f"workers-{workers}-detail-{mesh_detail}").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    meter = LoadMeter()
    result = run_explore(workspace, _config(sizes, workers, mesh_detail), 0, [task], None, {})
    wall_s = time.perf_counter() - meter.wall
    cpu_s = meter.ours()  # the pool's workers are reaped by now
    [(successes, shards)] = catalog.query(
        "SELECT (SELECT count(*) FILTER (WHERE success) FROM episodes), (SELECT count(*) FROM shards)"
    )
    detail = "" if mesh_detail == 1.0 else f", visual meshes at {mesh_detail:g} of their faces"
    return _row("d" if detail else f"c{workers}", f"sim2act explore stage, {workers} worker{'s' * (workers > 1)}{detail}",
                workers, result.episodes, successes, result.steps, wall_s, cpu_s, meter.other_load(),
                f"{shards} Parquet shards written and registered; pool start, imports and env creation counted"
                + ("; the decimated meshes cached beforehand (made once per host)" if detail else ""))


def _make_and_close(case: tuple[TaskRecord, RenderConfig]) -> int:
    from envs.registry import make_env

    task, render = case
    make_env(task.family, task.env_name, render).close()
    return 0


def fill_mesh_cache(tasks: list[TaskRecord], render: RenderConfig) -> None:
    """Decimate the tasks' meshes at `render.mesh_detail` before a clock starts (a host does it once, not
    once per campaign), in a worker process: renderers are made there, never in this one."""
    for _ in run_in_pool(_make_and_close, [(task, render) for task in tasks], workers=1):
        pass  # a generator: the units run as it is drained


def _ratio(name: str, value: float, target: float | None = None) -> Ratio:
    return Ratio.of(name, value, target)


def bench_rollout(sizes: RolloutSizes, scratch: Path | None = None) -> RolloutBench:
    from envs.suite import generate_tasks
    from stages.explore import plan_explore

    task = next(t for t in generate_tasks(_tasks_config(sizes), seed=0) if t.split == "seen")
    config = _config(sizes, workers=1)
    if scratch is not None:  # --scratch names a folder to use: made if missing, like a workspace
        Path(scratch).mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="sim2act-bench-", dir=scratch))
    try:
        # the episodes the stage explores, by seed: the loops run the same ones
        units = plan_explore(config, 0, [task], None, {}, Workspace.at(root / "plan"))
        seeds = [plan.seed for unit in units for plan in unit.episodes]
        rows = []
        for case, camera, name in (("a", config.render.camera, f"plain robosuite loop, {sizes.image_size}px camera"),
                                   ("b", None, "plain robosuite loop, physics only (no renderer)")):
            loop = LoopCase(task=task, camera=camera, image_size=sizes.image_size, noise=config.explore.noise_of(0),
                            seeds=seeds)
            meter = LoadMeter()
            [(_, done, _)] = run_in_pool(run_loop, [loop], workers=1)  # a fresh process each
            rows.append(_row(case, name, 1, len(seeds), done["successes"], done["steps"], done["wall_s"],
                             done["cpu_s"], meter.other_load(),
                             f"robosuite.make defaults (hard_reset); resets {done['reset_s']:.1f} s"))
        rows += [run_stage(task, sizes, workers, root) for workers in (1, 2)]
        fill_mesh_cache([task], RenderConfig(image_size=sizes.image_size, mesh_detail=sizes.mesh_detail))
        rows.append(run_stage(task, sizes, 1, root, sizes.mesh_detail))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    a, b, c1, c2, d = rows
    ratios = [
        _ratio("(c, 1 worker) / (a), per core", c1.steps_per_s_per_core / a.steps_per_s_per_core, 2.0),
        _ratio("(c, 2 workers) / (c, 1 worker)", c2.steps_per_s / c1.steps_per_s, 1.8),
        _ratio("(c, 1 worker) / (b), per core", c1.steps_per_s_per_core / b.steps_per_s_per_core),
        _ratio("(d) / (c, 1 worker)", d.steps_per_s / c1.steps_per_s, 2.0),
    ]
    return RolloutBench(task_id=task.task_id, env=task.env_name, image_size=sizes.image_size, horizon=task.horizon,
                        episodes=len(seeds), policy=POLICY, expert_noise=config.explore.noise_of(0), rows=rows,
                        ratios=ratios)


def markdown(bench: RolloutBench, command: str) -> str:
    lines = [
        "# Rollout benchmark: our explore stage vs a plain robosuite loop",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()}, {cores()} cores, no GPU used. Task `{bench.task_id}` "
        f"({bench.env}), {bench.image_size}px agentview, {bench.episodes} episodes of at most {bench.horizon} steps "
        f"(ending on success), the same episode seeds in every case; policy: the {bench.policy} with action noise "
        f"{bench.expert_noise}, reading robosuite's raw observation through the adapter's `observe` in (a) and (b). "
        "(a) and (b) are timed from `robosuite.make` in a fresh process; (c) and (d) from the stage call, everything "
        "included; (d) has the same physics as (c), so the same episodes and successes. The stage randomises each episode's scene (its default); the plain loops do not. "
        "Cores busy = our CPU time / wall time; other load = cores the machine's other processes kept busy "
        "meanwhile (above ~0.1, the figures are slowed by them).",
        "",
        *table(["case", "what", "steps", "episodes (succeeded)", "wall s", "steps/s", "steps/s per core", "cores busy",
                "other load", "notes"], [
            [r.case, r.name, f"{r.steps:,}", f"{r.episodes} ({r.successes})", f"{r.wall_s:.1f}", f"{r.steps_per_s:.1f}",
             f"{r.steps_per_s_per_core:.1f}", f"{r.cpu_s / r.wall_s:.2f}", f"{r.other_load:.2f}", r.note]
            for r in bench.rows]),
    ]
    return "\n".join([*lines, "", *ratio_table(bench.ratios)]) + "\n"
