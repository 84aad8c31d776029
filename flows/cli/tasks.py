"""The task suite: `sim2act tasks list | show | validate | experts`."""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

from flows.cli.common import Commands, noise_level, output_file, positive_int
from schemas.config import PRESETS, ConfigError
from schemas.tasks import FAMILIES
from schemas.workspace import write_text_atomically


def cmd_tasks_list(args: argparse.Namespace) -> int:
    import pyarrow as pa

    from envs.suite import suite_tasks
    from schemas.experts import load_expert_table
    from warehouse.sql import format_rows

    experts = load_expert_table().rows

    def expert(task_id: str) -> str:
        row = experts.get(task_id)
        return "not measured" if row is None else f"{row.success_rate:.0%}" + (" flagged" if row.below_target else "")

    rows = [
        {"task_id": t.task_id, "family": t.family, "env": t.env_name, "split": t.split, "horizon": t.horizon,
         "expert": expert(t.task_id), "instruction": t.instruction}
        for t in suite_tasks(args.spec_file)
        if (args.family is None or t.family == args.family) and (args.split is None or t.split == args.split)
    ]
    if args.format == "json":
        print(json.dumps(rows, indent=1))
    else:
        print(format_rows(pa.Table.from_pylist(rows), "table"))
    return 0


def cmd_tasks_show(args: argparse.Namespace) -> int:
    from envs.suite import suite_tasks

    found = [t for t in suite_tasks(args.spec_file) if t.task_id == args.task_id]
    if not found:
        raise ConfigError(f"tasks show: no task {args.task_id!r} in the suite (`sim2act tasks list` shows them)")
    print(found[0].model_dump_json(indent=1))
    return 0


def cmd_tasks_validate(args: argparse.Namespace) -> int:
    from envs.registry import check_spec
    from envs.suite import expand_spec
    from schemas.config import TasksConfig
    from schemas.config import read_text_file
    from schemas.task_spec import builtin_spec_file, load_specs, parse_spec_file

    if not args.file.is_file():
        raise ConfigError(f"tasks validate: expected a YAML spec file, got "
                          f"{'the folder ' if args.file.is_dir() else 'no such file '}{args.file}")
    specs = parse_spec_file(read_text_file(args.file, "tasks validate"), str(args.file))
    if not builtin_spec_file(args.file):  # (a built-in file itself is the suite's)
        load_specs([args.file])  # a name the built-in suite has already is refused here, as every campaign would
    campaign = None
    if args.preset:  # a campaign binds only its tasks.colours: the count it would see, beside the file's own
        from schemas.config import load_config

        campaign = load_config(args.preset).tasks
    count = bound = 0
    for spec in specs:
        check_spec(spec, str(args.file))
        count += len(expand_spec(spec, TasksConfig(specs=[spec.name]), seed=0))
        if campaign is not None:
            bound += len(expand_spec(spec, campaign.model_copy(update={"specs": [spec.name]}), seed=0))
    within = "" if campaign is None else f"; {bound} in a campaign of preset {args.preset} (its tasks.colours)"
    print(f"{args.file}: {len(specs)} spec(s), {count} task(s){within}, valid")
    return 0


def cmd_tasks_experts(args: argparse.Namespace) -> int:
    from bench.expert_table import markdown
    from envs.expert_check import measure_experts
    from envs.suite import suite_tasks
    from schemas.config import RandomiseConfig
    from schemas.experts import TARGET, default_table_path, load_expert_table, save_expert_table

    suite = suite_tasks(args.spec_file)
    unknown = sorted(set(args.task) - {t.task_id for t in suite})
    if unknown:
        raise ConfigError(f"tasks experts: --task: expected task ids of the suite (`sim2act tasks list`), got {', '.join(unknown)}")
    tasks = [
        t for t in suite
        if (args.family is None or t.family == args.family) and (not args.task or t.task_id in args.task)
    ]
    if not tasks:
        among = f" among --task {', '.join(args.task)}" if args.task else ""
        raise ConfigError(f"tasks experts: no task of --family {args.family}{among}")
    done = itertools.count(1)

    def report(row) -> None:
        print(f"[{next(done)}/{len(tasks)}] {row.task_id}: {row.successes}/{row.episodes}", flush=True)

    randomise = RandomiseConfig(enabled=not args.no_randomise)
    rows = measure_experts(tasks, args.episodes, args.noise, randomise, args.workers, args.command_line, report)
    record = args.record or default_table_path()
    table = load_expert_table(record).merged(rows)  # a partial run replaces only its own rows
    save_expert_table(table, record)
    shown = record.relative_to(Path.cwd()) if record.is_relative_to(Path.cwd()) else record
    write_text_atomically(args.out, markdown(table, [t.task_id for t in suite], str(shown)))
    below = sum(r.below_target for r in rows)
    print(f"{len(rows)} tasks measured, {below} below {TARGET:.0%}; record {record}, "
          f"table written to {args.out}")
    return 0


def register(commands: Commands) -> None:
    tasks = commands.add_parser("tasks", help="the task suite: list, show, validate spec files")
    task_commands = tasks.add_subparsers(dest="tasks_command", required=True)
    listing = task_commands.add_parser("list", help="every task of the suite")
    listing.add_argument("--family", choices=FAMILIES)
    listing.add_argument("--split", choices=("seen", "unseen"))
    listing.add_argument("--format", choices=("table", "json"), default="table")
    listing.set_defaults(handler=cmd_tasks_list)
    show = task_commands.add_parser("show", help="one task, in full")
    show.add_argument("task_id")
    show.set_defaults(handler=cmd_tasks_show)
    experts = task_commands.add_parser("experts", help="measure each task's scripted expert, write the table")
    experts.add_argument("--episodes", type=positive_int, default=10)
    experts.add_argument("--noise", type=noise_level, default=0.1, help="expert action noise, as in exploration")
    experts.add_argument("--no-randomise", action="store_true", help="nominal scenes, no domain randomisation")
    experts.add_argument("--family", choices=FAMILIES)
    experts.add_argument("--task", action="append", default=[], help="only these task ids")
    experts.add_argument("--workers", type=positive_int, default=2)
    experts.add_argument("--out", type=output_file, default=Path("docs/experts.md"))
    experts.add_argument("--record", type=output_file, help="default: the suite's own schemas/task_specs/experts.json")
    experts.set_defaults(handler=cmd_tasks_experts)
    for sub in (listing, show, experts):
        sub.add_argument("--spec-file", type=Path, action="append", default=[], help="extra YAML spec file")
    validate = task_commands.add_parser("validate", help="check a YAML spec file")
    validate.add_argument("file", type=Path)
    validate.add_argument("--preset", choices=PRESETS,
                          help="also count the tasks a campaign of this preset binds (only its tasks.colours)")
    validate.set_defaults(handler=cmd_tasks_validate)
