"""Optional LLM task proposer: any OpenAI-compatible chat endpoint proposes tasks over the
campaign's specs. Every proposal is parsed against the task schema and the spec it names;
invalid ones are rejected and counted by reason. Proposals of a new colour binding become new
tasks; proposals of an existing one add paraphrases to it."""

from __future__ import annotations

import json
import logging
from collections import Counter

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from envs.suite import bind_task, task_id_of
from policies.openai_chat import ChatUnavailable as ProposerUnavailable
from policies.openai_chat import complete
from schemas.config import ProposerConfig, TasksConfig
from schemas.task_spec import TaskSpec
from schemas.tasks import Colour, TaskRecord
from schemas.wordings import held_out_wording

log = logging.getLogger("sim2act.policies.llm_proposer")


class Proposal(BaseModel):
    model_config = ConfigDict(extra="forbid")

    spec: str
    colours: dict[str, Colour] = {}
    instructions: list[str] = Field(min_length=3)


class ProposalOutcome(BaseModel):
    tasks: list[TaskRecord]
    new_tasks: int
    valid: int
    rejected: dict[str, int]  # reason -> count


def build_messages(specs: dict[str, TaskSpec], count: int) -> list[dict[str, str]]:
    catalogue = [
        {"spec": s.name, "example": s.templates[0],
         "roles": {role: obj.colours for role, obj in s.objects.items()}}
        for s in specs.values()
    ]
    return [
        {"role": "system", "content": (
            "You propose language-described robot tasks. Answer with JSON only: "
            '{"tasks": [{"spec": <spec name>, "colours": {<role>: <colour>}, "instructions": [<3 or more '
            "different ways to say the task, each naming every bound colour>]}]}. Use only the specs, roles and "
            "colours given; bind distinct colours to distinct roles.")},
        {"role": "user", "content": f"Propose {count} tasks over these specs:\n{json.dumps(catalogue, indent=1)}"},
    ]


def chat(config: ProposerConfig, messages: list[dict[str, str]]) -> str:
    """One chat completion (policies.openai_chat); the answer's message content."""
    return complete(config, messages, who="LLM proposer").content


def _check(proposal: Proposal, specs: dict[str, TaskSpec]) -> str | None:
    """None if the proposal fits its spec, else the reason it is rejected."""
    spec = specs.get(proposal.spec)
    if spec is None:
        return "unknown_spec"
    if set(proposal.colours) != set(spec.objects):
        return "wrong_roles"
    if any(c not in spec.objects[r].colours for r, c in proposal.colours.items()):
        return "colour_not_allowed"
    if len(set(proposal.colours.values())) != len(proposal.colours):
        return "repeated_colour"
    if any(c not in text for text in proposal.instructions for c in proposal.colours.values()):
        return "colour_not_said"
    return None


def _held_out(task: TaskRecord) -> set[str]:
    """What evaluation says to `task` and training must never: its held-out paraphrases, and the held-out
    wording of its instructions (stages/evaluate.py's held_out_wording split). A model's proposal that
    repeats one is dropped (counted `held_out_instruction`), not trained on."""
    return set(task.unseen_instructions) | {held_out_wording(text) for text in task.instructions}


def merge_proposals(
    content: str, specs: dict[str, TaskSpec], config: TasksConfig, tasks: list[TaskRecord]
) -> ProposalOutcome:
    """Pure: the tasks after adding the valid proposals in `content` (the model's answer)."""
    rejected: Counter[str] = Counter()
    try:
        raw = json.loads(content).get("tasks", [])
    except (json.JSONDecodeError, AttributeError):
        return ProposalOutcome(tasks=tasks, new_tasks=0, valid=0, rejected={"not_json": 1})
    by_id = {t.task_id: t for t in tasks}
    valid = new = 0
    for item in raw if isinstance(raw, list) else []:
        try:
            proposal = Proposal.model_validate(item)
        except ValidationError:
            rejected["schema"] += 1
            continue
        reason = _check(proposal, specs)
        if reason:
            rejected[reason] += 1
            continue
        valid += 1
        spec = specs[proposal.spec]
        colours = {role: proposal.colours[role] for role in spec.objects}  # the spec's role order
        task_id = task_id_of(spec, colours)
        said = [text.strip() for text in proposal.instructions]
        if task_id in by_id:
            known = by_id[task_id]
            extra = [text for text in said if text not in known.instructions]
            kept = [text for text in extra if text not in _held_out(known)]
            if len(kept) < len(extra):
                rejected["held_out_instruction"] += len(extra) - len(kept)
            by_id[task_id] = known.model_copy(update={"instructions": known.instructions + kept})
        else:
            bound = bind_task(spec, colours, list(dict.fromkeys(said)), config)
            kept = [text for text in bound.instructions if text not in _held_out(bound)]
            if len(kept) < len(bound.instructions):
                rejected["held_out_instruction"] += len(bound.instructions) - len(kept)
            if not kept:
                continue
            by_id[task_id] = bound.model_copy(update={"instructions": kept})
            new += 1
    return ProposalOutcome(tasks=list(by_id.values()), new_tasks=new, valid=valid, rejected=dict(rejected))


def propose(config: TasksConfig, specs: dict[str, TaskSpec], tasks: list[TaskRecord]) -> ProposalOutcome:
    proposer = config.proposer
    try:
        content = chat(proposer, build_messages(specs, proposer.proposals))
    except ProposerUnavailable as exc:
        if not proposer.fallback_to_templates:
            raise
        log.warning("%s; tasks.proposer.fallback_to_templates is set: template tasks only", exc)
        return ProposalOutcome(tasks=tasks, new_tasks=0, valid=0, rejected={"unreachable": 1})
    outcome = merge_proposals(content, specs, config, tasks)
    log.info("generate_tasks: the LLM proposed %d valid tasks (%d new), rejected %s",
             outcome.valid, outcome.new_tasks, outcome.rejected or "none")
    return outcome
