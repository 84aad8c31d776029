"""redeploy: register the trained model in MLflow's model registry (with its signature and an
input example from the warehouse), move the alias to it when the evaluation decided so, and name
the explorer the next iteration uses: the champion, new or kept."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from mlflow import MlflowClient

from schemas.config import CampaignConfig
from schemas.keys import unit_key
from schemas.settings import REGISTRY_URI_ENV, TRACKING_URI_ENV, registry_uri, tracking_uri
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from stages.evaluate import Promotion
from stages.explore import PolicyExplorer
from warehouse.catalog import Catalog
from warehouse.store import FOLDER

STAGE, VERSION = "redeploy", 2
MODEL_KEY_TAG = "sim2act.model_key"
log = logging.getLogger("sim2act.stages.redeploy")


class RedeployResult(StageResult):
    registered_model: str
    version: int
    alias: str
    champion: PolicyExplorer
    skipped: bool

    def did_work(self) -> bool:
        return not self.skipped


def finished_iterations(workspace: Workspace, campaign: str) -> int:
    """How many of a campaign's iterations ran to the end (redeploy is the last stage)."""
    [(count,)] = Catalog(workspace.catalog).query(
        "SELECT coalesce(max(iteration) + 1, 0) FROM deployments WHERE campaign = ?", [campaign]
    )
    return count


def continued(config: CampaignConfig, workspace: Workspace) -> CampaignConfig:
    """The campaign `--continue` runs: one iteration past its latest finished one, and at least its
    configured iterations (the nightly deployment and `sim2act run --continue` share this)."""
    iterations = max(config.iterations, finished_iterations(workspace, config.name) + 1)
    return config.model_copy(update={"iterations": iterations})


def _registered_version(client: MlflowClient, name: str, model_key: str) -> int | None:
    """A version already made for this model (a run killed after registering, before the catalog row)."""
    for version in client.search_model_versions(f"name = '{name}'"):
        if version.tags.get(MODEL_KEY_TAG) == model_key:
            return int(version.version)
    return None


def champion_explorer(workspace: Workspace, client: MlflowClient, name: str, version: int) -> PolicyExplorer:
    """The registry's model version as an explorer: its checkpoint fetched from the artifact store."""
    model_version = client.get_model_version(name, str(version))
    target = workspace.registry_download(model_version.tags[MODEL_KEY_TAG])
    if not (target / "artifacts" / "policy.pt").exists():
        import shutil
        import tempfile

        import mlflow.artifacts

        target.parent.mkdir(parents=True, exist_ok=True)
        # downloaded aside and renamed into place: a kill mid-download leaves no half a checkpoint to be reused
        partial = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}-"))
        try:
            # this workspace's registry, not MLflow's default of ./mlflow.db: `models:/` URIs resolve through the
            # fluent global whatever download_artifacts is told (MLflow 3.17), so set it for the call
            with _fluent_tracking(workspace):
                mlflow.artifacts.download_artifacts(f"models:/{name}/{version}", dst_path=str(partial))
            shutil.rmtree(target, ignore_errors=True)  # an older layout's leftovers, or a racing download's
            partial.rename(target)
        finally:
            shutil.rmtree(partial, ignore_errors=True)
    checkpoint, model_key = str(target / "artifacts" / "policy.pt"), model_version.tags[MODEL_KEY_TAG]
    worker_checkpoint = None
    store = Catalog(workspace.catalog).store
    if store.url != FOLDER:  # rollout workers elsewhere share no folder with this one: they read the store
        import hashlib

        import pyarrow as pa

        data = Path(checkpoint).read_bytes()
        rel = f"models/{model_key}/policy.pt"  # the model's key: a registry that numbers versions anew cannot collide
        store.put_new(rel, pa.py_buffer(data), hashlib.sha256(data).hexdigest())
        worker_checkpoint = store.location(rel)
    return PolicyExplorer(name=f"policy:{name}/{version}", model_key=model_key, checkpoint=checkpoint,
                          worker_checkpoint=worker_checkpoint)


def input_example(catalog: Catalog, campaign: str):
    """One stored step of the campaign, as the MLflow model takes it."""
    import pandas as pd

    [(image, depth, proprio, instruction, family)] = catalog.query(
        "SELECT s.image, s.depth, s.proprio, s.instruction, t.family FROM steps s "
        "JOIN task_families t ON t.campaign = s.campaign AND t.task_id = s.task_id "
        "WHERE s.campaign = ? ORDER BY s.episode_id, s.step LIMIT 1", [campaign],
    )
    depths = {} if depth is None else {"depth": [depth]}  # a column only where the campaign records depth
    return pd.DataFrame({"image": [image], **depths, "proprio": [[float(x) for x in proprio]],
                         "instruction": [instruction], "family": [family]})


def _register(workspace: Workspace, catalog: Catalog, config: CampaignConfig, model_key: str, checkpoint: str,
              mlflow_run_id: str) -> int:
    import mlflow
    from mlflow.models import infer_signature
    from mlflow.types.schema import ColSpec, Schema

    from policies.mlflow_model import MODEL_CODE, predict_frame
    from policies.policy import Policy

    example = input_example(catalog, config.name)
    signature = infer_signature(example, predict_frame(Policy.load(Path(checkpoint)), example))
    # optional: rows of one episode act through its earlier chunks, as evaluation acts (policies/mlflow_model.py)
    signature.inputs = Schema([*signature.inputs.inputs, ColSpec("string", "episode_id", required=False)])
    with _fluent_tracking(workspace):
        with mlflow.start_run(run_id=mlflow_run_id):
            info = mlflow.pyfunc.log_model(
                name="policy", python_model=MODEL_CODE, artifacts={"checkpoint": checkpoint},
                signature=signature, input_example=example, pip_requirements=["sim2act", "torch==2.13.0"],
            )
            version = int(mlflow.register_model(info.model_uri, config.registered_model_name,
                                                tags={MODEL_KEY_TAG: model_key}).version)
        # the fluent run ended FINISHED as its block closed; the iteration goes on (evaluate.training_seeds'
        # trainings, for hours) and the flow ends its run when the iteration has finished
        mlflow.MlflowClient().update_run(mlflow_run_id, status="RUNNING")
    return version


@contextmanager
def _fluent_tracking(workspace: Workspace) -> Iterator[None]:
    """MLflow's fluent API (log_model, register_model) tracks one URI and registers at one URI per process,
    and writes them into MLFLOW_TRACKING_URI and MLFLOW_REGISTRY_URI, which this process's later work and
    every child it starts would then take for the user's settings (schemas.settings): another workspace's
    stores. Set for the call (`tracking_uri`, `registry_uri`), then put back as they were, variables included."""
    import mlflow

    with kept_tracking():
        mlflow.set_tracking_uri(tracking_uri(workspace))
        mlflow.set_registry_uri(registry_uri(workspace))
        yield


@contextmanager
def kept_tracking() -> Iterator[None]:
    """The process's MLflow tracking and registry settings (the fluent globals, MLFLOW_TRACKING_URI and
    MLFLOW_REGISTRY_URI) as they were before."""
    from mlflow.tracking._model_registry import utils as registry  # the fluent API's globals
    from mlflow.tracking._tracking_service import utils as tracking

    before = tracking._tracking_uri, registry._registry_uri
    before_env = {name: os.environ.get(name) for name in (TRACKING_URI_ENV, REGISTRY_URI_ENV)}
    try:
        yield
    finally:
        tracking._tracking_uri, registry._registry_uri = before
        for name, value in before_env.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def run_redeploy(
    workspace: Workspace, config: CampaignConfig, iteration: int, model_key: str, checkpoint: str,
    mlflow_run_id: str, promotion: Promotion,
) -> RedeployResult:
    """Unit of work: one trained model, keyed by the redeploy settings and its model key. Registers it
    in the MLflow registry (once per model key), moves the champion alias when `promotion` says so,
    and registers a `deployments` row."""
    catalog = Catalog(workspace.catalog)
    name, alias = config.registered_model_name, config.redeploy.alias
    key = unit_key(STAGE, VERSION, config.redeploy, [model_key])
    client = MlflowClient(tracking_uri=tracking_uri(workspace), registry_uri=registry_uri(workspace))
    existing = catalog.query("SELECT version, champion_version FROM deployments WHERE unit_key = ?", [key])
    if existing:
        version, champion = existing[0]
        log.info("redeploy it%d: %s version %d already registered, %s -> v%d, skipped", iteration, name, version, alias, champion)
        return RedeployResult(registered_model=name, version=version, alias=alias, skipped=True,
                              champion=champion_explorer(workspace, client, name, champion))

    def work() -> UnitOutput:
        version = _registered_version(client, name, model_key)
        if version is None:
            version = _register(workspace, catalog, config, model_key, checkpoint, mlflow_run_id)
        if promotion.promote:
            client.set_registered_model_alias(name, alias, str(version))
        champion = int(client.get_model_version_by_alias(name, alias).version)
        champion_key = client.get_model_version(name, str(champion)).tags[MODEL_KEY_TAG]
        return UnitOutput(
            {"registered_model": name, "version": version, "alias": alias, "champion_version": champion,
             "decision": promotion.reason},
            rows={"deployments": [{
                "unit_key": key, "model_key": model_key, "campaign": config.name, "iteration": iteration,
                "registered_model": name, "version": version, "alias": alias, "champion_version": champion,
                "champion_model_key": champion_key, "promoted": promotion.promote, "decision": promotion.reason,
                "mlflow_run_id": mlflow_run_id,
            }]},
            value=(version, champion),
        )

    started = time.monotonic()  # the deployments query above was the registration check: register without a second
    output = work()
    StageUnits(catalog, STAGE, config.name, iteration).register(key, output, time.monotonic() - started)
    version, champion = output.value
    log.info("redeploy it%d: registered %s version %d; %s -> v%d (%s)", iteration, name, version, alias, champion,
             promotion.reason)
    return RedeployResult(registered_model=name, version=version, alias=alias, skipped=False,
                          champion=champion_explorer(workspace, client, name, champion))
