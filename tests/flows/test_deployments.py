"""The deployments' process drops nightly runs Prefect scheduled for another campaign config, and all but the
latest of the nights missed (the stack down over a reboot: they would run one after another, each with its
day's parameters)."""

from __future__ import annotations

import datetime

from prefect import get_client
from prefect.settings import PREFECT_API_URL, temporary_settings
from prefect.states import Scheduled

from flows.deployments import NIGHTLY, build_deployments, drop_stale_nightly_runs
from schemas.config import load_config
from schemas.service import ServiceConfig
from schemas.workspace import Workspace
from tests.flows.test_service import cron_hours_from_now

# the nightly schedule 12 h away: runs Prefect schedules by itself stay out of the counts below
SERVICE = ServiceConfig(nightly_cron=cron_hours_from_now(12, 0))


def test_scheduled_nightly_runs_of_another_config_are_dropped_and_the_current_ones_kept(prefect_api, tmp_path):
    workspace = Workspace.at(tmp_path / "ws")
    old, new = load_config("smoke"), load_config("smoke", overrides={"iterations": 5})
    with temporary_settings({PREFECT_API_URL: prefect_api}):
        nightly = next(d for d in build_deployments(old, workspace, SERVICE) if d.name == NIGHTLY)
        deployment_id = nightly.apply()
        past = Scheduled(scheduled_time=datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(days=1))
        with get_client(sync_client=True) as client:
            made = {which: client.create_flow_run_from_deployment(deployment_id, parameters={
                "config": config.model_dump(mode="json"), "workspace": str(workspace.root), "continue_campaign": True},
                state=past.model_copy()).id for which, config in (("old", old), ("new", new))}
            assert drop_stale_nightly_runs(new, workspace) >= 1
            left = {run.id for run in client.read_flow_runs()}
        assert made["old"] not in left and made["new"] in left
        assert drop_stale_nightly_runs(new, workspace) == 0


def test_of_the_nights_missed_with_this_config_only_the_latest_runs(prefect_api, tmp_path):
    workspace = Workspace.at(tmp_path / "ws")
    config = load_config("smoke")
    now = datetime.datetime.now(datetime.timezone.utc)
    with temporary_settings({PREFECT_API_URL: prefect_api}):
        nightly = next(d for d in build_deployments(config, workspace, SERVICE) if d.name == NIGHTLY)
        deployment_id = nightly.apply()
        parameters = {"config": config.model_dump(mode="json"), "workspace": str(workspace.root), "continue_campaign": True}
        with get_client(sync_client=True) as client:
            made = {days: client.create_flow_run_from_deployment(deployment_id, parameters=parameters, state=Scheduled(
                scheduled_time=now + datetime.timedelta(days=days))).id for days in (-3, -2, -1, 1)}
            assert drop_stale_nightly_runs(config, workspace) >= 2  # (and another test's runs, for another workspace)
            left = {run.id for run in client.read_flow_runs()}
        assert {days for days, run_id in made.items() if run_id in left} == {-1, 1}  # last night's, and tomorrow's
        assert drop_stale_nightly_runs(config, workspace) == 0
