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

from flows.lifetime import watch
from schemas.config import PRESETS, ConfigError, load_config, parse_settings
from schemas.service import HOST, ServiceConfig
from schemas.tasks import FAMILIES
from schemas.workspace import Workspace, write_text_atomically
from warehouse.video import CONTROL_FPS


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
    from flows.service import running_urls

    # While `sim2act up` runs on this workspace, runs report to its servers and show in its UIs.
    for key, value in running_urls(workspace).items():
        os.environ.setdefault(key, value)


def log_stages_to_stderr() -> None:
    """Outside a flow (`sim2act train`, `eval`) no Prefect handler takes the stages' log lines, and
    the progress bar is drawn only on a terminal: without this, a run piped to a file is silent."""
    import logging

    logger = logging.getLogger("sim2act")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s | %(levelname)-7s | %(name)s - %(message)s", "%H:%M:%S"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)


def cmd_run(args: argparse.Namespace) -> int:
    overrides = parse_settings(args.set)
    if args.iterations is not None:
        overrides["iterations"] = args.iterations
    config = load_config(args.preset, args.config, overrides)
    from stages.generate_tasks import generate_tasks
    from warehouse.catalog import Catalog
    from warehouse.training_reader import check_where

    generate_tasks(config.tasks, config.seed)  # a task config that cannot run is refused here, before any work
    check_where(config.train.where)
    workspace = Workspace.at(args.workspace)
    Catalog(workspace.catalog).check_version()
    configure_environment(workspace)
    workspace.create()
    watch()  # the temporary Prefect server and the workers end with this command, however it ends
    print(
        f"sim2act: campaign {config.name!r}, {config.iterations} iteration(s), workspace {workspace.root}",
        flush=True,
    )
    from flows.bootstrap import bootstrap

    bootstrap(config=config, workspace=str(workspace.root), continue_campaign=args.continue_campaign)
    from stages.report import campaign_summary

    same = _same_campaign_flags(args)
    print("\n" + campaign_summary(Catalog(workspace.catalog), config.name, [
        f"the results table (iterations, per spec, baselines):  sim2act report {same}",
        f"dashboard (episodes, videos, SQL panels), MLflow UI:  sim2act up {same}",
        f"the warehouse in SQL:  sim2act sql \"SELECT * FROM task_success\" --workspace {workspace.root}",
        f"the champion on any split or task file:  sim2act eval --model champion {same}",
    ]), flush=True)
    return 0


def _same_campaign_flags(args: argparse.Namespace) -> str:
    """The flags that name this campaign again, as the user gave them."""
    flags = [f"--preset {args.preset}"] + ([f"--config {args.config}"] if args.config else [])
    flags += [f"--set {setting}" for setting in args.set] + [f"--workspace {args.workspace}"]
    return " ".join(flags)


def cmd_train(args: argparse.Namespace) -> int:
    config = load_config(args.preset, args.config, parse_settings(args.set))
    from flows.tracking import Tracking
    from stages.generate_tasks import generate_tasks, load_embeddings, tasks_unit_key
    from stages.index import latest_index
    from stages.train import run_train
    from warehouse.catalog import Catalog
    from warehouse.training_reader import check_where

    check_where(config.train.where)
    workspace = Workspace.at(args.workspace)
    catalog = Catalog(workspace.catalog)
    catalog.check_version()
    dataset = latest_index(workspace, config.name, args.iteration)
    if dataset is None:
        which = f"iteration {args.iteration}" if args.iteration is not None else "any iteration"
        raise ConfigError(f"--iteration: campaign {config.name!r} has no dataset for {which} in {workspace.root} "
                          "(run `sim2act run` with this config first)")
    tasks_key = tasks_unit_key(config, generate_tasks(config.tasks, config.seed))
    if not catalog.is_registered(tasks_key):
        raise ConfigError(f"tasks: this config's tasks were never generated in {workspace.root} (run `sim2act run` first)")
    configure_environment(workspace)
    log_stages_to_stderr()
    watch()  # the loader workers end with this command, however it ends
    tracking = Tracking(workspace, config)
    run_id = tracking.iteration_run(tracking.campaign_run(), dataset.iteration)
    print(f"sim2act: training on campaign {config.name!r} iteration {dataset.iteration}'s dataset "
          f"({dataset.triplets:,} triplets), MLflow run {run_id}", flush=True)
    result = run_train(
        workspace, config, dataset.iteration, dataset, tasks_key,
        load_embeddings(workspace, tasks_key, config.train.model.language_encoder),
        on_metrics=tracking.step_logger(run_id, "train."),
    )
    if result.skipped:
        state = "already trained"
    else:
        tracking.log_training_dataset(run_id, result.dataset_digest, result.dataset_shards, result.samples)
        resumed = f"resumed at step {result.resumed_at_step}, " if result.resumed_at_step else ""
        state = f"{resumed}final loss {result.history[-1]['loss']:.4f}"
    print(f"model {result.model_key}: {state}; checkpoint {result.checkpoint}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    overrides = parse_settings(args.set)
    if args.episodes is not None:
        if args.episodes < 1:
            raise ConfigError(f"--episodes: at least 1, got {args.episodes}")
        overrides.setdefault("evaluate", {})["episodes_per_task"] = args.episodes
    config = load_config(args.preset, args.config, overrides)
    from warehouse.catalog import Catalog

    workspace = Workspace.at(args.workspace)
    Catalog(workspace.catalog).check_version()
    configure_environment(workspace)
    log_stages_to_stderr()
    from flows.tracking import Tracking
    from stages.evaluate import Agent, evaluate_model, evaluated_key, episodes_per_split
    from stages.model_eval import check_model_fits, eval_cases, instruction_embeddings, resolve_model

    suite, cases = eval_cases(workspace, config, args.tasks, args.split)  # bad input refused here, before any work
    models = [resolve_model(workspace, config, ref) for ref in args.model]
    for model in models:
        check_model_fits(config, model)
    embeddings = instruction_embeddings(workspace, config, cases)
    watch()  # the rollout workers end with this command, however it ends
    tracking = Tracking(workspace, config)
    by_model = []
    for model in models:
        # the last weights are another agent than the registered (averaged) ones: their own evaluation units
        model_key = evaluated_key(model.model_key, args.weights)
        run_id = tracking.evaluation_run(model_key, suite, model.label)
        print(f"sim2act: evaluating {model.label} ({model.model_key}, trained at iteration {model.iteration}, "
              f"{weights_of_checkpoint(model.checkpoint, args.weights)} weights) on {len(cases)} case(s) of {suite}, "
              f"{'/'.join(map(str, sorted(set(episodes_per_split(config, cases).values()))))} episodes each; "
              f"MLflow run {run_id}", flush=True)
        evaluations, skipped = evaluate_model(workspace, config, model.iteration, model_key,
                                              Agent(kind="sim2act", path=model.checkpoint, weights=args.weights),
                                              cases, embeddings, suite)
        if skipped < len(evaluations):
            tracking.log_evaluation(run_id, evaluations)
        tracking.finish(run_id)
        _print_evaluations(evaluations)
        by_model.append(evaluations)
    if len(models) > 1:
        from stages.protocol import protocol_success

        print(f"\nover the {len(models)} models (training seeds): mean ± spread across them (each one's rate), "
              "pooled episodes [Wilson 95%]")
        for figure in protocol_success(by_model):
            print(f"{figure.group:<24} {figure.describe()}")
    return 0


def weights_of_checkpoint(path: str, weights: str) -> str:
    import torch

    from policies.policy import weights_of

    return weights_of(torch.load(path, map_location="cpu", weights_only=False), weights)


def _print_evaluations(evaluations) -> None:
    from stages.evaluate import group_success

    def interval(low: float, high: float) -> str:
        return f"[{low:4.0%}, {high:4.0%}]"

    print(f"\n{'task':<34} {'split':<18} {'success':>9} {'':>5}  Wilson 95%    length  instruction")
    for t in evaluations:
        print(f"{t.task_id:<34} {t.split:<18} {t.successes:>4}/{t.episodes:<4} {t.success_rate:>5.0%}  "
              f"{interval(t.ci_low, t.ci_high)}  {t.mean_length:6.1f}  {t.instruction}")
    print()
    for g in group_success(evaluations):
        print(f"{g.group:<53} {g.successes:>4}/{g.episodes:<4} {g.success_rate:>5.0%}  "
              f"{interval(g.ci_low, g.ci_high)}  {g.mean_length:6.1f}")


def _service_config(args: argparse.Namespace) -> ServiceConfig:
    from pydantic import ValidationError

    from schemas.config import describe_validation_error

    try:
        return ServiceConfig(**{f: getattr(args, f) for f in ServiceConfig.model_fields if getattr(args, f) is not None})
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc)) from None


def _print_status(rows: list[dict]) -> None:
    for row in rows:
        print(f"{row['name']:<12} {row['state']:<10} {row['url']:<36} pid {row['pid']:<8} log {row['log']}")


def cmd_up(args: argparse.Namespace) -> int:
    config = load_config(args.preset, args.config, parse_settings(args.set))  # the deployments' default campaign
    service = _service_config(args)
    from flows.service import up
    from warehouse.catalog import Catalog

    workspace = Workspace.at(args.workspace)
    catalog = Catalog(workspace.catalog)
    catalog.check_version()
    configure_environment(workspace)
    catalog.initialise()  # the dashboard reads it from the first minute
    print(f"sim2act: starting the stack over {workspace.root} (campaign {config.name!r}, nightly "
          f"{service.nightly_cron} {service.timezone})", flush=True)
    rows = up(workspace, service, config, on_ready=lambda line: print(f"  ready: {line}", flush=True))
    _print_status(rows)
    print("trigger: prefect deployment run 'bootstrap/on-demand'   (with PREFECT_API_URL="
          f"{service.url('prefect')}/api); stop: sim2act down --workspace {workspace.root}")
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    from flows.service import down

    workspace = Workspace.at(args.workspace)
    stopped = down(workspace)
    print(f"sim2act: stopped {', '.join(stopped)}" if stopped else f"sim2act: nothing runs over {workspace.root}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from flows.service import process_status

    workspace = Workspace.at(args.workspace)
    rows = process_status(workspace)
    if not rows:
        print(f"sim2act: the stack is not up over {workspace.root} (`sim2act up` starts it)")
        return 1
    _print_status(rows)
    return 0 if all(row["state"] == "up" for row in rows) else 1


def cmd_dashboard(args: argparse.Namespace) -> int:
    from dashboards.server import serve
    from warehouse.catalog import Catalog

    workspace = Workspace.at(args.workspace)
    Catalog(workspace.catalog).check_version()  # a warehouse of another layout: one line, before serving
    print(f"sim2act: dashboard over {workspace.root} at http://{args.host}:{args.port}", flush=True)
    serve(workspace, args.host, args.port)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    config = load_config(args.preset, args.config, parse_settings(args.set))
    from stages.results import results_markdown
    from warehouse.catalog import Catalog

    catalog = Catalog(Workspace.at(args.workspace).catalog)
    catalog.check_version()
    try:
        text = results_markdown(catalog, config.name, args.command_line)
    except ValueError as exc:
        raise ConfigError(f"report: {exc}") from None
    if args.out is None:
        print(text, end="")
        return 0
    write_text_atomically(args.out, text)
    print(f"sim2act: wrote {args.out}")
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


def cmd_bench_warehouse(args: argparse.Namespace) -> int:
    from bench.warehouse import QUICK, BenchSizes, bench_warehouse, markdown

    sizes = QUICK if args.quick else BenchSizes()
    if args.sql_steps:
        if min(args.sql_steps) < 1:
            raise ConfigError(f"bench warehouse: --sql-steps must be positive, got {args.sql_steps}")
        sizes = sizes.model_copy(update={"sql_steps": args.sql_steps})
    measures = bench_warehouse(sizes, args.scratch)
    return _report(args, json.dumps([m.model_dump() for m in measures], indent=1), markdown(measures, args.command_line))


def _report(args: argparse.Namespace, as_json: str, table: str) -> int:
    """A bench's result: its table (or its JSON with --json) printed, the table written to --out."""
    print(as_json if args.json else table)
    if args.out:
        write_text_atomically(args.out, table)
    return 0


def cmd_bench_rollout(args: argparse.Namespace) -> int:
    from bench.rollout import QUICK, RolloutSizes, bench_rollout, markdown

    os.environ.setdefault("MUJOCO_GL", "egl")
    bench = bench_rollout(QUICK if args.quick else RolloutSizes(), args.scratch)
    return _report(args, bench.model_dump_json(indent=1), markdown(bench, args.command_line))


def cmd_bench_train(args: argparse.Namespace) -> int:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the fine-tuned encoder case loads MiniLM from disk
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from bench.train import QUICK, TrainSizes, bench_train, markdown

    sizes = QUICK if args.quick else TrainSizes()
    if args.cases:
        sizes = sizes.model_copy(update={"cases": args.cases.split(",")})
    bench = bench_train(sizes, args.scratch)
    return _report(args, bench.model_dump_json(indent=1), markdown(bench, args.command_line))


def cmd_sql(args: argparse.Namespace) -> int:
    import duckdb

    from warehouse.catalog import Catalog
    from warehouse.sql import run_sql

    if args.as_of_iteration is not None and args.as_of_iteration < 0:
        raise ConfigError(f"sql: --as-of-iteration must be 0 or more, got {args.as_of_iteration}")
    try:
        print(run_sql(Catalog(Workspace.at(args.workspace).catalog), args.query, args.format, args.as_of_iteration))
    except duckdb.Error as exc:
        print(f"sim2act: SQL error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


def cmd_export_lerobot(args: argparse.Namespace) -> int:
    from warehouse.catalog import Catalog
    from warehouse.export_lerobot import export_lerobot

    if args.fps < 1:
        raise ConfigError(f"export lerobot: --fps must be at least 1, got {args.fps}")
    catalog = Catalog(Workspace.at(args.workspace).catalog)
    catalog.check_version()

    def report(done: int, total: int) -> None:
        print(f"\r[{done}/{total}] episodes", end="" if done < total else "\n", flush=True)

    summary = export_lerobot(catalog, args.out_dir, args.where, fps=args.fps, include_rejected=args.include_rejected,
                             repo_id=args.repo_id, progress=report)
    print(f"{summary.episodes} episodes, {summary.frames} frames, {summary.tasks} tasks, "
          f"{summary.bytes / 1e6:.1f} MB: LeRobotDataset v3.0 at {summary.out_dir}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from stages.replay import replay

    os.environ.setdefault("MUJOCO_GL", "egl")
    result = replay(Workspace.at(args.workspace), args.episode_id, args.camera, args.size, args.out, args.fps)
    print(f"{result.frames} frames of {args.episode_id} ({result.render.camera}, {result.render.image_size} px, "
          f"one per step) written to {result.path}")
    return 0


def cmd_warehouse_verify(args: argparse.Namespace) -> int:
    from warehouse.catalog import Catalog

    catalog = Catalog(Workspace.at(args.workspace).catalog)
    catalog.check_version()
    bad = catalog.verify(full=args.full)
    for path, reason in bad:
        print(f"quarantined {path}: {reason}")
    [(shards,)] = catalog.query("SELECT count(*) FROM shards")
    print(f"{shards} registered shard(s) verified{' (sha256 too)' if args.full else ''}, {len(bad)} quarantined "
          f"to {catalog.quarantine_folder}; the next `sim2act run` redoes their units")
    return 1 if bad else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sim2act", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    def campaign_parser(name: str, help: str, handler) -> argparse.ArgumentParser:
        """A command that reads a campaign config (preset, file, --set) and a workspace, as `run` does."""
        command = commands.add_parser(name, help=help)
        command.add_argument("--preset", choices=PRESETS, default="default")
        command.add_argument("--config", type=Path, help="YAML file whose fields override the preset's")
        command.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                             help="override one config field, e.g. --set train.contrastive_weight=0 (repeatable)")
        command.add_argument("--workspace", default=_default_workspace(),
                             help="default: $SIM2ACT_WORKSPACE or ./workspace")
        command.set_defaults(handler=handler)
        return command

    run = campaign_parser("run", "run a bootstrap campaign (embedded: no server needed)", cmd_run)
    run.add_argument("--iterations", type=int, help="number of bootstrap iterations")
    run.add_argument("--continue", dest="continue_campaign", action="store_true",
                     help="one iteration past the campaign's latest finished one (what the nightly deployment runs)")
    campaign_parser("train", "train the model alone on a campaign's dataset (resumes if killed)", cmd_train
                    ).add_argument("--iteration", type=int, help="whose dataset (default: the campaign's latest)")

    evaluate = campaign_parser("eval", "evaluate any model on the campaign's tasks, one split, or a task file",
                               cmd_eval)
    evaluate.add_argument("--model", required=True, action="append", metavar="REF",
                          help="champion, @alias, 3, v3, name/3, name@alias (the registry), or a model key train-...; "
                               "repeat it for several trainings (seeds): each is evaluated, then the results "
                               "protocol's mean, spread and pooled interval over them")
    evaluate.add_argument("--weights", choices=("registered", "final"), default="registered",
                          help="registered: the weights the training registers (its moving average, train.ema); "
                               "final: its last weights")
    which = evaluate.add_mutually_exclusive_group()
    which.add_argument("--tasks", type=Path, metavar="FILE", help="a task spec YAML file: its tasks, all colours")
    which.add_argument("--split", choices=("seen", "unseen", "unseen_paraphrase", "held_out_wording"),
                       help="only this split's cases (held_out_wording: seen tasks in words the generator never uses)")
    evaluate.add_argument("--episodes", type=int, help="episodes per case (default: the config's evaluate.episodes_per_task)")

    campaign_parser("report", "the results table: success per iteration beside the baselines, dataset, compute",
                    cmd_report).add_argument("--out", type=Path, help="write the Markdown here (default: print it)")

    stack_up = campaign_parser("up", "start the local stack: Prefect and MLflow servers, dashboard, deployments "
                               "(their default campaign: --preset/--config/--set)", cmd_up)
    stack_up.add_argument("--prefect-port", type=int)
    stack_up.add_argument("--mlflow-port", type=int)
    stack_up.add_argument("--dashboard-port", type=int)
    stack_up.add_argument("--nightly-cron", help="when bootstrap/nightly runs (default '0 2 * * *')")
    stack_up.add_argument("--timezone", help="of the cron line, an IANA name (default UTC)")
    for name, help, handler in (("down", "stop the local stack", cmd_down),
                                ("status", "the local stack's processes, health and URLs", cmd_status)):
        commands.add_parser(name, help=help).set_defaults(handler=handler)
    dashboard = commands.add_parser("dashboard", help="serve the warehouse dashboard alone (sim2act up starts it too)")
    dashboard.add_argument("--host", default=HOST)
    dashboard.add_argument("--port", type=int, default=ServiceConfig.model_fields["dashboard_port"].default)
    dashboard.set_defaults(handler=cmd_dashboard)
    for command in (commands.choices["down"], commands.choices["status"], dashboard):
        command.add_argument("--workspace", default=_default_workspace())

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

    def bench_parser(name: str, help: str, quick: str, handler) -> argparse.ArgumentParser:
        """A benchmark command with the options every side-by-side bench takes."""
        command = bench_commands.add_parser(name, help=help)
        command.add_argument("--json", action="store_true", help="print the figures as JSON")
        command.add_argument("--quick", action="store_true", help=quick)
        command.add_argument("--scratch", type=Path, help="folder for the throwaway workspaces (default: $TMPDIR)")
        command.add_argument("--out", type=Path, help="also write the table as markdown here")
        command.set_defaults(handler=handler)
        return command

    bench_parser("warehouse", "ingest, SQL and training-read speed vs bare references",
                 "small sizes (seconds, for a smoke check)", cmd_bench_warehouse
                 ).add_argument("--sql-steps", type=int, nargs="+", help="warehouse sizes for the SQL measure")
    bench_parser("rollout", "explore stage vs plain robosuite loops, steps/s",
                 "a few short episodes (seconds, for a smoke check)", cmd_bench_rollout)
    bench_parser("train", "train stage samples/s vs in-memory batches; policy latency",
                 "a few steps, default case only (seconds, a smoke check)", cmd_bench_train
                 ).add_argument("--cases", metavar="A,B", help="run only these cases (stage always runs): "
                                "stage, memory, precision (fp32 vs bf16, CPU), workers0, resnet18, vit, minilm, cuda, act")

    sql = commands.add_parser("sql", help="read-only SQL over the warehouse (tasks, episodes, steps, triplets, ...)")
    sql.add_argument("query")
    sql.add_argument("--format", choices=("table", "csv", "json"), default="table")
    sql.add_argument("--workspace", default=_default_workspace())
    sql.add_argument("--as-of-iteration", type=int, metavar="K", help="see the warehouse as it was after iteration K")
    sql.set_defaults(handler=cmd_sql)

    export = commands.add_parser("export", help="write a warehouse selection in another project's format")
    export_commands = export.add_subparsers(dest="export_command", required=True)
    lerobot = export_commands.add_parser("lerobot", help="a LeRobotDataset v3.0 (Parquet + MP4), kept episodes")
    lerobot.add_argument("out_dir", type=Path, help="a new or empty folder")
    lerobot.add_argument("--where", help="SQL over the steps columns; whole episodes with a matching step go out")
    lerobot.add_argument("--include-rejected", action="store_true", help="also episodes the filter rejected")
    lerobot.add_argument("--fps", type=int, default=CONTROL_FPS, help="control rate of the episodes (robosuite: 20)")
    lerobot.add_argument("--repo-id", default="sim2act/export")
    lerobot.add_argument("--workspace", default=_default_workspace())
    lerobot.set_defaults(handler=cmd_export_lerobot)

    replay = commands.add_parser("replay", help="re-render a stored episode from its MuJoCo states into an MP4")
    replay.add_argument("episode_id")
    replay.add_argument("--camera", help="default: the episode's own (agentview, frontview, birdview, sideview)")
    replay.add_argument("--size", type=int, help="image side in pixels; default: the episode's own")
    replay.add_argument("--out", type=Path, help="default: ./<episode_id>_<camera>_<size>px.mp4")
    replay.add_argument("--fps", type=int, default=None, help=f"frames per second (one frame per step; default {CONTROL_FPS})")
    replay.add_argument("--workspace", default=_default_workspace())
    replay.set_defaults(handler=cmd_replay)

    warehouse = commands.add_parser("warehouse", help="warehouse upkeep")
    warehouse_commands = warehouse.add_subparsers(dest="warehouse_command", required=True)
    verify = warehouse_commands.add_parser("verify", help="check every registered shard, quarantine bad ones")
    verify.add_argument("--full", action="store_true", help="also compare each file's sha256 with the catalog's")
    verify.add_argument("--workspace", default=_default_workspace())
    verify.set_defaults(handler=cmd_warehouse_verify)
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
        from dashboards.panels import PanelError
        from flows.run_lock import WorkspaceBusy
        from flows.service import ServiceError
        from stages.replay import ReplayError
        from warehouse.catalog import CatalogMissing, CatalogVersionError
        from warehouse.export_lerobot import ExportError
        from warehouse.shard_writer import DiskFull
        from warehouse.sql import ReadOnlyViolation
        from warehouse.training_reader import SelectionError

        if isinstance(exc, (CatalogMissing, CatalogVersionError, ReadOnlyViolation, ExportError, ReplayError,
                            SelectionError, ServiceError, PanelError, WorkspaceBusy, DiskFull)):
            print(f"sim2act: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
