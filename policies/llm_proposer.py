"""Optional LLM task proposer: any OpenAI-compatible chat endpoint proposes tasks over the
campaign's specs. Every proposal is parsed against the task schema and the spec it names;
invalid ones are rejected and counted by reason. Proposals of a new colour binding become new
tasks; proposals of an existing one add paraphrases to it."""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from collections.abc import Callable

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from envs.suite import bind_task, task_id_of
from schemas.experts import load_expert_table
from policies.openai_chat import ChatUnavailable as ProposerUnavailable
from policies.openai_chat import complete
from schemas.config import ProposerConfig, TasksConfig
from schemas.task_spec import TaskSpec
from schemas.tasks import Colour, TaskRecord
from schemas.wordings import held_out_word_in, held_out_wording, plain

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
    if any(not re.search(rf"\b{re.escape(c)}\b", text, re.IGNORECASE)
           for text in proposal.instructions for c in proposal.colours.values()):
        return "colour_not_said"
    return None


def _held_out(unseen_instructions: list[str], instructions: list[str]) -> set[str]:
    """What evaluation says to a task and training must never (compared plain: any case, no punctuation):
    its held-out paraphrases, and the held-out wording of its instructions (stages/evaluate.py's
    held_out_wording split says the canonical one's; a new task's canonical is not known before the filter)."""
    return {plain(text) for text in [*unseen_instructions, *map(held_out_wording, instructions)]}


def _keep_instructions(said: list[str], known: list[str], held_out: set[str], others: set[str],
                       rejected: Counter[str]) -> list[str]:
    """The proposed instructions training may use for a task that already says `known`, each counted in
    `rejected` if dropped: empty, a repeat (any case or punctuation), another task's instruction, or
    held-out text (one of `held_out`, or a word only the held-out wording uses)."""
    seen = {plain(text) for text in known}
    kept = []
    for text in (text.strip() for text in said):
        key = plain(text)
        reason = ("empty_instruction" if not key else "repeated_instruction" if key in seen
                  else "other_task_instruction" if key in others
                  else "held_out_instruction" if key in held_out or held_out_word_in(text) else None)
        if reason:
            rejected[reason] += 1
            continue
        seen.add(key)
        kept.append(text)
    return kept


def merge_proposals(
    content: str, specs: dict[str, TaskSpec], config: TasksConfig, tasks: list[TaskRecord],
    also_weak: frozenset[str] = frozenset(),
) -> ProposalOutcome:
    """Pure: the tasks after adding the valid proposals in `content` (the model's answer). A new binding
    becomes a task only if the config would take it (tasks.include, a scripted expert at target unless
    tasks.weak_experts: keep; `also_weak`: task ids measured below it elsewhere, the campaign's randomisation)
    and at least tasks.paraphrases of its instructions survive the filter."""
    rejected: Counter[str] = Counter()
    try:
        raw = json.loads(content).get("tasks", [])
    except (json.JSONDecodeError, AttributeError):
        return ProposalOutcome(tasks=tasks, new_tasks=0, valid=0, rejected={"not_json": 1})
    if not isinstance(raw, list):
        return ProposalOutcome(tasks=tasks, new_tasks=0, valid=0, rejected={"schema": 1})
    weak = load_expert_table().flagged() | also_weak if config.weak_experts == "skip" else set()
    by_id = {t.task_id: t for t in tasks}
    valid = new = 0
    for item in raw:
        try:
            proposal = Proposal.model_validate(item)
        except ValidationError:
            rejected["schema"] += 1
            continue
        reason = _check(proposal, specs)
        if reason:
            rejected[reason] += 1
            continue
        spec = specs[proposal.spec]
        colours = {role: proposal.colours[role] for role in spec.objects}  # the spec's role order
        task_id = task_id_of(spec, colours)
        if task_id not in by_id and config.include is not None and task_id not in config.include:
            rejected["not_included"] += 1
            continue
        if task_id not in by_id and task_id in weak:
            rejected["weak_expert"] += 1
            continue
        others = {plain(text) for other in by_id.values() if other.task_id != task_id
                  for text in [*other.instructions, *other.unseen_instructions]}
        if task_id in by_id:
            known = by_id[task_id]
            kept = _keep_instructions(proposal.instructions, known.instructions,
                                      _held_out(known.unseen_instructions, known.instructions), others, rejected)
            by_id[task_id] = known.model_copy(update={"instructions": known.instructions + kept})
        else:
            unseen = [template.format(**colours) for template in spec.split.unseen_templates]  # as bind_task says them
            kept = _keep_instructions(proposal.instructions, [], _held_out(unseen, proposal.instructions), others,
                                      rejected)
            if len(kept) < max(3, config.paraphrases):
                rejected["too_few_instructions"] += 1
                continue
            by_id[task_id] = bind_task(spec, colours, kept, config)
            new += 1
        valid += 1
    return ProposalOutcome(tasks=list(by_id.values()), new_tasks=new, valid=valid, rejected=dict(rejected))


def propose(config: TasksConfig, specs: dict[str, TaskSpec], tasks: list[TaskRecord],
            weak_among: Callable[[list[TaskRecord]], set[str]] | None = None) -> ProposalOutcome:
    """The templates `tasks` with the LLM's proposals merged in (merge_proposals).

    Args:
        weak_among: the ids among new bindings whose expert is below target under the campaign's own conditions
            (measured by the caller); the answer is merged again with them weak, so its counts say what was kept."""
    proposer = config.proposer
    try:
        content = chat(proposer, build_messages(specs, proposer.proposals))
    except ProposerUnavailable as exc:
        if not proposer.fallback_to_templates:
            raise
        log.warning("%s; tasks.proposer.fallback_to_templates is set: template tasks only", exc)
        return ProposalOutcome(tasks=tasks, new_tasks=0, valid=0, rejected={"unreachable": 1})
    outcome = merge_proposals(content, specs, config, tasks)
    templates = {t.task_id for t in tasks}
    late = weak_among([t for t in outcome.tasks if t.task_id not in templates]) if weak_among else set()
    if late:
        outcome = merge_proposals(content, specs, config, tasks, frozenset(late))
    log.info("generate_tasks: the LLM proposed %d valid tasks (%d new), rejected %s",
             outcome.valid, outcome.new_tasks, outcome.rejected or "none")
    return outcome
