"""`sim2act bench rollout --mix`: the explore stage over a sample of the generalist's mix, as it was
(full visual meshes, robosuite's arm controller at every substep), with decimated meshes
(`render.mesh_detail`), with the fused substeps beside them (envs/robosuite_control.py), and with the
colliding meshes drawn decimated too (`render.decimate_colliding`), the same episodes on every side
(issue 11 item 2: explore triplets/s per core over the generalist mix).

1. the sample: per family (robosuite, MetaWorld, navigation), `tasks_per_family` of the preset's
   specs with a seen task, evenly spaced in the preset's order, each spec's first seen task;
2. the decimated meshes made beforehand in a worker (a host makes them once, not once per campaign);
3. the explore stage (`run_explore`, one worker) on a fresh workspace per side (`sides`), twice on
   the same worker: cold (each unit makes its task's environment, as a run of one unit per task pays
   it; the worker's own start, its imports, lands in its first unit), then warm (the same episodes
   again, the environments made: as a campaign pays it, its kept workers reusing each environment
   over every later unit, `envs.pool.keep_workers`); the same seeds and physics, hence the same
   steps (checked);
4. per family, from the units the stage registered: steps, the units' seconds (one worker: CPU
   seconds of the one core it holds), steps per core-second, and each side's ratio to the first;
5. over the preset's own mix: the families' rates weighted by the steps the preset explores in each
   (its seen tasks' expert mean episode lengths, as `sim2act run` estimates them), i.e. the explore
   stage's steps per core-second over the whole campaign on each side, cold and warm.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from pydantic import BaseModel

from bench.rollout import LoadMeter
from bench.tables import table
from envs.robosuite_control import controller_path
from schemas.config import CampaignConfig, ExploreConfig, RenderConfig, load_config
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace


class MixSizes(BaseModel):
    preset: str = "generalist"
    tasks_per_family: int = 4  # per family, evenly spaced over the preset's specs with a seen task
    episodes_per_task: int = 8
    episodes_per_shard: int = 8  # one unit per task (cold: it makes the environment), the generalist's shard
    mesh_detail: float = 0.1


QUICK = MixSizes(tasks_per_family=1, episodes_per_task=1, episodes_per_shard=1)  # 3 tasks, seconds


class Side(BaseModel):
    label: str  # the table's column heading
    mesh_detail: float  # render.mesh_detail
    fused_control: bool  # robosuite's substeps through envs/robosuite_control (False: robosuite's own path)
    decimate_colliding: bool = False  # render.decimate_colliding: the colliding meshes drawn decimated too

    def render(self, render: RenderConfig) -> RenderConfig:
        return render.model_copy(update={"mesh_detail": self.mesh_detail,
                                         "decimate_colliding": self.decimate_colliding})

    @property
    def name(self) -> str:
        """The side's workspace folder name."""
        return (f"side-{self.mesh_detail:g}{'-colliding' if self.decimate_colliding else ''}"
                f"-{'fused' if self.fused_control else 'stock'}")


def sides(sizes: MixSizes) -> list[Side]:
    """The explore stage as it was (the baseline), with decimated meshes, with the fused substeps too, and with
    the colliding meshes drawn decimated as well."""
    detail = f"{sizes.mesh_detail:g}"
    return [Side(label="meshes 1.0, robosuite's controller", mesh_detail=1.0, fused_control=False),
            Side(label=f"meshes {detail}", mesh_detail=sizes.mesh_detail, fused_control=False),
            Side(label=f"meshes {detail}, fused substeps", mesh_detail=sizes.mesh_detail, fused_control=True),
            Side(label=f"meshes {detail} colliding ones too, fused substeps", mesh_detail=sizes.mesh_detail,
                 fused_control=True, decimate_colliding=True)]


class FamilyRate(BaseModel):
    family: str
    tasks: int
    episodes: int
    steps: int
    seconds: list[float]  # summed unit seconds on each side, cold (the units made their environments), in the order of sides
    warm_seconds: list[float]  # the same units again on the same worker, its environments already made

    def phase_seconds(self, warm: bool) -> list[float]:
        return self.warm_seconds if warm else self.seconds


class MixBench(BaseModel):
    sizes: MixSizes
    sides: list[Side]
    tasks: list[str]
    families: list[FamilyRate]
    preset_steps: dict[str, int]  # family -> the steps the preset's iteration 0 explores in it (estimated)
    wall_s: list[float]  # the stage's wall seconds on each side, cold and warm together
    other_load: list[float]  # cores the machine's other processes kept busy meanwhile, on each side


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


def _per_family(catalog, tasks: list[TaskRecord]) -> dict[str, list]:
    """family -> [task ids, episodes, steps, the units' summed seconds], from a workspace's catalog."""
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
    return per_family


def _explore(root: Path, config: CampaignConfig, tasks: list[TaskRecord], side: Side) -> tuple[dict, dict, float, float]:
    """(family -> [task ids, episodes, steps, unit seconds], cold; the same, warm; the two stages'
    wall seconds; the other load)."""
    from envs.pool import keep_workers
    from stages.explore import run_explore
    from warehouse.catalog import Catalog

    config = config.model_copy(update={"render": side.render(config.render)})
    runs = []
    # the stage's workers are spawned and inherit the controller path; both runs on one kept worker
    with controller_path(stock=not side.fused_control), keep_workers():
        meter = LoadMeter()
        for phase in ("cold", "warm"):
            workspace = Workspace.at(root / f"{side.name}-{phase}").create()
            catalog = Catalog(workspace.catalog)
            catalog.initialise()
            run_explore(workspace, config, 0, tasks, None, {})
            runs.append(_per_family(catalog, tasks))
        wall = time.perf_counter() - meter.wall
    return runs[0], runs[1], wall, meter.other_load()


def bench_mix(sizes: MixSizes, scratch: Path | None = None) -> MixBench:
    """The explore stage over the mix on each side (steps in the module docstring).

    Raises:
        RuntimeError: two sides explored different steps (the physics differ: a bug); or called inside
            keep_workers, whose one pool would serve every side (its worker spawned with the first
            side's controller path, and every side after the first warm)."""
    from bench.rollout import fill_mesh_cache
    from envs.pool import keeping_workers

    if keeping_workers():
        raise RuntimeError("bench mix: expected a fresh worker per side, got a caller's keep_workers pool")

    config, tasks, preset_steps = _sample(sizes)
    if scratch is not None:
        Path(scratch).mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="sim2act-bench-mix-", dir=scratch))
    try:
        fill_mesh_cache(tasks, sides(sizes)[-1].render(config.render))  # every decimated mesh any side draws
        runs = [_explore(root, config, tasks, side) for side in sides(sizes)]
    finally:
        shutil.rmtree(root, ignore_errors=True)
    families = []
    for family in sorted(runs[0][0]):
        names, episodes, steps, _ = runs[0][0][family]
        for side, (cold, warm, _, _) in zip(sides(sizes), runs):
            for phase, per_family in (("cold", cold), ("warm", warm)):
                if per_family[family][2] != steps:
                    raise RuntimeError(f"bench mix: {family} explored {steps} steps at first and {per_family[family][2]} "
                                       f"with {side.label} ({phase}): the same episodes should take the same steps")
        families.append(FamilyRate(family=family, tasks=len(names), episodes=episodes, steps=steps,
                                   seconds=[cold[family][3] for cold, _, _, _ in runs],
                                   warm_seconds=[warm[family][3] for _, warm, _, _ in runs]))
    return MixBench(sizes=sizes, sides=sides(sizes), tasks=[t.task_id for t in tasks], families=families,
                    preset_steps=preset_steps, wall_s=[run[2] for run in runs], other_load=[run[3] for run in runs])


def preset_rates(bench: MixBench, warm: bool = False) -> list[float]:
    """Steps per core-second over the preset's mix on each side, cold or warm: each family's rate
    weighted by the steps the preset explores in it (seconds per step, summed by share)."""
    rates = {f.family: f for f in bench.families}
    steps = {family: n for family, n in bench.preset_steps.items() if family in rates}
    total = sum(steps.values())
    return [1 / sum(n / total * rates[family].phase_seconds(warm)[i] / rates[family].steps for family, n in steps.items())
            for i in range(len(bench.sides))]


def _rows(bench: MixBench, warm: bool) -> list[list]:
    """The table's rows, cold or warm: per family, all of them, and the preset's mix."""
    total = FamilyRate(family="all", tasks=sum(f.tasks for f in bench.families),
                       episodes=sum(f.episodes for f in bench.families), steps=sum(f.steps for f in bench.families),
                       seconds=[sum(f.seconds[i] for f in bench.families) for i in range(len(bench.sides))],
                       warm_seconds=[sum(f.warm_seconds[i] for f in bench.families) for i in range(len(bench.sides))])
    rows = [[f.family, f.tasks, f.episodes, f"{f.steps:,}", *(f"{f.steps / s:.1f}" for s in f.phase_seconds(warm)),
             *(f"{f.phase_seconds(warm)[0] / s:.2f}×" for s in f.phase_seconds(warm)[1:])]
            for f in [*bench.families, total]]
    rates = preset_rates(bench, warm)
    shares = sum(bench.preset_steps.values())
    rows.append([f"the `{bench.sizes.preset}` mix, by its steps ("
                 + ", ".join(f"{family} {n / shares:.0%}" for family, n in sorted(bench.preset_steps.items())) + ")",
                 "", "", "", *(f"{rate:.1f}" for rate in rates), *(f"**{rate / rates[0]:.2f}×**" for rate in rates[1:])])
    return rows


def markdown(bench: MixBench, command: str) -> str:
    headings = ["family", "tasks", "episodes", "steps", *(f"steps/s per core, {side.label}" for side in bench.sides),
                *(f"{side.label} / the first" for side in bench.sides[1:])]
    walls = ", ".join(f"{wall:.0f} s" for wall in bench.wall_s)
    loads = " / ".join(f"{load:.2f}" for load in bench.other_load)
    return "\n".join([
        f"`{command}`: the explore stage, one worker, over {len(bench.tasks)} tasks of the `{bench.sizes.preset}` "
        f"preset ({', '.join(bench.tasks)}), {bench.sizes.episodes_per_task} episodes each, the same seeds on every "
        f"side (the same steps: checked). Steps per core-second = steps / the units' summed seconds (one worker holds "
        f"one core). Stage wall per side, cold and warm together: {walls}; other load {loads} cores.", "",
        "**Warm** (the worker's environments already made, as a campaign's kept workers explore every unit after "
        "their first):", "", *table(headings, _rows(bench, warm=True)), "",
        "**Cold** (each unit makes its task's environment: imports, model compilation, GL upload counted):", "",
        *table(headings, _rows(bench, warm=False))]) + "\n"
