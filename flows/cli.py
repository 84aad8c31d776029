"""`sim2act`: a thin front over the flows and the warehouse.

Configs are validated before anything is imported or written: bad input costs one line.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from schemas.config import PRESETS, ConfigError, load_config
from schemas.workspace import Workspace


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

    generate_tasks(config.tasks, config.seed)  # unknown task ids are refused here, before any work
    workspace = Workspace.at(args.workspace)
    configure_environment(workspace)
    workspace.create()
    print(
        f"sim2act: campaign {config.name!r}, {config.iterations} iteration(s), workspace {workspace.root}",
        flush=True,
    )
    from flows.bootstrap import bootstrap

    bootstrap(config=config, workspace=str(workspace.root))
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

    sql = commands.add_parser("sql", help="read-only SQL over the warehouse (tasks, episodes, steps, triplets, ...)")
    sql.add_argument("query")
    sql.add_argument("--format", choices=("table", "csv", "json"), default="table")
    sql.add_argument("--workspace", default=_default_workspace())
    sql.set_defaults(handler=cmd_sql)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except ConfigError as exc:
        print(f"sim2act: config error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sim2act: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except Exception as exc:  # a known failure mode gets one line, not a traceback
        from warehouse.catalog import CatalogMissing
        from warehouse.sql import ReadOnlyViolation

        if isinstance(exc, (CatalogMissing, ReadOnlyViolation)):
            print(f"sim2act: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
