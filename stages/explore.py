"""explore: rollouts in the simulators, one unit = one shard of K episodes of one task.

Each step becomes a triplet (o_t, l, a_t, o_{t+1}) with reward, done and success, plus the
MuJoCo state for replay and the expert's label. Iteration 0 explores with the noisy scripted
expert (and a VLM, if configured); later iterations mix in the redeployed policy. Workers write
shards; this process registers them.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Callable, Iterator

import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from envs.observation import Observation
from envs.pool import Progress, interleaved, run_in_pool
from envs.registry import ACHIEVED_TESTS
from envs.rollout import Act, Explorer, rollout, worker_env
from policies.openai_chat import ChatUnavailable
from schemas.config import (RENDER_LEGACY_VALUES, CampaignConfig, RandomiseConfig, RenderConfig, VlmExplorerConfig,
                            render_key_fields)
from schemas.frames import encode_depth, encode_frame
from schemas.keys import derive_seed, key_fields, unit_key
from schemas.tables import EPISODES, STEPS
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from warehouse.catalog import Catalog
from warehouse.priority import TaskPriority, plan_priorities
from warehouse.shard_writer import ShardFile, write_shard
from warehouse.store import FOLDER, open_store

STAGE, VERSION = "explore", 4  # 4: the pick-and-place expert catches up with a hand already at the object
EXPERT, VLM = "expert", "vlm"
CHAINED = "via subtasks"  # suffix of the champion's name on the episodes it explores by chaining sub-tasks
# Fields added after VERSION, at the value that does what the stage did before them (stages/train.py)
LEGACY_VALUES = {"curriculum": False, "relabel": False, "expert_takeover": 0.0, "policy_steps": None,
                 "first_episodes_per_task": None}
log = logging.getLogger("sim2act.stages.explore")


class PolicyExplorer(BaseModel):
    """The redeployed policy: where its checkpoint is and what to call it in the warehouse."""

    name: str  # e.g. "policy:sim2act-smoke/1"
    model_key: str
    checkpoint: str  # a file on the flow's host (evaluation and adaptation load it there)
    # where rollout workers fetch it when the shard store is S3 (they share no folder with the flow)
    worker_checkpoint: str | None = None


class EpisodePlan(BaseModel):
    episode_id: str
    seed: int
    instruction: str
    explorer: str
    expert_noise: float | None  # the expert's noise level, when the expert explores this episode
    subgoals: list[str] = []  # chaining: the instruction the policy follows for each goal the environment pursues


class ExploreUnit(BaseModel):
    unit_key: str
    workspace: str
    campaign: str
    iteration: int
    task: TaskRecord
    shard: int
    render: RenderConfig
    randomise: RandomiseConfig
    expert_labels: bool
    episodes: list[EpisodePlan]
    policy: PolicyExplorer | None
    vlm: VlmExplorerConfig | None
    # instruction -> embedding, only the few this unit's episodes say (small vectors)
    embeddings: dict[str, list[float]]
    relabel_to: list[TaskRecord] = []  # explore.relabel: the seen tasks a failed episode may have done instead
    expert_takeover: float = 0.0  # explore.expert_takeover: the share of the policy's steps the expert drives
    policy_steps: int | None = None  # explore.policy_steps: the policy's episodes end after this many steps
    # where the warehouse keeps shards (warehouse/store.py; not part of the key): a worker, which has no
    # catalog, writes there with the credentials of its own environment
    shard_store: str = FOLDER


class ExploreResult(StageResult):
    unit_keys: list[str]
    episodes: int  # explored by this run (0 when every shard was registered)
    steps: int
    skipped_units: int
    priorities: list[TaskPriority]  # how the budget was shared (empty: equal shares, no champion to rank by)

    def did_work(self) -> bool:
        return self.skipped_units < len(self.unit_keys)

    def metrics(self) -> dict[str, float]:
        if not self.episodes:
            return {}
        return {"explore.episodes": self.episodes, "explore.triplets": self.steps,
                **{f"explore.episodes.{p.task_id}": p.episodes for p in self.priorities},
                **{f"explore.priority.{p.task_id}": p.score for p in self.priorities}}


def _explorers(config: CampaignConfig, iteration: int, task: TaskRecord, policy: PolicyExplorer | None,
               count: int) -> list[str]:
    """Who explores each of a task's `count` episodes: the policy takes its share (iterations >= 1),
    the VLM its share of the rest, the expert the remainder; drawn from the task's seed."""
    explore = config.explore
    rng = np.random.default_rng(derive_seed(config.name, config.seed, iteration, task.task_id, "explorers"))
    order = rng.permutation(count).tolist()
    explorers = [EXPERT] * count
    n_policy = round(explore.policy_fraction * count) if policy else 0
    n_vlm = round(explore.vlm_fraction * (count - n_policy)) if explore.vlm else 0
    for index in order[:n_policy]:
        explorers[index] = policy.name
    for index in order[n_policy:n_policy + n_vlm]:
        explorers[index] = f"{VLM}:{explore.vlm.model}"
    return explorers


def plan_explore(
    config: CampaignConfig,
    iteration: int,
    tasks: list[TaskRecord],
    policy: PolicyExplorer | None,
    embeddings: dict[str, np.ndarray],
    workspace: Workspace,
    episodes_of: dict[str, int] | None = None,
    subgoals_of: dict[str, list[str]] | None = None,
) -> list[ExploreUnit]:
    """Pure: the shards this iteration explores, `episodes_of[task_id]` episodes per seen task
    (default: explore.episodes_at(iteration) each). Unseen tasks are never explored. Under
    explore.curriculum a task with sub-tasks (`subgoals_of[task_id]`: their instructions) is
    explored only by the policy chaining them, so not at all before there is one."""
    explore = config.explore
    takeover = explore.takeover_of(iteration)
    policy_steps = explore.policy_steps if policy else None  # only where a policy explores
    reads = {
        "campaign": config.name, "seed": config.seed, "iteration": iteration,
        "render": render_key_fields(config.render),
        "randomise": config.randomise,
        # what is in effect at this iteration, not the config: the takeover share, not its schedule (changing
        # a later level redoes only the iterations from that one on); policy_steps only where a policy explores;
        # the iteration's own episode count (iteration 0 is the same work with first_episodes_per_task or without)
        "explore": key_fields(explore.model_copy(update={"expert_takeover": takeover,
                                                         "policy_steps": policy_steps,
                                                         "episodes_per_task": explore.episodes_at(iteration),
                                                         "first_episodes_per_task": None}),
                              {"workers", "dask_address"}, LEGACY_VALUES),
        "policy": policy.model_key if policy else None,
    }
    units = []
    for task in (t for t in tasks if t.split == "seen"):
        subgoals = (subgoals_of or {}).get(task.task_id, []) if explore.curriculum else []
        if subgoals and policy is None:
            continue
        count = explore.episodes_at(iteration) if episodes_of is None else episodes_of[task.task_id]
        explorer_of = [f"{policy.name} {CHAINED}"] * count if subgoals else _explorers(config, iteration, task, policy, count)
        # the noise schedule runs over the expert's own episodes: each level gets its share
        expert_rank = {index: rank for rank, index in enumerate(i for i, e in enumerate(explorer_of) if e == EXPERT)}
        relabel_to = [t for t in tasks if explore.relabel and t.split == "seen" and t.env_name == task.env_name
                      and t.task_id != task.task_id]
        test = ACHIEVED_TESTS.get((task.family, task.env_name))  # a scene whose test came after units were keyed
        can_relabel = bool(relabel_to) and (test is not None or task.family == "navigation")  # a scene that can tell
        for shard, first in enumerate(range(0, count, explore.episodes_per_shard)):
            # where relabelling can happen: the scene's test, the tasks a failure may be filed under (a changed task
            # set, e.g. a colour held out, changes them), and the relabelled episodes' rewards made the achieved
            # task's sparse ones (units explored before keep their keys and their episodes' dense rewards)
            relabelling = [*([f"achieved test {test}"] if test else []), "relabelled rewards sparse",
                           "relabel to " + ",".join(sorted(t.task_id for t in relabel_to))] if can_relabel else []
            key = unit_key(STAGE, VERSION, reads, [task.model_dump_json(), str(shard), str(count), *relabelling])
            episodes = []
            for index in range(first, min(first + explore.episodes_per_shard, count)):
                seed = derive_seed(config.name, config.seed, iteration, task.task_id, shard, index)
                instruction = task.instructions[np.random.default_rng(seed).integers(len(task.instructions))]
                episode_id = f"{config.name}-i{iteration}-{task.task_id}-{key[-8:]}-e{index:03d}"
                episodes.append(EpisodePlan(episode_id=episode_id, seed=seed, instruction=instruction,
                                            explorer=explorer_of[index], subgoals=subgoals,
                                            expert_noise=explore.noise_of(expert_rank[index]) if index in expert_rank else None))
            said = {e.instruction for e in episodes if policy and e.explorer == policy.name} | set(subgoals)
            units.append(
                ExploreUnit(
                    unit_key=key, workspace=str(workspace.root), campaign=config.name, iteration=iteration,
                    task=task, shard=shard, render=config.render, randomise=config.randomise,
                    expert_labels=explore.expert_labels, episodes=episodes,
                    policy=policy, vlm=explore.vlm,
                    # a sub-task the campaign does not hold has no cached embedding: the policy encodes it
                    embeddings={text: embeddings[text].tolist() for text in said if text in embeddings},
                    # seen tasks only: a held-out task is never trained on, relabelled or not
                    relabel_to=relabel_to,
                    expert_takeover=takeover,
                    policy_steps=policy_steps,
                )
            )
    return units


# -- worker side ------------------------------------------------------------------------------

def _explorer(unit: ExploreUnit, plan: EpisodePlan, policy) -> Explorer:
    from envs.registry import make_expert

    if plan.explorer == EXPERT:
        noise = plan.expert_noise
        return Explorer(act=make_expert(unit.task, noise, np.random.default_rng(plan.seed)),
                        stats=lambda: {"expert_noise": noise})
    if plan.explorer.startswith(f"{VLM}:"):
        from policies.vlm_explorer import VlmExplorer

        vlm = VlmExplorer(unit.vlm, unit.task.family, plan.instruction)
        return Explorer(act=vlm.act, stats=vlm.stats)
    actor = policy.episode(unit.task.family)  # a chunked policy keeps its chunks per episode
    if plan.subgoals:
        def follow_subgoals(obs: Observation) -> np.ndarray:
            goal = min(int(obs.privileged["stage"][0]), len(plan.subgoals) - 1)
            return actor(obs, plan.subgoals[goal]).action

        return Explorer(act=follow_subgoals)
    return Explorer(act=lambda obs: actor(obs, plan.instruction).action)


def _labeller(unit: ExploreUnit, plan: EpisodePlan) -> Act | None:
    """The noiseless expert, following along whoever explores (its own rng: the explorer's
    draws, and so the episode, do not depend on whether labels are recorded); none where the
    curriculum withholds it (a chained episode)."""
    from envs.registry import make_expert

    labelled = unit.expert_labels and not plan.subgoals
    return make_expert(unit.task, 0.0, np.random.default_rng([plan.seed, 1])) if labelled else None


def expert_takeover(policy_act: Act, expert_act: Act, share: float, rng: np.random.Generator) -> tuple[Explorer, Act]:
    """DAgger's mixture (Ross et al. 2011, beta): at each step the expert's action is executed with
    probability `share`, else the policy's; both are asked at every state in the rollout's order (the
    actor, then the labeller), so the policy's chunks stay in step and the stateful expert sees every
    state once. -> (the explorer, whose stats count the steps the expert drove; the labeller, which
    returns the expert action the explorer just asked for)."""
    asked: list[np.ndarray] = []
    driven = [0, 0]  # steps the expert drove, steps in all

    def act(obs: Observation) -> np.ndarray:
        policy_action = policy_act(obs)  # every step: a chunked policy keeps its queue in step
        expert_action = np.asarray(expert_act(obs), dtype=np.float32)
        asked.append(expert_action)
        driven[1] += 1
        if rng.random() < share:
            driven[0] += 1
            return expert_action
        return policy_action

    def label(obs: Observation) -> np.ndarray:
        return asked.pop()

    return (Explorer(act=act, stats=lambda: {"expert_takeover": share, "expert_steps": driven[0], "steps": driven[1]}),
            label)


def relabel(rows: list[dict], achieved: TaskRecord, plan: EpisodePlan, intended: TaskRecord,
            stats: dict | None) -> tuple[dict, dict, bool]:
    """Hindsight relabelling of a failed episode that ended doing `achieved` instead: -> (the task and
    instruction its rows are recorded under, its explorer_stats naming what it set out to do, success).
    The instruction is one of the achieved task's, drawn from the episode's seed; the rows' expert labels
    are dropped (they led to the intended goal: the executed actions are what reached this one) and the
    last step succeeds. The rewards become the achieved task's sparse ones (0, then 1 at the last step):
    the recorded ones measured progress toward the intended goal (navigation's often negative, away from
    it), which the filter's min_return would have read as this success's return."""
    instruction = achieved.instructions[np.random.default_rng([plan.seed, 2]).integers(len(achieved.instructions))]
    for row in rows:
        row["expert_action"] = None
        row["reward"] = 0.0
    rows[-1]["success"] = True
    rows[-1]["reward"] = 1.0
    return ({"task_id": achieved.task_id, "instruction": instruction},
            {**(stats or {}), "relabelled_from": intended.task_id, "intended_instruction": plan.instruction}, True)


def _depth_bytes(depth: np.ndarray | None) -> bytes | None:
    return None if depth is None else encode_depth(depth)


def run_explore_unit(unit: ExploreUnit) -> list[ShardFile]:
    """Worker: roll out the unit's episodes and write its episodes and steps shards."""
    from envs.randomisation import sample_randomisation

    policy = None
    if unit.policy is not None:
        from policies.policy import Policy

        checkpoint = open_store(Workspace.at(unit.workspace).warehouse, unit.shard_store).fetch(
            unit.policy.worker_checkpoint or unit.policy.checkpoint)
        policy = Policy.load(checkpoint,
                             {text: np.asarray(vector, dtype=np.float32) for text, vector in unit.embeddings.items()})
    env = worker_env(unit.task, unit.render)
    episode_rows, step_rows = [], []
    common = {"campaign": unit.campaign, "iteration": unit.iteration, "task_id": unit.task.task_id}
    for plan in unit.episodes:
        error = None
        randomisation = sample_randomisation(unit.randomise, plan.seed, env.RANDOMISES)
        explorer, label = _explorer(unit, plan, policy), _labeller(unit, plan)
        if unit.expert_takeover > 0 and label is not None and unit.policy and plan.explorer == unit.policy.name:
            explorer, label = expert_takeover(explorer.act, label, unit.expert_takeover,
                                              np.random.default_rng([plan.seed, 3]))
        try:
            own = unit.policy is not None and plan.explorer == unit.policy.name  # not a chained episode
            rows, final, success = rollout(env, unit.task, plan.seed, explorer.act, randomisation, label,
                                           steps=unit.policy_steps if own else None)
        except ChatUnavailable as exc:
            # the endpoint's failure, not the episode's: recorded, it would stay failed under this unit's key for
            # good; the unit fails instead (nothing written), and the same command redoes it once the endpoint answers
            fix = ("it refused the request: check explore.vlm (url, model, api_key_env)" if exc.refused else
                   "start it")
            raise ChatUnavailable(f"explore: {exc}: {fix} (or set explore.vlm_fraction=0), then run the same "
                                  "command again to resume", exc.failures, exc.refused) from None
        except Exception as exc:  # a simulator (or explorer) failure marks the episode, not the shard
            rows, final, success, error = [], None, False, f"{type(exc).__name__}: {exc}"
        done = {**common, "instruction": plan.instruction}
        stats = explorer.stats() if explorer.stats else None
        if rows and not success and unit.relabel_to and hasattr(env, "achieved"):
            achieved = env.achieved(unit.relabel_to)
            if achieved is not None:
                recorded_as, stats, success = relabel(rows, achieved, plan, unit.task, stats)
                done.update(recorded_as)
        for row in rows:
            row.update(done, episode_id=plan.episode_id, image=encode_frame(row["image"]),
                       depth=_depth_bytes(row["depth"]), next_image=None, next_depth=None)
        if rows:
            rows[-1].update(next_image=encode_frame(final.image), next_depth=_depth_bytes(final.depth))
        step_rows.extend(rows)
        episode_rows.append(
            {
                **done, "episode_id": plan.episode_id, "explorer": plan.explorer,
                "seed": plan.seed, "shard_key": unit.unit_key, "num_steps": len(rows),
                "episode_return": float(sum(r["reward"] for r in rows)), "success": success, "error": error,
                "randomisation": randomisation.model_dump() if randomisation else None,
                "render": unit.render.model_dump(),
                "explorer_stats": json.dumps(stats) if stats is not None else None,
            }
        )
    workspace = Workspace.at(unit.workspace)
    store = open_store(workspace.warehouse, unit.shard_store)
    return [
        write_shard("episodes", pa.Table.from_pylist(episode_rows, schema=EPISODES),
                    workspace.shard_path("episodes", unit.iteration, unit.unit_key), store),
        write_shard("steps", pa.Table.from_pylist(step_rows, schema=STEPS),
                    workspace.shard_path("steps", unit.iteration, unit.unit_key), store),
    ]


def unit_label(unit: ExploreUnit) -> str:
    return f"{unit.task.task_id} shard {unit.shard}"


# -- registrar side ---------------------------------------------------------------------------


# (unit, its shard files, seconds in the worker), in completion order
Completed = Iterator[tuple[ExploreUnit, list[ShardFile], float]]
Execute = Callable[[list[ExploreUnit]], Completed]


def on_local_workers(workers: int) -> Execute:
    """The default: `workers` local processes, each unit retried on a fresh one if its worker dies."""
    return lambda units: run_in_pool(run_explore_unit, units, workers, unit_label)


def curriculum_subgoals(config: CampaignConfig, tasks: list[TaskRecord]) -> dict[str, list[str]]:
    """task id -> its sub-tasks' instructions, for the long-horizon tasks a curriculum chains."""
    if not config.explore.curriculum:
        return {}
    from envs.suite import subtask_instructions
    from schemas.task_spec import load_specs

    suite = load_specs(config.tasks.spec_files)
    return {t.task_id: chain for t in tasks if (chain := subtask_instructions(t, suite))}


def unit_summary(unit: ExploreUnit, shards: list) -> dict:
    """What the ledger keeps of an explored unit: its counts, and the render settings replay needs that
    episodes.render (a shard schema older than them) lacks, where not at their defaults."""
    by_table = {s.table: s for s in shards}
    summary = {"episodes": by_table["episodes"].num_rows, "steps": by_table["steps"].num_rows,
               # the ranges drawn from (episodes keep the draws): `sim2act eval` tells another domain by them
               "randomise": unit.randomise.model_dump(mode="json")}
    if unit.render is not None:  # the render fields added since that schema, where not at their legacy values
        keyed = render_key_fields(unit.render)
        summary.update({field: keyed[field] for field in RENDER_LEGACY_VALUES if field in keyed})
    return summary


def run_explore(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    tasks: list[TaskRecord],
    policy: PolicyExplorer | None,
    embeddings: dict[str, np.ndarray],
    execute: Execute | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> ExploreResult:
    """Plan the iteration's shards, run the unregistered ones through `execute` (default: local
    worker processes) and register each as it completes: a kill loses only shards in flight.

    Unit of work: one shard of a task's episodes (explore.episodes_per_shard), keyed by the explore,
    render and randomise settings, the explorer, the task, the shard's index and the task's episode
    count. Registers its `episodes` and `steps` shards."""
    catalog = Catalog(workspace.catalog)
    priorities = []
    if policy is not None and config.explore.prioritise:
        priorities = plan_priorities(catalog, config.name, policy.model_key, tasks, config.explore.episodes_per_task,
                                     config.explore.priority_floor)
        log.info("explore it%d: episodes by the champion's evaluation (success, uncertainty -> score): %s", iteration,
                 ", ".join(f"{p.task_id} {p.episodes}" + ("" if p.success is None else
                           f" ({p.success:.0%}, {p.uncertainty:.2f} -> {p.score:.2f})") for p in priorities))
    episodes_of = {p.task_id: p.episodes for p in priorities} if priorities else None
    units = plan_explore(config, iteration, tasks, policy, embeddings, workspace, episodes_of, curriculum_subgoals(config, tasks))
    units = [u.model_copy(update={"shard_store": catalog.store.url}) for u in units]
    keys = [u.unit_key for u in units]
    ledger = StageUnits(catalog, STAGE, config.name, iteration)
    pending = set(ledger.pending(keys))
    # shard 0 of every task, then shard 1 of every task, ...: the families differ 16x in speed per step
    todo = interleaved([u for u in units if u.unit_key in pending], lambda u: u.task.task_id)
    explorers = dict(Counter(e.explorer for u in units for e in u.episodes))
    log.info("explore it%d: %d shards (%d already registered), episodes by explorer: %s",
             iteration, len(units), len(units) - len(todo), explorers)
    execute = execute or on_local_workers(config.explore.workers)
    progress = Progress(log, f"explore it{iteration}", sum(len(u.episodes) for u in todo), "episodes", "triplets",
                        on_progress)
    episodes = steps = 0
    try:
        for unit, shards, seconds in execute(todo):
            summary = unit_summary(unit, shards)
            ledger.register(unit.unit_key, UnitOutput(summary, shards), seconds)
            episodes += summary["episodes"]
            steps += summary["steps"]
            progress.advance(summary["episodes"], summary["steps"])
    finally:
        progress.close()
    return ExploreResult(unit_keys=keys, episodes=episodes, steps=steps, skipped_units=len(units) - len(todo),
                         priorities=priorities)
