"""The task suite: the concrete tasks the specs make. A spec (schemas/task_specs) is an
environment, object roles and templates; a task binds colours to the roles and says it at least
three ways. Pure and deterministic for a seed: the generate_tasks stage registers what these
functions return, and the CLI, the benches and the tests call them directly."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from envs.registry import check_spec
from schemas.config import ConfigError, TasksConfig
from schemas.experts import load_expert_table
from schemas.keys import derive_seed
from schemas.task_spec import SuiteEntry, TaskSpec, load_specs
from schemas.tasks import TaskRecord


def _bindings(spec: TaskSpec, allowed: list[str] | None) -> list[dict[str, str]]:
    """Every assignment of distinct colours to the spec's object roles, in spec order."""
    roles = list(spec.objects)
    choices = [[c for c in spec.objects[r].colours if allowed is None or c in allowed] for r in roles]
    return [dict(zip(roles, combo)) for combo in itertools.product(*choices) if len(set(combo)) == len(combo)]


def task_id_of(spec: TaskSpec, colouring: dict[str, str]) -> str:
    return "-".join([spec.name, *colouring.values()])


def bind_task(spec: TaskSpec, colouring: dict[str, str], instructions: list[str], config: TasksConfig) -> TaskRecord:
    """The task one binding of colours to a spec's roles makes, said with `instructions`: its
    split, horizon and held-out paraphrases follow from the spec and the config alone."""
    task_id = task_id_of(spec, colouring)
    unseen_colours = set(spec.split.unseen_colours) | set(config.unseen_colours)
    unseen = task_id in spec.split.unseen_tasks or any(c in unseen_colours for c in colouring.values())
    return TaskRecord(
        task_id=task_id, spec=spec.name, family=spec.family, env_name=spec.env, object_colours=colouring,
        instructions=instructions, split="unseen" if unseen else "seen",
        horizon=config.horizon.get(spec.name, spec.horizon),
        unseen_instructions=[template.format(**colouring) for template in spec.split.unseen_templates],
    )


def expand_spec(spec: TaskSpec, config: TasksConfig, seed: int, skip: frozenset[str] = frozenset()) -> list[TaskRecord]:
    """Pure: the concrete tasks one spec yields under a tasks config, leaving out `skip` ids
    before max_tasks_per_spec counts."""
    if len(spec.templates) < config.paraphrases:
        raise ConfigError(f"tasks.paraphrases: spec {spec.name} has {len(spec.templates)} templates, "
                          f"{config.paraphrases} asked")
    tasks = []
    kept = [b for b in _bindings(spec, config.colours) if task_id_of(spec, b) not in skip]
    for colouring in kept[: config.max_tasks_per_spec]:
        rng = np.random.default_rng(derive_seed(seed, task_id_of(spec, colouring), "paraphrases"))
        order = [0, *(1 + rng.permutation(len(spec.templates) - 1))]
        said = [spec.templates[i].format(**colouring) for i in order[: config.paraphrases]]
        tasks.append(bind_task(spec, colouring, said, config))
    return tasks


def generate_tasks(config: TasksConfig, seed: int) -> list[TaskRecord]:
    """Pure: the concrete tasks a tasks config describes. Raises ConfigError for what does not exist."""
    suite = load_specs(config.spec_files)
    flagged = frozenset(load_expert_table().flagged() if config.weak_experts == "skip" else ())
    weak = sorted(set(config.include or ()) & flagged)
    if weak:
        raise ConfigError(f"tasks.include: {weak[0]!r} has a scripted expert below target (docs/experts.md); "
                          "set tasks.weak_experts: keep to use it")
    tasks = []
    for name in config.specs:
        if name not in suite:
            raise ConfigError(f"tasks.specs: unknown spec {name!r} (`sim2act tasks list` shows the suite)")
        check_spec(suite[name].spec, suite[name].origin)
        tasks.extend(expand_spec(suite[name].spec, config, seed, skip=flagged))
    unknown_horizons = sorted(set(config.horizon) - set(config.specs))
    if unknown_horizons:
        raise ConfigError(f"tasks.horizon: {unknown_horizons[0]!r} is not one of tasks.specs")
    if config.include is not None:
        known = {t.task_id for t in tasks}
        unknown = sorted(set(config.include) - known)
        if unknown:
            raise ConfigError(f"tasks.include: unknown task {unknown[0]!r} (known: {', '.join(sorted(known))})")
        tasks = [t for t in tasks if t.task_id in config.include]
    if not tasks:
        raise ConfigError("tasks: the config yields no task")
    return tasks


def weak_tasks_left_out(config: TasksConfig) -> list[str]:
    """Pure: the tasks the config's specs and colours would bind that generate_tasks leaves out because
    their scripted expert is below target (tasks.weak_experts: skip), for the one line that says so."""
    if config.weak_experts == "keep" or config.include is not None:  # an include list names a weak task: refused
        return []
    suite, flagged = load_specs(config.spec_files), load_expert_table().flagged()
    ids = {task_id_of(suite[name].spec, b) for name in config.specs if name in suite
           for b in _bindings(suite[name].spec, config.colours)}
    return sorted(ids & flagged)


def short_horizons(config: TasksConfig, tasks: list[TaskRecord]) -> str:
    """Pure: '' or the one line naming each spec whose tasks.horizon override is shorter than its scripted experts'
    mean episode in the shipped table (measured at the spec's own horizon): few of its expert episodes can succeed.
    Said, not refused: a short horizon is a test's or a smoke run's choice, and the filter keeps what succeeds."""
    table = load_expert_table().rows
    short = []
    for spec, horizon in config.horizon.items():
        lengths = [table[t.task_id].mean_length for t in tasks if t.spec == spec and t.task_id in table]
        mean = sum(lengths) / len(lengths) if lengths else 0.0
        if horizon < mean:
            short.append(f"{spec} {horizon} < {mean:.0f}")
    if not short:
        return ""
    return ("tasks.horizon: shorter than the scripted expert's mean episode at the spec's own horizon (docs/experts.md), "
            f"few of its episodes can succeed and the filter keeps only those: {', '.join(short)} steps")


def subtask_instructions(task: TaskRecord, suite: dict[str, SuiteEntry]) -> list[str]:
    """A long-horizon task's sub-tasks, said canonically with its colours, in order ([]: not long-horizon,
    or a spec the suite does not hold, such as a proposer's)."""
    entry = suite.get(task.spec)
    subtasks = entry.spec.subtasks if entry else []
    return [suite[sub.spec].spec.templates[0].format(**{role: task.object_colours[mine] for role, mine in sub.objects.items()})
            for sub in subtasks]


def suite_tasks(spec_files: list[Path] = (), seed: int = 0) -> list[TaskRecord]:
    """Every task of the built-in suite and the given files, all colours bound."""
    names = list(load_specs(list(spec_files)))
    return generate_tasks(TasksConfig(specs=names, spec_files=list(spec_files), weak_experts="keep"), seed)
