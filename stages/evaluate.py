"""evaluate: roll the trained policy out on every task, seen and unseen, said canonically; and
on each seen task said with a held-out paraphrase (split `unseen_paraphrase`). Success per
(task, instruction) with its Wilson 95% interval, episode lengths and MP4s of a success and a
failure go to the warehouse `evaluations` table; the new model is promoted only if it beats the
champion on the same cases."""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from pydantic import BaseModel

from envs.observation import DISCRETE_FAMILIES, Observation
from envs.pool import Progress, interleaved, run_in_pool
from envs.rollout import rollout, worker_env
from envs.shadow import CaseShadow, shadow_episode
from schemas.config import Acting, CampaignConfig, RandomiseConfig, RenderConfig, render_key_fields
from schemas.keys import derive_seed, unit_key
from schemas.tasks import CAMPAIGN_SUITE, CONTROL_HZ, UNSEEN_PARAPHRASE, Split, TaskRecord
from schemas.wordings import HELD_OUT_WORDING, held_out_wording
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from warehouse.catalog import Catalog

STAGE, VERSION = "evaluate", 5  # 5: episode_achieved
log = logging.getLogger("sim2act.stages.evaluate")
SPLITS = (*get_args(Split), UNSEEN_PARAPHRASE, HELD_OUT_WORDING)  # the evaluation's splits, in report order
CANONICAL_SPLITS = get_args(Split)  # seen, unseen: each task once, said as the suite says it


class Agent(BaseModel):
    """Who is evaluated: a Sim2Act checkpoint, the task's scripted expert (noiseless: the ceiling),
    or an RL baseline saved by stable-baselines3 (stages.baselines)."""

    kind: Literal["sim2act", "expert", "ppo", "sac"]
    path: str | None = None  # the checkpoint or the saved agent; none for the expert
    weights: Literal["registered", "final"] = "registered"  # sim2act: the averaged weights, or the last (Policy.load)
    acting: Acting | None = None  # sim2act: acting otherwise than it trained to (sim2act shadow --execution)


class EvalUnit(BaseModel):
    unit_key: str
    task: TaskRecord
    split: str
    instruction: str
    render: RenderConfig
    randomise: RandomiseConfig
    agent: Agent
    seeds: list[int]
    embedding: list[float]  # of the instruction
    # the evaluated set's other tasks in the same environment: a failed episode may have ended doing one
    # of them instead (the goal the words did not name: how well the policy reads them)
    others: list[TaskRecord] = []
    video_stem: str | None  # <stem>-success.mp4 / <stem>-failure.mp4: the first episode of each outcome
    metaworld_placements: str = "benchmark"  # evaluate.metaworld_placements: applies to MetaWorld tasks
    max_steps: int | None = None  # evaluate.max_steps: each episode ends there at the latest (None: the horizon)


class TaskEvaluation(BaseModel):
    task_id: str
    family: str
    split: str
    instruction: str
    episodes: int
    successes: int
    ci_low: float  # Wilson 95% interval of the success rate
    ci_high: float
    mean_return: float
    mean_length: float
    episode_lengths: list[int]  # in seed order
    episode_successes: list[bool]
    uncertainty: float  # the Sim2Act policy's, per step, averaged over the episodes (policies.model.uncertainty); 0 for other agents
    success_video: str | None
    failure_video: str | None
    # per episode: the task it ended doing (task_id on success, another task of the evaluated set, or
    # None); None where not recorded (evaluations before layout 7)
    episode_achieved: list[str | None] | None = None

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes

    def first(self, episodes: int) -> TaskEvaluation:
        """The case over its first `episodes` episodes: a case's episodes are seeded by their index, so these are
        the episodes an evaluation of `episodes` played. Its mean return and videos stay the whole evaluation's
        (per-episode returns are not kept). Itself where it has no more, or no per-episode record to cut."""
        if episodes >= self.episodes or len(self.episode_successes) != self.episodes:
            return self
        outcomes, lengths = self.episode_successes[:episodes], self.episode_lengths[:episodes]
        low, high = wilson_interval(sum(outcomes), episodes)
        return self.model_copy(update={
            "episodes": episodes, "successes": sum(outcomes), "ci_low": low, "ci_high": high,
            "mean_length": sum(lengths) / episodes, "episode_lengths": lengths, "episode_successes": outcomes,
            "episode_achieved": None if self.episode_achieved is None else self.episode_achieved[:episodes]})


def wilson_interval(successes: int, episodes: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success rate (95% at z = 1.96): unlike p +- z*se it stays
    inside [0, 1] and is not zero-width at 0/n or n/n, which small evaluations hit often."""
    if episodes == 0:
        return 0.0, 1.0
    p = successes / episodes
    centre = (p + z * z / (2 * episodes)) / (1 + z * z / episodes)
    half = z * math.sqrt(p * (1 - p) / episodes + z * z / (4 * episodes * episodes)) / (1 + z * z / episodes)
    return max(0.0, centre - half), min(1.0, centre + half)


class GroupSuccess(BaseModel):
    """Success pooled over a group of evaluation cases (a split, a family, a split within a family)."""

    group: str  # "seen", "unseen", "unseen_paraphrase", "robosuite", "robosuite/seen", ...
    cases: int
    episodes: int
    successes: int
    ci_low: float
    ci_high: float
    mean_length: float

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes


def read_evaluations(catalog: Catalog, lead: str, rest: str, params: list,
                     table: str = "current_evaluations") -> list[tuple[Any, TaskEvaluation]]:
    """(the `lead` column, the row as a TaskEvaluation) for each row of `SELECT lead, ... FROM
    <table> v <rest>`: rest joins, filters and orders, the table aliased v. The current evaluation of
    each case by default (a case evaluated twice counts once); `evaluations` for every row."""
    fields = list(TaskEvaluation.model_fields)
    rows = catalog.query(f"SELECT {lead}, {', '.join('v.' + f for f in fields)} FROM {table} v {rest}", params)
    return [(lead_value, TaskEvaluation(**dict(zip(fields, values)))) for lead_value, *values in rows]


def group_success(evaluations: list[TaskEvaluation]) -> list[GroupSuccess]:
    """Per split, per family, and per split within each family: episodes pooled, with a Wilson interval.
    A family's own group holds its tasks once each, said canonically (seen and unseen): a seen task said
    again in a held-out paraphrase or wording replays the same episode seeds, and pooled beside its canonical
    case it would count twice or three times as independent episodes."""
    groups: dict[str, list[TaskEvaluation]] = {}
    for t in evaluations:
        canonical = (t.family,) if t.split in CANONICAL_SPLITS else ()
        for group in (t.split, *canonical, f"{t.family}/{t.split}"):
            groups.setdefault(group, []).append(t)
    summaries = []
    for group, members in sorted(groups.items()):
        episodes, successes = sum(t.episodes for t in members), sum(t.successes for t in members)
        low, high = wilson_interval(successes, episodes)
        summaries.append(GroupSuccess(
            group=group, cases=len(members), episodes=episodes, successes=successes, ci_low=low, ci_high=high,
            mean_length=sum(sum(t.episode_lengths) for t in members) / episodes,
        ))
    return summaries


class Promotion(BaseModel):
    """The evaluation's decision on the registry alias: the alias moves only when this says so."""

    promote: bool
    reason: str
    success: float  # mean success of the new model over the evaluation cases
    champion_success: float | None  # the current champion's over the same cases; None without one


class EvaluateResult(StageResult):
    model_key: str
    tasks: list[TaskEvaluation]
    skipped_units: int
    promotion: Promotion

    def did_work(self) -> bool:
        return self.skipped_units < len(self.tasks)

    def metrics(self) -> dict[str, float]:
        return evaluation_metrics(self.tasks) if self.did_work() else {}

    def artifacts(self) -> list[tuple[str, str]]:
        return evaluation_videos(self.tasks) if self.did_work() else []


def evaluation_metrics(evaluations: list[TaskEvaluation]) -> dict[str, float]:
    """Success per case and per group (split, family, split within family) with their Wilson
    intervals, and mean episode lengths: MLflow metric names."""
    metrics = {}
    for t in evaluations:
        name = f"success.{t.task_id}" + {UNSEEN_PARAPHRASE: ".paraphrase", HELD_OUT_WORDING: ".held_out_wording"}.get(
            t.split, "")
        metrics.update({name: t.success_rate, f"{name}.ci_low": t.ci_low, f"{name}.ci_high": t.ci_high,
                        f"length.{t.task_id}": t.mean_length})
    for g in group_success(evaluations):
        metrics.update({f"success.{g.group}": g.success_rate, f"success.{g.group}.ci_low": g.ci_low,
                        f"success.{g.group}.ci_high": g.ci_high, f"length.{g.group}": g.mean_length})
    return metrics


def evaluation_videos(evaluations: list[TaskEvaluation]) -> list[tuple[str, str]]:
    """(video, folder) for every case's success and failure videos."""
    return [(video, f"evaluation/{t.task_id}/{t.split}") for t in evaluations
            for video in (t.success_video, t.failure_video) if video]


def decide_promotion(catalog: Catalog, campaign: str, model_key: str, evaluations: list[TaskEvaluation],
                     registered_model: str, alias: str) -> Promotion:
    """Promote when there is no champion, or when the new model's mean success over the evaluation cases both
    met (seen, unseen, held-out paraphrases) beats the champion's on the same episodes. A case's episodes are
    seeded by their index, so where one side played more (`sim2act eval --episodes 50` of the champion), the
    first N of its episodes are the other's N: each case compares those, not 50 episodes against 10.

    The champion is who holds `alias` of `registered_model` now: the last registered deployment's, not the
    highest iteration's (a campaign re-run with other settings deploys its iteration 0 after an older run's
    iteration 3), and none under another registered model or alias (redeploy.* changed: its first model is
    promoted, so the alias exists where redeploy reads it)."""
    success = float(np.mean([t.success_rate for t in evaluations]))
    champion = catalog.query(
        "SELECT d.champion_model_key FROM deployments d LEFT JOIN stage_runs r ON r.unit_key = d.unit_key "
        "WHERE d.campaign = ? AND d.registered_model = ? AND d.alias = ? AND d.model_key <> ? "
        "ORDER BY r.finished_at DESC NULLS LAST, d.iteration DESC LIMIT 1", [campaign, registered_model, alias, model_key],
    )
    if not champion:
        return Promotion(promote=True, reason="no champion yet", success=success, champion_success=None)
    theirs = {(task_id, split, instruction): outcomes for task_id, split, instruction, outcomes in catalog.query(
        "SELECT task_id, split, instruction, episode_successes FROM current_evaluations WHERE campaign = ? "
        "AND model_key = ? AND suite = ?", [campaign, champion[0][0], CAMPAIGN_SUITE])}
    pairs = []  # per case both met: (the new model's rate, the champion's) over the episodes both played
    for t in evaluations:
        champion_outcomes = theirs.get((t.task_id, t.split, t.instruction)) or []
        if n := min(len(champion_outcomes), len(t.episode_successes)):
            pairs.append((float(np.mean(t.episode_successes[:n])), float(np.mean(champion_outcomes[:n]))))
    if not pairs:
        return Promotion(promote=True, reason="the champion was never evaluated on these tasks", success=success,
                         champion_success=None)
    success, before = (float(np.mean(side)) for side in zip(*pairs))
    better = success > before
    reason = f"success {success:.0%} {'beats' if better else 'does not beat'} the champion's {before:.0%} on {len(pairs)} cases"
    return Promotion(promote=better, reason=reason, success=success, champion_success=before)


def _write_video(frames: list[np.ndarray], path: Path, fps: int) -> None:
    from warehouse.video import video_writer

    tmp = path.with_name(path.stem + ".tmp.mp4")
    writer = video_writer(tmp, fps=fps)
    for frame in frames:
        writer.append_data(frame)
    writer.close()
    tmp.replace(path)


Decide = Callable[[Observation], tuple[np.ndarray, float]]  # -> (action, uncertainty)


def episode_actor(unit: EvalUnit) -> Callable[[int], Decide]:
    """episode seed -> how the unit's agent acts in that episode."""
    embedding = np.asarray(unit.embedding, dtype=np.float32)
    if unit.agent.kind == "sim2act":
        from policies.policy import Policy

        policy = Policy.load(Path(unit.agent.path), {unit.instruction: embedding}, unit.agent.weights)
        if unit.agent.acting is not None:
            policy.acting_as(unit.agent.acting)

        def episode(seed: int) -> Decide:
            actor = policy.episode(unit.task.family)  # a chunked policy keeps its chunks per episode

            def decide(obs: Observation) -> tuple[np.ndarray, float]:
                decision = actor(obs, unit.instruction)
                return decision.action, decision.uncertainty

            return decide

        return episode
    if unit.agent.kind == "expert":
        from envs.registry import make_expert

        def expert_for(seed: int) -> Decide:
            expert = make_expert(unit.task, 0.0, np.random.default_rng(seed))
            return lambda obs: (expert(obs), 0.0)

        return expert_for
    from policies.rl_agent import RLAgent

    agent = RLAgent.load(unit.agent.kind, Path(unit.agent.path), unit.task.family)
    return lambda seed: lambda obs: (agent.act(obs, embedding), 0.0)


def ended_doing(env, others: list[TaskRecord]) -> str | None:
    """The task of `others` whose goal a failed episode ended at, where the environment can tell
    (its `achieved`, as hindsight relabelling asks it: navigation, robosuite's Stack); None otherwise."""
    if not others or not hasattr(env, "achieved"):
        return None
    done = env.achieved(others)
    return None if done is None else done.task_id


def evaluate_unit(unit: EvalUnit) -> TaskEvaluation:
    """Worker: the agent's mean (or most likely) action, episodes until success or the horizon;
    its uncertainty at every step; an MP4 of the first success and of the first failure."""
    from envs.randomisation import sample_randomisation

    actor = episode_actor(unit)
    env = worker_env(unit.task, unit.render)
    returns, lengths, outcomes, uncertainties, achieved = [], [], [], [], []
    videos: dict[bool, str] = {}

    for seed in unit.seeds:
        decide = actor(seed)

        def act(obs: Observation) -> np.ndarray:
            action, uncertainty = decide(obs)
            uncertainties.append(uncertainty)
            return action

        rows, final, success = rollout(
            env, unit.task, seed, act, sample_randomisation(unit.randomise, seed, env.RANDOMISES),
            steps=unit.max_steps, placements=_placements(unit),
        )
        returns.append(sum(r["reward"] for r in rows))
        lengths.append(len(rows))
        outcomes.append(bool(success))
        achieved.append(unit.task.task_id if success else ended_doing(env, unit.others))
        if unit.video_stem and bool(success) not in videos and final.image.size:
            path = Path(f"{unit.video_stem}-{'success' if success else 'failure'}.mp4")
            path.parent.mkdir(parents=True, exist_ok=True)
            _write_video([r["image"] for r in rows] + [final.image], path, CONTROL_HZ[unit.task.family])
            videos[bool(success)] = str(path)
    successes = sum(outcomes)
    low, high = wilson_interval(successes, len(outcomes))
    return TaskEvaluation(
        task_id=unit.task.task_id, family=unit.task.family, split=unit.split, instruction=unit.instruction,
        episodes=len(outcomes), successes=successes, ci_low=low, ci_high=high, mean_return=float(np.mean(returns)),
        mean_length=float(np.mean(lengths)), episode_lengths=lengths, episode_successes=outcomes,
        uncertainty=float(np.mean(uncertainties)), success_video=videos.get(True), failure_video=videos.get(False),
        episode_achieved=achieved,
    )


def _placements(unit: EvalUnit) -> str:
    """The unit's evaluate.metaworld_placements where its task is MetaWorld's (the others draw theirs from the seed)."""
    return unit.metaworld_placements if unit.task.family == "metaworld" else "benchmark"


def shadow_unit(unit: EvalUnit) -> CaseShadow:
    """Worker: the unit's episodes as evaluate_unit plays them (same agent, seeds, randomisation), the
    noiseless expert asked at every state the agent reaches (envs.shadow; no videos, nothing registered)."""
    from envs.randomisation import sample_randomisation
    from envs.registry import make_expert

    actor = episode_actor(unit)
    env = worker_env(unit.task, unit.render)
    case = CaseShadow(unit.task.task_id, unit.split, unit.task.family in DISCRETE_FAMILIES, spec=unit.task.spec)
    for seed in unit.seeds:
        decide = actor(seed)
        case.add(shadow_episode(env, unit.task, seed, lambda obs: decide(obs)[0],
                                make_expert(unit.task, 0.0, np.random.default_rng(seed)),
                                sample_randomisation(unit.randomise, seed, env.RANDOMISES),
                                placements=_placements(unit), steps=unit.max_steps))
    return case


def evaluated_key(model_key: str, weights: str) -> str:
    """Whom an evaluation names: the model with its registered weights, or `<key>:final` for its last
    weights (another agent: its own evaluation units)."""
    return model_key if weights == "registered" else f"{model_key}:{weights}"


class GoalConfusion(BaseModel):
    """A split's failed episodes by what they ended doing (the environments that can tell): the goal
    of a task of the same spec in another colour (the colour misread), of another spec (the object
    misread), or none named by any evaluated task."""

    split: str
    failures: int  # failed episodes whose end was recorded
    same_spec: int  # ended at the goal of the same spec in another colour
    other_spec: int  # ended at the goal of another spec
    commonest: list[tuple[str, str, int]]  # (evaluated task, task done instead, episodes), most first


def goal_confusions(evaluations: list[TaskEvaluation], spec_of: dict[str, str], top: int = 3) -> list[GoalConfusion]:
    """Per split, in report order: what failed episodes ended doing, where any was recorded.
    `spec_of`: task id -> its spec, for the evaluated tasks and those done instead."""
    by_split: dict[str, list[tuple[str, str | None]]] = {}
    for t in evaluations:
        if t.episode_achieved is None:
            continue
        failed = [done for done, success in zip(t.episode_achieved, t.episode_successes) if not success]
        by_split.setdefault(t.split, []).extend((t.task_id, done) for done in failed)
    confusions = []
    for split in sorted(by_split, key=lambda s: SPLITS.index(s) if s in SPLITS else len(SPLITS)):
        pairs = by_split[split]
        wrong = [(task, done) for task, done in pairs if done is not None]
        same = sum(spec_of.get(done) == spec_of.get(task) for task, done in wrong)
        confusions.append(GoalConfusion(
            split=split, failures=len(pairs), same_spec=same, other_spec=len(wrong) - same,
            commonest=[(task, done, n) for (task, done), n in Counter(wrong).most_common(top)]))
    return confusions


def episodes_per_split(config: CampaignConfig, cases: list[tuple[TaskRecord, str, str]]) -> dict[str, int]:
    """Split -> episodes for each of its cases (evaluate.episodes_per_split over the split's case count)."""
    return {split: config.evaluate.episodes_per_case(n) for split, n in Counter(s for _, s, _ in cases).items()}


def evaluation_cases(tasks: list[TaskRecord], held_out_wordings: bool = False) -> list[tuple[TaskRecord, str, str]]:
    """(task, split, instruction): every task said canonically, every seen task that has held-out
    paraphrases said with the first of them, and with `held_out_wordings` every seen task in words
    the generator never uses (schemas/wordings.py); same seeds, so only the words differ."""
    cases = [(task, task.split, task.instruction) for task in tasks]
    cases += [(task, UNSEEN_PARAPHRASE, task.unseen_instructions[0])
              for task in tasks if task.split == "seen" and task.unseen_instructions]
    if held_out_wordings:
        cases += [(task, HELD_OUT_WORDING, held_out_wording(task.instruction)) for task in tasks if task.split == "seen"]
    return cases


def others_of(task: TaskRecord, cases: list[tuple[TaskRecord, str, str]]) -> list[TaskRecord]:
    """The cases' other tasks in `task`'s environment, each once, in case order: the scene's `achieved`
    says which of them, if any, a failed episode ended doing (navigation: one-goal tasks; robosuite's
    Stack: the reversed pair)."""
    others: dict[str, TaskRecord] = {}
    for other, _, _ in cases:
        if other.env_name == task.env_name and other.task_id != task.task_id:
            others.setdefault(other.task_id, other)
    return list(others.values())


def evaluation_units(workspace: Workspace, config: CampaignConfig, model_key: str, agent: Agent,
                     cases: list[tuple[TaskRecord, str, str]], embeddings: dict[str, np.ndarray],
                     suite: str = CAMPAIGN_SUITE, per_split: dict[str, int] | None = None) -> list[EvalUnit]:
    """One unit per (task, split, instruction) case, keyed by what it reads (evaluate_model); its seeds derive
    from (campaign, task, episode), so every agent given the same cases meets the same episodes. `per_split`:
    episodes per case of each split where `cases` are part of the campaign's (an RL agent's family), counted
    on the whole (episodes_per_split); None: counted on `cases`."""
    units = []
    missing = sorted({instruction for _, _, instruction in cases} - set(embeddings))
    if missing:  # wordings the generator never made (held_out_wording): encoded now by the frozen encoder
        from policies.language import encode

        embeddings = {**embeddings, **dict(zip(missing, encode(config.train.model.language_encoder, missing)))}
    # a unit reads its own episode count, not the split's size: the same case evaluated in a smaller task
    # set (sim2act eval --split) finds the same unit
    reads = {"evaluate": config.evaluate.model_dump(exclude={"workers", "episodes_per_split", "episodes_per_task",
                                                             "held_out_wordings", "training_seeds",
                                                             "metaworld_placements", "max_steps"}),
             "render": render_key_fields(config.render), "randomise": config.randomise,
             "seeds_from": [config.name, config.seed]}  # the episodes' seeds derive from these
    if config.evaluate.max_steps is not None:  # only where set, as placements: episodes cut short are other units
        reads["max_steps"] = config.evaluate.max_steps
    per_split = per_split or episodes_per_split(config, cases)
    for task, split, instruction in cases:
        episodes = per_split[split]
        reads["evaluate"]["episodes_per_task"] = episodes  # where it was before the split's count existed: old keys hold
        # in a MetaWorld case's key only, and only where set: older units and the other families' keep theirs
        placements = config.evaluate.metaworld_placements if task.family == "metaworld" else "benchmark"
        reads.pop("metaworld_placements", None)
        if placements != "benchmark":
            reads["metaworld_placements"] = placements
        key = unit_key(STAGE, VERSION, reads, [model_key, suite, task.model_dump_json(), split, instruction])
        seeds = [derive_seed(config.name, config.seed, "evaluate", task.task_id, e) for e in range(episodes)]
        units.append(EvalUnit(unit_key=key, task=task, split=split, instruction=instruction, render=config.render,
                              randomise=config.randomise, agent=agent, seeds=seeds,
                              embedding=embeddings[instruction].tolist(), others=others_of(task, cases),
                              video_stem=str(workspace.media / key) if config.evaluate.videos else None,
                              metaworld_placements=config.evaluate.metaworld_placements,
                              max_steps=config.evaluate.max_steps))
    return units


def evaluate_model(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    model_key: str,
    agent: Agent,
    cases: list[tuple[TaskRecord, str, str]],
    embeddings: dict[str, np.ndarray],
    suite: str = CAMPAIGN_SUITE,
    per_split: dict[str, int] | None = None,
    fresh_workers: bool = False,
) -> tuple[list[TaskEvaluation], int]:
    """Roll the agent out on each (task, split, instruction) case with the campaign's render,
    randomisation and evaluate settings; each case is a unit registered in the catalog's
    `evaluations` under `suite`. -> (the cases' evaluations in case order, how many were already registered).
    Seeds derive from (campaign, task, episode): every model meets the same episodes; `per_split`: as in
    evaluation_units; `fresh_workers`: on processes of its own, closed after (run_in_pool), not the kept ones."""
    if agent.acting is not None:  # its evaluations would be registered as the model's own, under the same keys
        raise ValueError(f"evaluate_model: expected the agent acting as it trained to, got acting {agent.acting.describe()}")
    catalog = Catalog(workspace.catalog)
    units = evaluation_units(workspace, config, model_key, agent, cases, embeddings, suite, per_split)
    ledger = StageUnits(catalog, STAGE, config.name, iteration)
    pending = set(ledger.pending(u.unit_key for u in units))
    # a case of each family in turn: a navigation case runs in seconds, a robosuite one in minutes
    todo = interleaved([u for u in units if u.unit_key in pending], lambda u: u.task.family)
    done = len(units) - len(todo)
    log.info("evaluate it%d: %d cases (%d already evaluated), %s episodes each", iteration, len(units), done,
             "/".join(str(n) for n in sorted({len(u.seeds) for u in units})))
    progress = Progress(log, f"evaluate it{iteration}", len(todo), "cases", "episodes")
    try:
        for unit, result, seconds in run_in_pool(evaluate_unit, todo, config.evaluate.workers, lambda u: u.task.task_id,
                                                 fresh_workers):
            row = {"unit_key": unit.unit_key, "campaign": config.name, "iteration": iteration, "suite": suite,
                   "model_key": model_key,
                   **result.model_dump(), "success_rate": result.success_rate}
            summary = {"model_key": model_key,
                       **result.model_dump(exclude={"episode_lengths", "episode_successes", "episode_achieved"})}
            ledger.register(unit.unit_key, UnitOutput(summary, rows={"evaluations": [row]}), seconds)
            progress.advance(1, result.episodes)
            log.info("evaluate it%d: %s (%s, %r) success %d/%d [%.0f%%, %.0f%%]", iteration, result.task_id,
                     result.split, result.instruction, result.successes, result.episodes, 100 * result.ci_low,
                     100 * result.ci_high)
    finally:
        progress.close()
    by_key = dict(read_evaluations(catalog, "v.unit_key", "WHERE list_contains(?, v.unit_key)",
                                   [[u.unit_key for u in units]], table="evaluations"))
    return [by_key[u.unit_key] for u in units], done


def run_evaluate(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    model_key: str,
    checkpoint: str,
    tasks: list[TaskRecord],
    embeddings: dict[str, np.ndarray],
) -> EvaluateResult:
    """The flow's stage: every evaluation case of the campaign's tasks, then the promotion decision.

    Unit of work: one case (a task, a split, an instruction), keyed by the evaluate, render and
    randomise settings, the model, the suite, the task, the split and the instruction (evaluate_model).
    Registers an `evaluations` row per case: successes, episode lengths, Wilson interval, videos."""
    evaluations, skipped = evaluate_model(workspace, config, iteration, model_key,
                                          Agent(kind="sim2act", path=checkpoint),
                                          evaluation_cases(tasks, config.evaluate.held_out_wordings), embeddings)
    catalog = Catalog(workspace.catalog)
    promotion = decide_promotion(catalog, config.name, model_key, evaluations, config.registered_model_name,
                                 config.redeploy.alias)
    log.info("evaluate it%d: %s: %s", iteration, "promote" if promotion.promote else "keep the champion", promotion.reason)
    return EvaluateResult(model_key=model_key, tasks=evaluations, skipped_units=skipped, promotion=promotion)
