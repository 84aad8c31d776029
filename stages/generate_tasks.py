"""generate_tasks: the campaign's tasks (envs.suite: the specs bound to colours, said at least
three ways), or an LLM proposer's, registered with their instruction embeddings.

Unit of work: the whole task list, keyed by the tasks themselves, the encoder and the proposer
settings; registers the `tasks` rows and one `instructions` shard.
"""

from __future__ import annotations

import logging

import pyarrow as pa

from envs.registry import check_render
from envs.suite import generate_tasks
from schemas.config import CampaignConfig
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

    def did_work(self) -> bool:
        return not self.skipped

    def metrics(self) -> dict[str, float]:
        if self.skipped:
            return {}
        return {"tasks.count": len(self.task_ids), "tasks.proposals_valid": self.proposals_valid,
                **{f"tasks.proposals_rejected.{k}": v for k, v in self.proposals_rejected.items()}}


def tasks_unit_key(config: CampaignConfig, tasks: list[TaskRecord]) -> str:
    """Keyed by the template tasks themselves (editing a spec file makes new tasks) and the
    proposer settings: an LLM is asked once per key, and its answer is what gets registered."""
    reads = {"campaign": config.name, "encoder": config.train.model.language_encoder,
             "proposer": config.tasks.proposer}
    return unit_key(STAGE, VERSION, reads, [t.model_dump_json() for t in tasks])


def run_generate_tasks(workspace: Workspace, config: CampaignConfig) -> TasksResult:
    """Unit of work: the campaign's whole task list, keyed by the tasks (tasks_unit_key). Registers the
    `tasks` rows and the `instructions` shard (every instruction's embedding by the campaign's encoder);
    with a proposer, the LLM's tasks in place of the templates'."""
    catalog = Catalog(workspace.catalog)
    tasks = generate_tasks(config.tasks, config.seed)
    check_render(config.render, tasks)  # a flow started from the UI is refused as `sim2act run` refuses it
    key = tasks_unit_key(config, tasks)

    def work() -> UnitOutput:
        from policies.language import encode  # loading the encoder is slow: only when there is work

        proposed, proposals = tasks, None
        if config.tasks.proposer is not None:
            from policies.llm_proposer import propose

            suite = load_specs(config.tasks.spec_files)
            proposals = propose(config.tasks, {n: suite[n].spec for n in config.tasks.specs}, tasks)
            proposed = proposals.tasks
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
                   **({"proposals": proposals.model_dump(exclude={"tasks"})} if proposals else {})}
        result = TasksResult(unit_key=key, task_ids=[t.task_id for t in proposed], instructions=len(pairs),
                             skipped=False, proposals_valid=proposals.valid if proposals else 0,
                             proposals_rejected=proposals.rejected if proposals else {})
        return UnitOutput(summary, [shard], {"tasks": task_rows(proposed, config.name, key)}, value=result)

    output = StageUnits(catalog, STAGE, config.name, 0).run(key, work)
    if output is None:
        ids = [t.task_id for t in load_tasks(workspace, key)]
        log.info("generate_tasks: %d tasks already registered (%s), skipped", len(ids), key)
        return TasksResult(unit_key=key, task_ids=ids, instructions=0, skipped=True)
    log.info("generate_tasks: registered %d tasks: %s", len(output.value.task_ids), ", ".join(output.value.task_ids))
    return output.value
