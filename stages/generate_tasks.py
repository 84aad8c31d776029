"""generate_tasks: the campaign's tasks (envs.suite: the specs bound to colours, said at least
three ways), or an LLM proposer's, registered with their instruction embeddings.

Unit of work: the whole task list, keyed by the tasks themselves, the encoder and the proposer
settings; registers the `tasks` rows and one `instructions` shard.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable

import pyarrow as pa

from envs.expert_check import checks_experts, experts_under, felt_apart, said
from envs.registry import check_render
from envs.suite import generate_tasks, short_horizons
from schemas.config import CampaignConfig, ConfigError
from schemas.experts import TARGET, ExpertRow
from schemas.keys import unit_key
from schemas.tables import INSTRUCTIONS
from schemas.task_spec import load_specs
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from warehouse.catalog import Catalog
from warehouse.shard_writer import write_shard
from warehouse.tasks import load_tasks, task_rows

STAGE, VERSION = "generate_tasks", 1
log = logging.getLogger("sim2act.stages.generate_tasks")


class TasksResult(StageResult):
    unit_key: str
    task_ids: list[str]
    instructions: int
    skipped: bool
    proposals_valid: int = 0
    proposals_rejected: dict[str, int] = {}
    experts_left_out: list[str] = []  # below target under the campaign's own randomisation: templates, proposals

    def did_work(self) -> bool:
        return not self.skipped

    def metrics(self) -> dict[str, float]:
        if self.skipped:
            return {}
        return {"tasks.count": len(self.task_ids), "tasks.proposals_valid": self.proposals_valid,
                "tasks.experts_left_out": len(self.experts_left_out),
                **{f"tasks.proposals_rejected.{k}": v for k, v in self.proposals_rejected.items()}}


def tasks_unit_key(config: CampaignConfig, tasks: list[TaskRecord]) -> str:
    """Keyed by the template tasks themselves (editing a spec file makes new tasks) and the
    proposer settings: an LLM is asked once per key, and its answer is what gets registered (with a
    proposer, the randomisation its new bindings' experts are measured under, where they are)."""
    reads = {"campaign": config.name, "encoder": config.train.model.language_encoder,
             "proposer": config.tasks.proposer}
    if config.tasks.proposer is not None and checks_experts(config.tasks.weak_experts, config.randomise):
        reads["experts_felt"] = felt_apart(config.randomise)
    return unit_key(STAGE, VERSION, reads, [t.model_dump_json() for t in tasks])


def weak_under_campaign(workspace: Workspace, config: CampaignConfig, tasks: list[TaskRecord], measure: bool,
                        progress: Callable[[ExpertRow], None] | None = None) -> list[ExpertRow]:
    """The rows of `tasks` whose scripted expert is below target under the campaign's own randomisation, where it
    moves what an expert feels from the shipped table's (envs.expert_check.felt_apart; [] where it does not, or
    with tasks.weak_experts: keep). measure: measure the tasks this workspace has no row for (`sim2act run` and
    the flow's generate_tasks do, before exploring); otherwise a task never measured counts as strong."""
    if not checks_experts(config.tasks.weak_experts, config.randomise):
        return []
    rows = experts_under(workspace, tasks, config.randomise, config.explore.workers, measure, progress)
    return [rows[t.task_id] for t in tasks if t.task_id in rows and rows[t.task_id].below_target]


def left_out_line(weak: list[ExpertRow], config: CampaignConfig, kept: list[TaskRecord]) -> str:
    """The one line that says which tasks the campaign's randomisation left out, and which family went whole."""
    families = sorted({r.family for r in weak})
    whole = [f for f in families if not any(t.family == f for t in kept)]
    per_family = "; ".join(f"{family}: " + ", ".join(f"{r.task_id} {r.successes}/{r.episodes}"
                                                    for r in weak if r.family == family) for family in families)
    return (f"{len(weak)} task(s) left out, their scripted expert below {TARGET:.0%} under this campaign's "
            f"randomisation ({said(felt_apart(config.randomise))}; tasks.weak_experts: keep uses them): {per_family}"
            + (f"; {'family' if len(whole) == 1 else 'families'} {', '.join(whole)} left out whole" if whole else ""))


def campaign_tasks(workspace: Workspace, config: CampaignConfig, measure: bool = False,
                   progress: Callable[[ExpertRow], None] | None = None) -> tuple[list[TaskRecord], list[ExpertRow]]:
    """The campaign's tasks: envs.suite's for its tasks config, less those whose scripted expert is below target
    under its own randomisation (weak_under_campaign); every call site that keys the campaign's tasks uses this,
    so that it agrees with the flow's key.

    Returns:
        (the tasks kept, the rows of those left out).
    Raises:
        ConfigError: tasks.include names a task left out, or no seen task is left to explore.
    """
    tasks = generate_tasks(config.tasks, config.seed)
    weak = weak_under_campaign(workspace, config, tasks, measure, progress)
    if not weak:
        return tasks, []
    left = {r.task_id for r in weak}
    named = [r for r in weak if r.task_id in set(config.tasks.include or ())]
    if named:
        raise ConfigError(f"tasks.include: expected tasks whose scripted expert reaches {TARGET:.0%} under this campaign's "
                          f"randomisation ({said(felt_apart(config.randomise))}), got "
                          + ", ".join(f"{r.task_id!r} at {r.successes}/{r.episodes}" for r in named)
                          + "; set tasks.weak_experts: keep to use them")
    kept = [t for t in tasks if t.task_id not in left]
    if not any(t.split == "seen" for t in kept):
        raise ConfigError(f"tasks: expected at least one seen task to explore, got none: "
                          f"{left_out_line(weak, config, kept)}")
    return kept, weak


def run_generate_tasks(workspace: Workspace, config: CampaignConfig, tasks: list[TaskRecord] | None = None) -> TasksResult:
    """Unit of work: the campaign's whole task list, keyed by the tasks (tasks_unit_key). Registers the
    `tasks` rows and the `instructions` shard (every instruction's embedding by the campaign's encoder);
    with a proposer, the LLM's tasks in place of the templates'.

    Args:
        tasks: the tasks to register (an adaptation's: its source campaign's, whose experts are not measured again
            under the shifted domain); None: campaign_tasks's, measured under the config's randomisation."""
    catalog = Catalog(workspace.catalog)
    checking = tasks is None  # the campaign's own tasks: their experts measured under its randomisation
    tasks, weak = campaign_tasks(workspace, config, measure=True) if checking else (tasks, [])
    if weak:
        log.warning("generate_tasks: %s", left_out_line(weak, config, tasks))
    if short := short_horizons(config.tasks, tasks):
        log.warning("generate_tasks: %s", short)
    check_render(config.render, tasks)  # a flow started from the UI is refused as `sim2act run` refuses it
    key = tasks_unit_key(config, tasks)

    def work() -> UnitOutput:
        from policies.language import encode  # loading the encoder is slow: only when there is work

        proposed, proposals = tasks, None
        if config.tasks.proposer is not None:
            from policies.llm_proposer import propose

            suite = load_specs(config.tasks.spec_files)
            late: list[ExpertRow] = []  # new bindings whose expert is below target under the campaign's randomisation

            def weak_among(new: list[TaskRecord]) -> set[str]:
                late.extend(weak_under_campaign(workspace, config, new, measure=True))
                return {r.task_id for r in late}

            # the proposer checks new bindings against the shipped table; measured under the campaign's own
            # randomisation too, as the templates were (not an adaptation's: its source's tasks stand)
            proposals = propose(config.tasks, {n: suite[n].spec for n in config.tasks.specs}, tasks,
                                weak_among if checking else None)
            proposed = proposals.tasks
            if late:
                log.warning("generate_tasks: the proposer's %s", left_out_line(late, config, proposed))
                said_before = {w.task_id for w in weak}  # left out of the templates already: named once
                weak.extend(r for r in late if r.task_id not in said_before)
        pairs = [(t.task_id, text) for t in proposed for text in [*t.instructions, *t.unseen_instructions]]
        encoder = config.train.model.language_encoder
        log.info("generate_tasks: %d tasks, %d instructions; embedding them with %s", len(proposed), len(pairs), encoder)
        embeddings = encode(encoder, [text for _, text in pairs])
        shard = write_shard(
            "instructions",
            pa.table(
                {
                    "task_id": [task_id for task_id, _ in pairs],
                    "instruction": [text for _, text in pairs],
                    "encoder": [encoder] * len(pairs),
                    "embedding": [row.tolist() for row in embeddings],
                },
                schema=INSTRUCTIONS,
            ),
            workspace.shard_path("instructions", 0, key), catalog.store,
        )
        summary = {"tasks": len(proposed), "instructions": len(pairs),
                   **({"proposals": proposals.model_dump(exclude={"tasks"})} if proposals else {}),
                   **({"experts_left_out": [r.task_id for r in weak]} if weak else {})}
        result = TasksResult(unit_key=key, task_ids=[t.task_id for t in proposed], instructions=len(pairs),
                             skipped=False, proposals_valid=proposals.valid if proposals else 0,
                             proposals_rejected=proposals.rejected if proposals else {},
                             experts_left_out=[r.task_id for r in weak])
        return UnitOutput(summary, [shard], {"tasks": task_rows(proposed, config.name, key)}, value=result)

    output = StageUnits(catalog, STAGE, config.name, 0).run(key, work)
    if output is None:
        ids = [t.task_id for t in load_tasks(workspace, key)]
        log.info("generate_tasks: %d tasks already registered (%s), skipped", len(ids), key)
        summary = catalog.query("SELECT summary FROM stage_runs WHERE unit_key = ?", [key])
        left_out = json.loads(summary[0][0] or "{}").get("experts_left_out", []) if summary else []
        return TasksResult(unit_key=key, task_ids=ids, instructions=0, skipped=True,
                           experts_left_out=left_out)  # as registered: the proposer's dropped tasks too
    log.info("generate_tasks: registered %d tasks: %s", len(output.value.task_ids), ", ".join(output.value.task_ids))
    return output.value
