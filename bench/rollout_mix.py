"""`sim2act bench rollout --mix`: the explore stage over a sample of the generalist's mix, full visual
meshes against decimated ones (`render.mesh_detail`), the same episodes on both sides (issue 11 item 2:
explore triplets/s per core over the generalist mix).

1. the sample: per family (robosuite, MetaWorld, navigation), `tasks_per_family` of the preset's
   specs with a seen task, evenly spaced in the preset's order, each spec's first seen task;
2. the decimated meshes made beforehand in a worker (a host makes them once, not once per campaign);
3. the explore stage (`run_explore`, one worker) on a fresh workspace at 1.0, then at `mesh_detail`:
   the same seeds and physics, hence the same steps (checked);
4. per family, from the units the stage registered: steps, the units' seconds (one worker: CPU
   seconds of the one core it holds), steps per core-second, and the ratio of the two sides;
5. over the preset's own mix: the families' rates weighted by the steps the preset explores in each
   (its seen tasks' expert mean episode lengths, as `sim2act run` estimates them), i.e. the explore
   stage's steps per core-second over the whole campaign at each mesh detail.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from pydantic import BaseModel

from bench.rollout import LoadMeter
from bench.tables import table
from schemas.config import CampaignConfig, ExploreConfig, RenderConfig, load_config
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace


class MixSizes(BaseModel):
    preset: str = "generalist"
    tasks_per_family: int = 4  # per family, evenly spaced over the preset's specs with a seen task
    episodes_per_task: int = 8
    episodes_per_shard: int = 8  # one unit per task, the generalist's shard: env creation counted as a campaign pays it
    mesh_detail: float = 0.1


QUICK = MixSizes(tasks_per_family=1, episodes_per_task=1, episodes_per_shard=1)  # 3 tasks, seconds


class FamilyRate(BaseModel):
    family: str
    tasks: int
    episodes: int
    steps: int
    full_s: float  # summed unit seconds at mesh_detail 1.0
    decimated_s: float  # the same at `mesh_detail`

    @property
    def ratio(self) -> float:
        return self.full_s / self.decimated_s if self.decimated_s else 0.0


class MixBench(BaseModel):
    sizes: MixSizes
    tasks: list[str]
    families: list[FamilyRate]
    preset_steps: dict[str, int]  # family -> the steps the preset's iteration 0 explores in it (estimated)
    wall_s: tuple[float, float]  # the stage's wall seconds, 1.0 and decimated
    other_load: tuple[float, float]


def _sample(sizes: MixSizes) -> tuple[CampaignConfig, list[TaskRecord], dict[str, int]]:
    """(the bench's config, its tasks, family -> the steps the preset explores in it)."""
    from envs.suite import generate_tasks
    from schemas.experts import load_expert_table
    from warehouse.capacity import expected_steps

    preset = load_config(sizes.preset, None, {})
    seen = [task for task in generate_tasks(preset.tasks, preset.seed) if task.split == "seen"]
    firsts: dict[str, TaskRecord] = {}
    for task in seen:
        firsts.setdefault(task.spec, task)
    tasks = []
    for family in sorted({task.family for task in firsts.values()}):
        members = [task for task in firsts.values() if task.family == family]
        count = min(sizes.tasks_per_family, len(members))
        tasks += [members[round(i * (len(members) - 1) / max(count - 1, 1))] for i in range(count)]
    config = preset.model_copy(update={
        "name": "bench-mix", "explore": ExploreConfig(episodes_per_task=sizes.episodes_per_task,
                                                      episodes_per_shard=sizes.episodes_per_shard, workers=1)})
    experts = load_expert_table()
    preset_steps: dict[str, int] = {}
    for task in seen:
        preset_steps[task.family] = preset_steps.get(task.family, 0) + round(expected_steps(preset, task, experts))
    return config, tasks, preset_steps


def _explore(root: Path, config: CampaignConfig, tasks: list[TaskRecord], detail: float) -> tuple[dict, float, float]:
    """family -> (tasks, episodes, steps, unit seconds); the stage's wall seconds and the other load."""
    from stages.explore import run_explore
    from warehouse.catalog import Catalog

    workspace = Workspace.at(root / f"detail-{detail:g}").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    config = config.model_copy(update={"render": config.render.model_copy(update={"mesh_detail": detail})})
    meter = LoadMeter()
    run_explore(workspace, config, 0, tasks, None, {})
    wall = time.perf_counter() - meter.wall
    family_of = {t.task_id: t.family for t in tasks}
    per_family: dict[str, list] = {}
    for task_id, episodes, steps, seconds in catalog.query(
            "SELECT e.task_id, count(*), sum(e.num_steps), any_value(u.wall_s) FROM episodes e "
            "JOIN (SELECT unit_key, wall_s FROM stage_runs) u ON u.unit_key = e.shard_key GROUP BY e.task_id, e.shard_key"):
        row = per_family.setdefault(family_of[task_id], [set(), 0, 0, 0.0])
        row[0].add(task_id)
        row[1] += episodes
        row[2] += steps
        row[3] += seconds
    return per_family, wall, meter.other_load()


def bench_mix(sizes: MixSizes, scratch: Path | None = None) -> MixBench:
    """The explore stage over the mix at full and decimated meshes (steps in the module docstring).

    Raises:
        RuntimeError: the two sides explored different steps (the physics differ: a bug)."""
    from bench.rollout import fill_mesh_cache

    config, tasks, preset_steps = _sample(sizes)
    if scratch is not None:
        Path(scratch).mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="sim2act-bench-mix-", dir=scratch))
    try:
        fill_mesh_cache(tasks, config.render.model_copy(update={"mesh_detail": sizes.mesh_detail}))
        full, full_wall, full_load = _explore(root, config, tasks, 1.0)
        decimated, dec_wall, dec_load = _explore(root, config, tasks, sizes.mesh_detail)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    families = []
    for family in sorted(full):
        (names, episodes, steps, full_s), (_, _, dec_steps, dec_s) = full[family], decimated[family]
        if dec_steps != steps:
            raise RuntimeError(f"bench mix: {family} explored {steps} steps at 1.0 and {dec_steps} decimated: "
                               "the same episodes should take the same steps")
        families.append(FamilyRate(family=family, tasks=len(names), episodes=episodes, steps=steps,
                                   full_s=full_s, decimated_s=dec_s))
    return MixBench(sizes=sizes, tasks=[t.task_id for t in tasks], families=families, preset_steps=preset_steps,
                    wall_s=(full_wall, dec_wall), other_load=(full_load, dec_load))


def preset_rates(bench: MixBench) -> tuple[float, float]:
    """Steps per core-second over the preset's mix at 1.0 and at the bench's detail: each family's rate
    weighted by the steps the preset explores in it (seconds per step, summed by share)."""
    rates = {f.family: f for f in bench.families}
    steps = {family: n for family, n in bench.preset_steps.items() if family in rates}
    total = sum(steps.values())
    full = sum(n / total * rates[family].full_s / rates[family].steps for family, n in steps.items())
    decimated = sum(n / total * rates[family].decimated_s / rates[family].steps for family, n in steps.items())
    return 1 / full, 1 / decimated


def markdown(bench: MixBench, command: str) -> str:
    detail = f"{bench.sizes.mesh_detail:g}"
    total = FamilyRate(family="all", tasks=sum(f.tasks for f in bench.families),
                       episodes=sum(f.episodes for f in bench.families), steps=sum(f.steps for f in bench.families),
                       full_s=sum(f.full_s for f in bench.families),
                       decimated_s=sum(f.decimated_s for f in bench.families))
    rows = [[f.family, f.tasks, f.episodes, f"{f.steps:,}", f"{f.steps / f.full_s:.1f}",
             f"{f.steps / f.decimated_s:.1f}", f"{f.ratio:.2f}×"] for f in [*bench.families, total]]
    full, decimated = preset_rates(bench)
    shares = sum(bench.preset_steps.values())
    rows.append([f"the `{bench.sizes.preset}` mix, by its steps ("
                 + ", ".join(f"{family} {n / shares:.0%}" for family, n in sorted(bench.preset_steps.items())) + ")",
                 "", "", "", f"{full:.1f}", f"{decimated:.1f}", f"**{decimated / full:.2f}×**"])
    return "\n".join([
        f"`{command}`: the explore stage, one worker, over {len(bench.tasks)} tasks of the `{bench.sizes.preset}` "
        f"preset ({', '.join(bench.tasks)}), {bench.sizes.episodes_per_task} episodes each, the same seeds on both "
        f"sides (the same steps: checked). Steps per core-second = steps / the units' summed seconds (one worker holds "
        f"one core). Stage wall: {bench.wall_s[0]:.0f} s at 1.0, {bench.wall_s[1]:.0f} s at {detail}; other load "
        f"{bench.other_load[0]:.2f} / {bench.other_load[1]:.2f} cores.", "",
        *table(["family", "tasks", "episodes", "steps", "steps/s per core, meshes 1.0",
                f"steps/s per core, meshes {detail}", "ratio"], rows)]) + "\n"
