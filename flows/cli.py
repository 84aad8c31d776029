"""`sim2act`: a thin front over the flows and the warehouse.

Configs are validated before anything is imported or written: bad input costs one line.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path

from schemas.config import PRESETS, ConfigError, load_config
from schemas.tasks import FAMILIES
from schemas.workspace import Workspace, write_text_atomically


def _default_workspace() -> str:
    return os.environ.get("SIM2ACT_WORKSPACE", "workspace")


def configure_environment(workspace: Workspace) -> None:
    """Embedded defaults: Prefect's ephemeral API with its home in the workspace, MLflow on SQLite
    in the workspace, offscreen EGL rendering, no telemetry, no hub downloads."""
    defaults = {
        "PREFECT_HOME": str(workspace.prefect_home),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_LOGGING_EXTRA_LOGGERS": "sim2act",
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
        "MLFLOW_DISABLE_TELEMETRY": "true",
        "MLFLOW_TRACKING_URI": workspace.tracking_uri,
        "MUJOCO_GL": "egl",
        "HF_HUB_OFFLINE": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "PYTHONWARNINGS": "ignore::DeprecationWarning,ignore::FutureWarning",
        "TRANSFORMERS_VERBOSITY": "error",
        "HF_HUB_DISABLE_PROGRESS_BARS": "1",
        "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
    }
    for key, value in defaults.items():
        os.environ.setdefault(key, value)


def cmd_run(args: argparse.Namespace) -> int:
    overrides = {"iterations": args.iterations} if args.iterations is not None else {}
    config = load_config(args.preset, args.config, overrides)
    from stages.generate_tasks import generate_tasks
    from stages.train import check_trainable
    from warehouse.catalog import Catalog

    check_trainable(generate_tasks(config.tasks, config.seed))  # refused here, before any work
    workspace = Workspace.at(args.workspace)
    Catalog(workspace.catalog).check_version()
    configure_environment(workspace)
    workspace.create()
    print(
        f"sim2act: campaign {config.name!r}, {config.iterations} iteration(s), workspace {workspace.root}",
        flush=True,
    )
    from flows.bootstrap import bootstrap

    bootstrap(config=config, workspace=str(workspace.root))
    return 0


def cmd_tasks_list(args: argparse.Namespace) -> int:
    import pyarrow as pa

    from schemas.experts import load_expert_table
    from stages.generate_tasks import suite_tasks
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
    from stages.generate_tasks import suite_tasks

    found = [t for t in suite_tasks(args.spec_file) if t.task_id == args.task_id]
    if not found:
        raise ConfigError(f"tasks show: no task {args.task_id!r} in the suite (`sim2act tasks list` shows them)")
    print(found[0].model_dump_json(indent=1))
    return 0


def cmd_tasks_validate(args: argparse.Namespace) -> int:
    from envs.registry import check_spec
    from schemas.config import TasksConfig
    from schemas.task_spec import parse_spec_file
    from stages.generate_tasks import expand_spec

    if not args.file.is_file():
        raise ConfigError(f"tasks validate: no such file {args.file}")
    specs = parse_spec_file(args.file.read_text(), str(args.file))
    count = 0
    for spec in specs:
        check_spec(spec, str(args.file))
        count += len(expand_spec(spec, TasksConfig(specs=[spec.name]), seed=0))
    print(f"{args.file}: {len(specs)} spec(s), {count} task(s), valid")
    return 0


def cmd_tasks_experts(args: argparse.Namespace) -> int:
    from schemas.config import RandomiseConfig
    from schemas.experts import TARGET, default_table_path, load_expert_table, save_expert_table
    from stages.expert_table import markdown, measure_experts
    from stages.generate_tasks import suite_tasks

    os.environ.setdefault("MUJOCO_GL", "egl")
    suite = suite_tasks(args.spec_file)
    tasks = [
        t for t in suite
        if (args.family is None or t.family == args.family) and (not args.task or t.task_id in args.task)
    ]
    if not tasks:
        raise ConfigError("tasks experts: no task matches --family/--task")
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


def cmd_bench_envs(args: argparse.Namespace) -> int:
    from bench.envs import bench_envs, markdown

    if args.steps < 1:
        raise ConfigError(f"bench envs: --steps must be at least 1, got {args.steps}")
    os.environ.setdefault("MUJOCO_GL", "egl")
    rows = bench_envs(args.family or list(FAMILIES), args.steps)
    table = markdown(rows, args.command_line)
    print(table)
    if args.out:
        write_text_atomically(args.out, table)
        print(f"written to {args.out}")
    return 0


def cmd_sql(args: argparse.Namespace) -> int:
    from warehouse.catalog import Catalog
    from warehouse.sql import run_sql

    print(run_sql(Catalog(Workspace.at(args.workspace).catalog), args.query, args.format))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sim2act", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="run a bootstrap campaign (embedded: no server needed)")
    run.add_argument("--preset", choices=PRESETS, default="default")
    run.add_argument("--config", type=Path, help="YAML file whose fields override the preset's")
    run.add_argument("--iterations", type=int, help="number of bootstrap iterations")
    run.add_argument("--workspace", default=_default_workspace(), help="default: $SIM2ACT_WORKSPACE or ./workspace")
    run.set_defaults(handler=cmd_run)

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
    experts.add_argument("--episodes", type=int, default=10)
    experts.add_argument("--noise", type=float, default=0.1, help="expert action noise, as in exploration")
    experts.add_argument("--no-randomise", action="store_true", help="nominal scenes, no domain randomisation")
    experts.add_argument("--family", choices=FAMILIES)
    experts.add_argument("--task", action="append", default=[], help="only these task ids")
    experts.add_argument("--workers", type=int, default=2)
    experts.add_argument("--out", type=Path, default=Path("docs/experts.md"))
    experts.add_argument("--record", type=Path, help="default: the suite's own schemas/task_specs/experts.json")
    experts.set_defaults(handler=cmd_tasks_experts)
    for sub in (listing, show, experts):
        sub.add_argument("--spec-file", type=Path, action="append", default=[], help="extra YAML spec file")
    validate = task_commands.add_parser("validate", help="check a YAML spec file")
    validate.add_argument("file", type=Path)
    validate.set_defaults(handler=cmd_tasks_validate)

    bench = commands.add_parser("bench", help="benchmarks: speed side by side, as ratios")
    bench_commands = bench.add_subparsers(dest="bench_command", required=True)
    bench_env = bench_commands.add_parser("envs", help="env steps/s per family: raw physics, env, adapter, render")
    bench_env.add_argument("--steps", type=int, default=500, help="timed control steps per layer")
    bench_env.add_argument("--family", choices=FAMILIES, action="append", help="default: every family")
    bench_env.add_argument("--out", type=Path, help="also write the table as markdown here")
    bench_env.set_defaults(handler=cmd_bench_envs)

    sql = commands.add_parser("sql", help="read-only SQL over the warehouse (tasks, episodes, steps, triplets, ...)")
    sql.add_argument("query")
    sql.add_argument("--format", choices=("table", "csv", "json"), default="table")
    sql.add_argument("--workspace", default=_default_workspace())
    sql.set_defaults(handler=cmd_sql)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.command_line = " ".join(["sim2act", *argv])  # reports say the command that made them
    try:
        return args.handler(args)
    except ConfigError as exc:
        print(f"sim2act: config error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sim2act: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except Exception as exc:  # a known failure mode gets one line, not a traceback
        from warehouse.catalog import CatalogMissing, CatalogVersionError
        from warehouse.sql import ReadOnlyViolation

        if isinstance(exc, (CatalogMissing, CatalogVersionError, ReadOnlyViolation)):
            print(f"sim2act: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
