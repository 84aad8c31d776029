"""The local stack: `sim2act up`, `down`, `status`, and the dashboard alone. up's flags are made
from ServiceConfig's fields, so a setting added there is a flag here, with its default and help."""

from __future__ import annotations

import argparse

from pydantic import ValidationError

from flows.cli.common import (Commands, add_campaign_options, add_workspace_option, campaign_config, check_tracking_uris,
                              configure_environment, open_catalog, port_number)
from schemas.config import ConfigError, describe_validation_error
from schemas.service import HOST, ServiceConfig
from schemas.workspace import Workspace


def add_service_options(command: argparse.ArgumentParser) -> None:
    """One flag per ServiceConfig field (--prefect-port, ..., --timezone); unset flags keep the model's defaults."""
    for name, field in ServiceConfig.model_fields.items():
        kind = int if field.annotation is int else str
        help = f"{field.description} (default {field.default!r})" if field.description else f"default {field.default!r}"
        command.add_argument(f"--{name.replace('_', '-')}", type=kind, help=help)


def service_config(args: argparse.Namespace) -> ServiceConfig:
    try:
        return ServiceConfig(**{f: getattr(args, f) for f in ServiceConfig.model_fields if getattr(args, f) is not None})
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc)) from None


def print_status(rows: list[dict]) -> None:
    for row in rows:
        print(f"{row['name']:<12} {row['state']:<10} {row['url']:<36} pid {row['pid']:<8} log {row['log']}")


def cmd_up(args: argparse.Namespace) -> int:
    config = campaign_config(args)  # the deployments' default campaign
    service = service_config(args)
    from flows.service import up

    workspace, catalog = open_catalog(args)
    configure_environment(workspace)
    check_tracking_uris()  # before the MLflow server logs a refused one whole
    catalog.initialise()  # the dashboard reads it from the first minute
    print(f"sim2act: starting the stack over {workspace.root} (campaign {config.name!r}, nightly "
          f"{service.nightly_cron} {service.timezone})", flush=True)
    rows = up(workspace, service, config, on_ready=lambda line: print(f"  ready: {line}", flush=True))
    print_status(rows)
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
    print_status(rows)
    return 0 if all(row["state"] == "up" for row in rows) else 1


def cmd_dashboard(args: argparse.Namespace) -> int:
    from dashboards.server import listening_socket, serve

    workspace, catalog = open_catalog(args)  # a warehouse of another layout: one line, before serving
    if not catalog.path.exists():
        print(f"sim2act: no warehouse in {workspace.root} yet: the dashboard shows it once a campaign runs there",
              flush=True)
    sock = listening_socket(args.host, args.port)  # a port in use: one line, before saying where it serves
    print(f"sim2act: dashboard over {workspace.root} at http://{args.host}:{args.port}", flush=True)
    serve(workspace, sock, args.host)
    return 0


def register(commands: Commands) -> None:
    stack_up = add_campaign_options(commands.add_parser(
        "up", help="start the local stack: Prefect and MLflow servers, dashboard, deployments "
                   "(their default campaign: --preset/--config/--set)"))
    add_service_options(stack_up)
    stack_up.set_defaults(handler=cmd_up)
    for name, help, handler in (("down", "stop the local stack", cmd_down),
                                ("status", "the local stack's processes, health and URLs", cmd_status)):
        add_workspace_option(commands.add_parser(name, help=help)).set_defaults(handler=handler)
    dashboard = add_workspace_option(commands.add_parser(
        "dashboard", help="serve the warehouse dashboard alone (sim2act up starts it too)"))
    dashboard.add_argument("--host", default=HOST)
    dashboard.add_argument("--port", type=port_number, default=ServiceConfig.model_fields["dashboard_port"].default)
    dashboard.set_defaults(handler=cmd_dashboard)
