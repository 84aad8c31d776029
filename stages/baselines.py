"""baselines: what a campaign is measured against, on its own evaluation cases and seeds.

- `expert`: the tasks' scripted experts without noise — the ceiling.
- `ppo`, `sac`: RL from scratch (stable-baselines3), one instruction-conditioned agent per
  family trained on the campaign's seen tasks with as many environment steps as the campaign's
  exploration took on that family (its explore units, every iteration, kept and rejected
  episodes alike).
BC on iteration 0's data alone is iteration 0's own model: its evaluation is already stored.
Each trained agent is a unit (models/<key>/agent.zip); evaluations go to the warehouse
`evaluations` under the agent's model key, so `sim2act report` puts them beside the campaign."""

from __future__ import annotations

import contextvars
import gc
import json
import logging
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from envs.pool import Progress, run_in_pool
from schemas.config import CampaignConfig, RandomiseConfig, RenderConfig, render_key_fields
from schemas.keys import unit_key
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace, read_json_written, write_text_atomically
from stages import StageResult, StageUnits, UnitOutput
from stages.evaluate import (SPLITS, Agent, TaskEvaluation, episodes_per_split, evaluate_model, evaluation_cases,
                              group_success)
from warehouse.catalog import Catalog
from warehouse.store import fsync_path

STAGE, VERSION = "baselines", 1
# fields added since version 1, at the values that did what it did
LEGACY_VALUES = {"sac_encoder": "separate", "end_on_success": True, "sac_target_entropy": "all"}
EXPERT = "expert"
# beside an agent's agent.zip, for `sim2act report` while it trains: what it trains, and how far it got
PLAN, PROGRESS = "plan.json", "progress.json"
log = logging.getLogger("sim2act.stages.baselines")


class RLUnit(BaseModel):
    unit_key: str
    algorithm: str
    family: str
    tasks: list[TaskRecord]  # the family's seen tasks
    embeddings: dict[str, list[float]]  # their training instructions'
    render: RenderConfig
    randomise: RandomiseConfig
    env_steps: int
    replay_size: int  # SAC's replay buffer, transitions
    checkpoint_every: int  # environment steps between resumable checkpoints
    threads: int = 1  # torch threads of its training (baselines.threads): how fast, not what it learns from
    sac_encoder: str = "separate"  # SAC's: the critic's, shared with the actor (policies/rl_sac.py), or one each
    end_on_success: bool = True  # an episode ends at its first success (baselines.end_on_success)
    target_entropy: float | None = None  # SAC's; None: SB3's, minus the action dimensions
    seed: int
    path: str  # where the trained agent is saved; its checkpoints beside it
    # train.amp's rule for its encoder's updates: the workspace's measured precision choices; None: fp32
    precision_cache: str | None = None


class RLTrained(BaseModel):
    algorithm: str
    family: str
    env_steps: int  # the budget
    steps_taken: int  # what training stepped: PPO's whole rollouts pass the budget by less than one step each
    episodes: int  # finished while training
    successes: int
    resumed_at: int  # the environment step its last start resumed at (a checkpoint); 0: trained in one go
    path: str


class Baseline(BaseModel):
    agent: str  # expert, ppo or sac
    model_key: str  # its rows in `evaluations`
    family: str | None  # an RL agent serves one family
    env_steps: int  # its training budget; 0 for the expert
    evaluations: list[TaskEvaluation]


class AgentInTraining(BaseModel):
    """An RL agent of a campaign planned or training, not registered yet (`sim2act report` lists it)."""
    model_key: str
    algorithm: str
    family: str
    env_steps: int  # its budget
    started: bool  # False: waiting for a worker (no progress, no checkpoint)
    done: int  # environment steps at its latest progress or checkpoint
    episodes: int  # training episodes finished by then
    successes: int
    as_of: float | None  # when `done` was written (epoch seconds)
    rate: float | None  # env steps/s of the agent's latest run (progress.json); None: none yet, or older code
    checkpoint_steps: int  # where a restart resumes it; 0: from scratch
    checkpoint_at: float | None


class BaselinesResult(StageResult):
    baselines: list[Baseline]

    def did_work(self) -> bool:  # its units are its agents' trainings and the evaluate stage's cases
        return True

    def metrics(self) -> dict[str, float]:
        """baseline.<agent>[.<family>].success.<split>, for the campaign run beside its own success.<split>."""
        return {f"baseline.{b.agent}{'.' + b.family if b.family else ''}.success.{g.group}": g.success_rate
                for b in self.baselines for g in group_success(b.evaluations) if g.group in SPLITS}


def exploration_steps(catalog: Catalog, explore_units: list[str]) -> dict[str, int]:
    """family -> environment steps these explore units took (a campaign's: every iteration's)."""
    rows = catalog.query(
        "SELECT f.family, sum(e.num_steps) FROM episodes e "
        "JOIN task_families f ON f.campaign = e.campaign AND f.task_id = e.task_id "
        "WHERE list_contains(?, e.shard_key) GROUP BY f.family ORDER BY f.family", [explore_units])  # shard_key: its explore unit
    return {family: int(steps) for family, steps in rows}


def progress_callback(progress: Progress, folder: Path, env) -> Callable[[int, int], None]:
    """learn_with_checkpoints' `on_progress(done, resumed_at)` for a training in `folder`: the log line
    (rate, ETA) and progress.json at each 1% of the budget, and progress.json at its first call too
    (a resumed agent's last progress ran past the checkpoint it resumes at). `progress`: the bar
    over the budget; `env`: the training env, counting its episodes."""
    every_percent = max(1, progress.total // 100)
    written = False

    def on_progress(done: int, resumed_at: int) -> None:
        nonlocal written
        if progress.done < resumed_at:
            progress.resume_at(resumed_at)
        crossed = False
        if done > progress.done:
            crossed = done // every_percent > progress.done // every_percent
            progress.advance(done - progress.done, done - progress.done, log=crossed)
        if crossed or not written:
            write_progress(folder, done, env.episodes_finished, env.successes, progress.pace() or None)
            written = True

    return on_progress


def target_entropy(algorithm: str, family: str, rule: str) -> float | None:
    """SAC's entropy target under baselines.sac_target_entropy, where it is not SB3's own (minus the action
    dimensions): minus the components the family acts on."""
    from envs.observation import ACTING_COMPONENTS

    if algorithm != "sac" or rule == "all" or family not in ACTING_COMPONENTS:
        return None
    return -float(len(ACTING_COMPONENTS[family]))


def train_rl_agent(unit: RLUnit) -> RLTrained:
    """Worker: train one agent from scratch for its budget of environment steps (from its last
    checkpoint where a kill interrupted it) and save it."""
    from envs.gym_env import InstructedTasksEnv
    from envs.pool import log_stages_to_stderr
    from envs.rollout import close_envs
    from policies.rl_agent import learn_with_checkpoints

    import torch

    log_stages_to_stderr()  # a worker has no Prefect handler, and an agent trains for hours: its progress on stderr
    torch.set_num_threads(unit.threads)  # the pool's workers start with one
    env = InstructedTasksEnv(unit.tasks, {k: np.asarray(v, dtype=np.float32) for k, v in unit.embeddings.items()},
                             unit.render, unit.randomise, unit.end_on_success)
    path = Path(unit.path)
    path.parent.mkdir(parents=True, exist_ok=True)
    progress = Progress(log, f"baselines: {unit.algorithm} on {unit.family}", unit.env_steps, "env steps", "env steps")
    try:
        agent, resumed_at = learn_with_checkpoints(unit.algorithm, env, unit.env_steps, unit.seed, path.parent,
                                                   unit.checkpoint_every, unit.replay_size,
                                                   progress_callback(progress, path.parent, env),
                                                   Path(unit.precision_cache) if unit.precision_cache else None,
                                                   unit.sac_encoder, unit.target_entropy)
    finally:
        progress.close()
        # its scenes go with it (MetaWorld's 44 ~6.3 GB with every one kept): an evaluation beside the trainings
        # still running takes this core and that memory (run_baselines); a next agent here remakes its own in seconds
        close_envs()
    tmp = path.with_name(path.stem + ".tmp.zip")
    agent.save(tmp)
    # on the disk before its registration deletes the checkpoints: a machine that stops (not only a killed process)
    # leaves the agent whole, or its checkpoints; a killed training leaves no agent behind
    fsync_path(tmp)
    tmp.replace(path)
    fsync_path(path.parent)
    steps_taken = agent.num_timesteps
    del agent  # and SAC's replay (~2.1 GB full) with it now, for what runs beside the trainings still going
    gc.collect()
    return RLTrained(algorithm=unit.algorithm, family=unit.family, env_steps=unit.env_steps,
                     steps_taken=steps_taken, episodes=env.episodes_finished, successes=env.successes,
                     resumed_at=resumed_at, path=str(path))


def planned_agents(config: CampaignConfig, tasks: list[TaskRecord]) -> list[tuple[str, str, list[TaskRecord]]]:
    """(algorithm, family, its seen tasks) for each RL agent of `baselines.agents` on each family with
    seen tasks that the algorithm acts in (of `baselines.families` where it names some)."""
    from policies.rl_agent import RL_ALGORITHMS, supports

    families = sorted({t.family for t in tasks})
    if config.baselines.families is not None:
        families = [family for family in families if family in config.baselines.families]
    planned = []
    for algorithm in [a for a in config.baselines.agents if a in RL_ALGORITHMS]:
        for family in families:
            seen = [t for t in tasks if t.family == family and t.split == "seen"]
            if not seen:
                continue
            if not supports(algorithm, family):
                log.info("baselines: %s does not act in %s's discrete action space; skipped", algorithm, family)
                continue
            planned.append((algorithm, family, seen))
    return planned


def rl_budget(env_steps: int | dict[str, int] | None, family: str, explored: dict[str, int]) -> int:
    """A family's RL training budget: `baselines.env_steps` where it names one (a number for every family,
    or the family's entry), else the steps the campaign's exploration took on the family (0: none)."""
    given = env_steps.get(family) if isinstance(env_steps, dict) else env_steps
    return given or explored.get(family, 0)


def rl_units(workspace: Workspace, config: CampaignConfig, tasks_key: str, tasks: list[TaskRecord],
             embeddings: dict[str, np.ndarray], budgets: dict[str, int]) -> list[RLUnit]:
    """One unit per (RL algorithm, family with seen tasks) that the algorithm can act in."""
    from policies.rl_agent import replay_buffer_size

    units = []
    for algorithm, family, seen in planned_agents(config, tasks):
        steps = rl_budget(config.baselines.env_steps, family, budgets)
        if steps:
            said = {text: embeddings[text].tolist() for task in seen for text in task.instructions}
            replay = replay_buffer_size(steps, config.baselines.replay_size)
            # a replay smaller than the budget changes the agent (keys of agents whose replay held it stay as they were)
            smaller_replay = [f"replay {replay}"] if algorithm == "sac" and replay < steps else []
            # likewise the critic's shared encoder: SAC agents trained with an encoder each keep their keys
            shared_encoder = ["encoder critic"] if algorithm == "sac" and config.baselines.sac_encoder == "critic" else []
            # and agents whose episodes ended at their first success, or whose SAC aimed at all 7 components' entropy
            to_horizon = [] if config.baselines.end_on_success else ["episodes to the horizon"]
            target = target_entropy(algorithm, family, config.baselines.sac_target_entropy)
            acting_target = [] if target is None else [f"target entropy {target:g}"]
            key = unit_key(STAGE, VERSION, {"render": render_key_fields(config.render), "randomise": config.randomise,
                                            "seed": config.seed},
                           [tasks_key, algorithm, family, str(steps), *smaller_replay, *shared_encoder, *to_horizon,
                            *acting_target])  # tasks key: campaign, tasks, encoder
            units.append(RLUnit(unit_key=key, algorithm=algorithm, family=family, tasks=seen, embeddings=said,
                                render=config.render, randomise=config.randomise, env_steps=steps, replay_size=replay,
                                checkpoint_every=config.baselines.checkpoint_every, seed=config.seed,
                                threads=config.baselines.threads,
                                sac_encoder=config.baselines.sac_encoder,
                                end_on_success=config.baselines.end_on_success, target_entropy=target,
                                path=str(workspace.models / key / "agent.zip"),
                                precision_cache=str(workspace.precision_choices) if config.train.amp else None))
    return units


def all_plans(models: Path) -> dict[str, dict]:
    """model key -> plan, of every campaign's agents planned in `models` (a workspace's)."""
    plans = {}
    for path in sorted(models.glob(f"{STAGE}-*/{PLAN}")):
        try:
            plans[path.parent.name] = json.loads(path.read_text())
        except FileNotFoundError:  # a run dropped it meanwhile
            continue
    return plans


def campaign_plans(models: Path, campaign: str) -> dict[str, dict]:
    """model key -> plan, of the campaign's agents planned in `models` (a workspace's): those its
    latest run of the stage made, trained or not."""
    return {key: plan for key, plan in all_plans(models).items() if plan["campaign"] == campaign}


def write_plans(models: Path, campaign: str, units: list[RLUnit], families: list[str] | None = None) -> None:
    """Each of `units`' plan.json in its models/<key>/ before any trains, so that a report read
    mid-run names the agents the checkpoints belong to (a key alone does not say its algorithm,
    family or budget); the campaign's other plans (settings since changed, agents since dropped) are
    removed: no run trains or evaluates them. `families` (baselines.families): the run plans those
    families' agents alone, so the other families' plans stay, an unfinished agent's with its pending row."""
    planned = {unit.unit_key for unit in units}
    for key, plan in campaign_plans(models, campaign).items():
        if key not in planned and (families is None or plan["family"] in families):
            (models / key / PLAN).unlink(missing_ok=True)
    for unit in units:
        write_text_atomically(Path(unit.path).with_name(PLAN), json.dumps({
            "campaign": campaign, "algorithm": unit.algorithm, "family": unit.family, "env_steps": unit.env_steps}))


def write_progress(folder: Path, done: int, episodes: int, successes: int, rate: float | None = None) -> None:
    """A training's progress between its checkpoints (`progress_callback`: at its start and each 1%);
    `rate`: this run's env steps/s over its last ~10 minutes (`Progress.pace`; None at its start), which
    `sim2act report` turns into an ETA."""
    write_text_atomically(folder / PROGRESS, json.dumps({"num_timesteps": done, "episodes": episodes,
                                                         "successes": successes, "rate": rate}))


def agents_in_training(models: Path, catalog: Catalog, plans: dict[str, dict]) -> list[AgentInTraining]:
    """The agents of `plans` (`campaign_plans` of `models`, a workspace's) not registered: each at its
    latest progress or checkpoint, whichever was written last; SAC first, then by family."""
    from policies.rl_agent import checkpoint_state

    registered = catalog.registered_keys(list(plans))
    agents = []
    for key, plan in plans.items():
        if key in registered:
            continue
        checkpoint = checkpoint_state(models / key)
        progress = read_json_written(models / key / PROGRESS)
        latest = max((found for found in (checkpoint, progress) if found), key=lambda found: found[1], default=None)
        state, as_of = latest or ({"num_timesteps": 0, "episodes": 0, "successes": 0}, None)
        agents.append(AgentInTraining(
            model_key=key, algorithm=plan["algorithm"], family=plan["family"], env_steps=plan["env_steps"],
            started=latest is not None, done=state["num_timesteps"], episodes=state["episodes"],
            successes=state["successes"], as_of=as_of,
            # the pace of the run that wrote progress.json: a checkpoint written since (by that run: each run
            # writes progress.json at its start) has no pace of its own and does not change it
            rate=progress[0].get("rate") if progress else None,
            checkpoint_steps=checkpoint[0]["num_timesteps"] if checkpoint else 0,
            checkpoint_at=checkpoint[1] if checkpoint else None))
    return sorted(agents, key=lambda a: (a.algorithm != "sac", a.family))


def training_order(units: list[RLUnit], workers: int) -> list[RLUnit]:
    """The agents in the order the pool starts them. On several workers SAC before PPO, then the larger budgets:
    the stage ends when its last agent does, so the long ones start first and the short ones fill in beside them.
    On one worker the end is the same in any order, so the shortest first: each agent's rows land as early as
    they can. A SAC step takes a gradient step on a batch of 64 frames: ~120-200 ms of a core at 84 px, against
    PPO's 8-18 ms (`sim2act bench rl` on the generalist's families); at the generalist's budgets that is ~15-25 h
    for SAC on robosuite."""
    if workers == 1:
        return sorted(units, key=lambda unit: (unit.algorithm == "sac", unit.env_steps))
    return sorted(units, key=lambda unit: (unit.algorithm != "sac", -unit.env_steps))


def run_baselines(workspace: Workspace, config: CampaignConfig, iteration: int, tasks_key: str,
                  tasks: list[TaskRecord], embeddings: dict[str, np.ndarray], explore_units: list[str]) -> BaselinesResult:
    """Evaluate the experts on the campaign's evaluation cases, train the RL agents not trained yet
    with the steps `explore_units` (the campaign's, every iteration) took per family, and evaluate
    each on its family's cases: as soon as it has trained, beside the trainings still running where they
    leave a core idle (on one worker: before the next training begins), the rest after the last training;
    rows under `iteration`.

    Unit of work: one RL agent (an algorithm on a family), keyed by the render and randomise settings,
    the campaign seed, the algorithm, the family, its step budget (and SAC's replay where smaller
    than it) and the tasks' instructions; it saves a resumable checkpoint every
    `baselines.checkpoint_every` environment steps, so a kill loses at most those. Registers the
    agent's summary; its evaluations are the evaluate stage's units."""
    from policies.rl_agent import remove_checkpoints

    catalog = Catalog(workspace.catalog)
    units = rl_units(workspace, config, tasks_key, tasks, embeddings, exploration_steps(catalog, explore_units))
    ledger = StageUnits(catalog, STAGE, config.name, iteration)
    pending = set(ledger.pending(u.unit_key for u in units))
    todo = training_order([u for u in units if u.unit_key in pending], config.baselines.workers)
    log.info("baselines: %d RL agent(s) to train (%d already trained)", len(todo), len(units) - len(todo))
    write_plans(workspace.models, config.name, units, config.baselines.families)
    cases = evaluation_cases(tasks)
    baselines = []
    if EXPERT in config.baselines.agents:  # first: the ceiling in the report minutes in, not after the trainings' hours
        evaluations, _ = evaluate_model(workspace, config, iteration, EXPERT, Agent(kind="expert"), cases, embeddings)
        baselines.append(Baseline(agent=EXPERT, model_key=EXPERT, family=None, env_steps=0, evaluations=evaluations))
    per_split = episodes_per_split(config, cases)  # the whole campaign's split sizes: the expert's and the policy's

    def evaluated(unit: RLUnit, workers: int, fresh_workers: bool = False) -> Baseline:
        family_cases = [case for case in cases if case[0].family == unit.family]
        # evaluate.workers is not part of an evaluation unit's key: the same units on fewer workers
        on_workers = config.model_copy(update={"evaluate": config.evaluate.model_copy(update={"workers": workers})})
        evaluations, _ = evaluate_model(workspace, on_workers, iteration, unit.unit_key,
                                        Agent(kind=unit.algorithm, path=unit.path), family_cases, embeddings,
                                        per_split=per_split, fresh_workers=fresh_workers)
        return Baseline(agent=unit.algorithm, model_key=unit.unit_key, family=unit.family,
                        env_steps=unit.env_steps, evaluations=evaluations)

    # an agent's evaluation runs beside the trainings still running, on the cores they leave idle: its rows
    # land hours before the last training ends (six times a workspace went with its machine in between and
    # kept none: docs/results-generalist.md). Memory should hold: the evaluation's workers (one family's scenes,
    # MetaWorld's ~6 GB each) stand where finished trainings' did (their scenes and replays, ~7 GB each for the
    # generalist's SACs; docs/evaluation.md), on processes of its own closed after it (the kept pool is not the
    # beside evaluation's to use: the trainings' fresh pool retires it). One evaluation at a time, in a thread
    # (the catalog takes one writer at a time in a process); the trainings register as they finish meanwhile.
    beside = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim2act-baselines-evaluate")
    early: dict[str, Future] = {}
    # one worker: no core is left beside a training, so the agents train one at a time, each in a pool of its own,
    # and each is evaluated on every evaluation worker after its pool closed and before the next one begins
    # (minutes against the next one's hours)
    one_at_a_time = config.baselines.workers == 1
    evaluated_first: dict[str, Baseline] = {}

    def evaluate_now(unit: RLUnit) -> None:
        log.info("baselines: %s on %s evaluated before the next training", unit.algorithm, unit.family)
        evaluated_first[unit.unit_key] = evaluated(unit, config.evaluate.workers)

    def evaluated_beside(unit: RLUnit, workers: int) -> Baseline:
        try:
            return evaluated(unit, workers, fresh_workers=True)
        except Exception as exc:  # said when it happens; raised after the trainings (below)
            log.error("baselines: evaluating %s on %s beside the trainings failed: %r", unit.algorithm, unit.family, exc)
            raise

    def evaluate_beside(unit: RLUnit, training: int) -> None:
        idle = max(0, config.baselines.workers - training)  # cores no training takes
        if training and idle:
            log.info("baselines: %s on %s evaluated beside %d training(s)", unit.algorithm, unit.family, training)
            # in the flow's context: Prefect's log handler finds its run there (a thread starts with none)
            early[unit.unit_key] = beside.submit(contextvars.copy_context().run, evaluated_beside, unit,
                                                 min(config.evaluate.workers, idle))

    try:
        for unit in units:  # trained by an earlier run, its evaluation cut (or not begun) when that run stopped
            if unit.unit_key not in pending:
                if one_at_a_time and todo:
                    evaluate_now(unit)
                else:
                    evaluate_beside(unit, len(todo))
        left = len(todo)
        # fresh workers: the kept ones hold up to SIM2ACT_SCENES_PER_WORKER scenes of the campaign's evaluation
        # (~3 GB on the generalist), which an agent training for hours on one family's never uses (docs/evaluation.md)
        for batch in [[unit] for unit in todo] if one_at_a_time else [todo]:
            for unit, trained, seconds in run_in_pool(train_rl_agent, batch, config.baselines.workers,
                                                      lambda u: f"{u.algorithm} on {u.family}", fresh_workers=True):
                ledger.register(unit.unit_key, UnitOutput(trained.model_dump()), seconds)
                remove_checkpoints(Path(unit.path).parent)  # registered: its checkpoints and progress are spent
                Path(unit.path).with_name(PROGRESS).unlink(missing_ok=True)
                log.info("baselines: %s on %s trained, %d env steps in %.0fs (%d/%d training episodes succeeded)",
                         unit.algorithm, unit.family, trained.steps_taken, seconds, trained.successes, trained.episodes)
                left -= 1
                evaluate_beside(unit, left)
            if one_at_a_time and left:  # its pool closed; the last agent is evaluated below, as before
                evaluate_now(batch[0])
    finally:
        # the one in flight finishes (its cases register as they end); those not begun run below on every worker,
        # or, after a failed training, in the run that resumes this one
        beside.shutdown(wait=True, cancel_futures=True)
    # the rest after the last training, on every worker: beside trainings that take every core an evaluation's
    # workers would add their family's scenes to the trainings' (~14 GB for the generalist's two SACs with every
    # scene kept), past the machine's 24 GB (docs/evaluation.md); the training workers are closed by now
    for unit in units:
        early_one = early.get(unit.unit_key)
        if unit.unit_key in evaluated_first:
            baselines.append(evaluated_first[unit.unit_key])
        elif early_one is not None and not early_one.cancelled():
            baselines.append(early_one.result())
        else:
            baselines.append(evaluated(unit, config.evaluate.workers))
    return BaselinesResult(baselines=baselines)
