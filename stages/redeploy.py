"""redeploy: register the trained model in MLflow's model registry, point the alias at it, and
name the explorer the next iteration uses."""

from __future__ import annotations

import logging
import time

from mlflow import MlflowClient
from pydantic import BaseModel

from schemas.config import CampaignConfig
from schemas.keys import unit_key
from schemas.workspace import Workspace
from stages.explore import PolicyExplorer
from warehouse.catalog import Catalog

STAGE, VERSION = "redeploy", 1
MODEL_KEY_TAG = "sim2act.model_key"
log = logging.getLogger("sim2act.stages.redeploy")


class RedeployResult(BaseModel):
    registered_model: str
    version: int
    alias: str
    champion: PolicyExplorer
    skipped: bool


def _registered_version(client: MlflowClient, name: str, model_key: str) -> int | None:
    """A version already made for this model (a run killed after registering, before the catalog row)."""
    for version in client.search_model_versions(f"name = '{name}'"):
        if version.tags.get(MODEL_KEY_TAG) == model_key:
            return int(version.version)
    return None


def champion_explorer(workspace: Workspace, client: MlflowClient, name: str, version: int) -> PolicyExplorer:
    """The registry's model version as an explorer: its checkpoint fetched from the artifact store."""
    model_version = client.get_model_version(name, str(version))
    target = workspace.models / "registry" / name / str(version)
    if not (target / "artifacts" / "policy.pt").exists():
        import mlflow.artifacts

        target.mkdir(parents=True, exist_ok=True)
        mlflow.artifacts.download_artifacts(f"models:/{name}/{version}", dst_path=str(target))
    return PolicyExplorer(
        name=f"policy:{name}/{version}",
        model_key=model_version.tags[MODEL_KEY_TAG],
        checkpoint=str(target / "artifacts" / "policy.pt"),
    )


def run_redeploy(
    workspace: Workspace, config: CampaignConfig, iteration: int, model_key: str, checkpoint: str, mlflow_run_id: str
) -> RedeployResult:
    import mlflow

    from policies.mlflow_model import MODEL_CODE

    catalog = Catalog(workspace.catalog)
    name, alias = config.registered_model_name, config.redeploy.alias
    key = unit_key(STAGE, VERSION, config.redeploy, [model_key])
    client = MlflowClient(tracking_uri=workspace.tracking_uri)
    existing = catalog.query("SELECT version, champion_version FROM deployments WHERE unit_key = ?", [key])
    if existing:
        version, champion = existing[0]
        log.info("redeploy it%d: %s version %d already registered, %s -> v%d, skipped", iteration, name, version, alias, champion)
        return RedeployResult(registered_model=name, version=version, alias=alias, skipped=True,
                              champion=champion_explorer(workspace, client, name, champion))

    started = time.monotonic()
    version = _registered_version(client, name, model_key)
    if version is None:
        mlflow.set_tracking_uri(workspace.tracking_uri)
        with mlflow.start_run(run_id=mlflow_run_id):
            info = mlflow.pyfunc.log_model(
                name="policy",
                python_model=MODEL_CODE,
                artifacts={"checkpoint": checkpoint},
                pip_requirements=["sim2act", "torch==2.13.0"],
            )
        version = int(mlflow.register_model(info.model_uri, name, tags={MODEL_KEY_TAG: model_key}).version)
    # Every new model becomes the champion for now; gating on held-out evaluation is issue 7's.
    client.set_registered_model_alias(name, alias, str(version))
    catalog.register_unit(
        unit_key=key, stage=STAGE, campaign=config.name, iteration=iteration,
        summary={"registered_model": name, "version": version, "alias": alias}, wall_s=time.monotonic() - started,
        rows={"deployments": [{
            "unit_key": key, "model_key": model_key, "campaign": config.name, "iteration": iteration,
            "registered_model": name, "version": version, "alias": alias, "champion_version": version,
            "champion_model_key": model_key, "mlflow_run_id": mlflow_run_id,
        }]},
    )
    log.info("redeploy it%d: registered %s version %d, alias %s -> v%d", iteration, name, version, alias, version)
    return RedeployResult(registered_model=name, version=version, alias=alias, skipped=False,
                          champion=champion_explorer(workspace, client, name, version))
