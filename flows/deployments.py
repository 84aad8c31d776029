"""The bootstrap flow's two deployments, served from one process that `sim2act up` starts:

- `bootstrap/on-demand`: run from the UI's form or `prefect deployment run 'bootstrap/on-demand'`;
- `bootstrap/nightly`: on a cron schedule, one iteration past the campaign's latest finished one.

Both default to the campaign config `sim2act up` was given, in its workspace. Flow runs execute
one at a time (`limit=1`): a second run on the same workspace waits for the first.
"""

from __future__ import annotations

import argparse

from prefect import serve
from prefect.client.schemas.schedules import CronSchedule
from prefect.deployments.runner import EntrypointType, RunnerDeployment

from flows.bootstrap import bootstrap
from schemas.config import CampaignConfig
from schemas.service import ServiceConfig
from schemas.workspace import Workspace

ON_DEMAND, NIGHTLY = "on-demand", "nightly"


def build_deployments(config: CampaignConfig, workspace: Workspace, service: ServiceConfig) -> list[RunnerDeployment]:
    parameters = {"config": config.model_dump(mode="json"), "workspace": str(workspace.root)}
    # Module path, not file path: the runner imports `flows.bootstrap` whatever its working folder.
    common = {"entrypoint_type": EntrypointType.MODULE_PATH, "tags": ["sim2act", config.name]}
    return [
        bootstrap.to_deployment(
            name=ON_DEMAND, parameters=parameters, description="a bootstrap campaign, run when asked", **common,
        ),
        bootstrap.to_deployment(
            name=NIGHTLY, parameters={**parameters, "continue_campaign": True},
            schedules=[CronSchedule(cron=service.nightly_cron, timezone=service.timezone)],
            description=f"one more iteration of {config.name!r}, {service.nightly_cron} ({service.timezone})",
            **common,
        ),
    ]


def drop_stale_nightly_runs(config: CampaignConfig, workspace: Workspace) -> int:
    """Delete the nightly deployment's scheduled runs that are not tonight's step; -> how many. Prefect keeps
    the runs it scheduled while the stack was down (a reboot), each with the parameters of its day, and would
    run them one after another (serving anew replaces only the future ones): those made for another campaign
    config or workspace go, and of the nights missed with this config only the latest is kept (three nights
    down make one iteration, not three back to back: a night is a step, not a quota)."""
    from datetime import datetime, timezone

    from prefect import get_client
    from prefect.client.schemas.filters import (DeploymentFilter, DeploymentFilterId, FlowRunFilter, FlowRunFilterState,
                                                FlowRunFilterStateType)
    from prefect.client.schemas.objects import StateType
    from prefect.exceptions import ObjectNotFound
    from pydantic import ValidationError

    def stale(parameters: dict) -> bool:
        try:
            return (CampaignConfig.model_validate(parameters.get("config", {})) != config
                    or parameters.get("workspace") != str(workspace.root))
        except ValidationError:  # an older sim2act's config
            return True

    with get_client(sync_client=True) as client:
        try:
            deployment = client.read_deployment_by_name(f"{bootstrap.name}/{NIGHTLY}")
        except ObjectNotFound:
            return 0
        runs = client.read_flow_runs(
            deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment.id])),
            flow_run_filter=FlowRunFilter(state=FlowRunFilterState(type=FlowRunFilterStateType(any_=[StateType.SCHEDULED]))))
        dropped = [run for run in runs if stale(run.parameters)]
        now, gone = datetime.now(timezone.utc), {run.id for run in dropped}
        missed = sorted((run for run in runs if run.id not in gone and run.expected_start_time
                         and run.expected_start_time <= now), key=lambda run: run.expected_start_time)
        dropped += missed[:-1]
        for run in dropped:
            client.delete_flow_run(run.id)
    return len(dropped)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m flows.deployments", description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", required=True)
    parser.add_argument("--service", required=True, help="ServiceConfig as JSON")
    args = parser.parse_args(argv)
    workspace = Workspace.at(args.workspace)
    config = CampaignConfig.model_validate_json(workspace.deployment_config.read_text())
    service = ServiceConfig.model_validate_json(args.service)
    dropped = drop_stale_nightly_runs(config, workspace)
    if dropped:
        print(f"deployments: {dropped} scheduled nightly run(s) deleted (another campaign config, or nights "
              "missed before the latest)", flush=True)
    serve(*build_deployments(config, workspace, service), limit=1, print_starting_message=True)


if __name__ == "__main__":
    main()
