"""Every path Sim2Act reads or writes, from one root. Nothing else builds paths."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Workspace:
    root: Path

    @classmethod
    def at(cls, root: str | Path) -> Workspace:
        return cls(Path(root).expanduser().resolve())

    @property
    def warehouse(self) -> Path:
        return self.root / "warehouse"

    @property
    def catalog(self) -> Path:
        return self.warehouse / "catalog.duckdb"

    @property
    def shards(self) -> Path:
        return self.warehouse / "shards"

    def shard_path(self, table: str, iteration: int, key: str) -> Path:
        """Hive-style folders by iteration: shards/<table>/iteration=<k>/<key>.parquet."""
        return self.shards / table / f"iteration={iteration}" / f"{key}.parquet"

    @property
    def models(self) -> Path:
        return self.root / "models"

    def checkpoint(self, model_key: str) -> Path:
        return self.models / model_key / "policy.pt"

    def registry_download(self, model_key: str) -> Path:
        """Where a registry version of model `model_key` is downloaded to (by its key: a registry made again
        numbers its versions from 1 again)."""
        return self.models / "registry" / model_key

    def train_state(self, model_key: str, member: int = 0) -> Path:
        """An unfinished training's last resumable checkpoint of an ensemble member (removed once the
        model is registered)."""
        return self.models / model_key / f"train-state-{member}.pt"

    @property
    def precision_choices(self) -> Path:
        """bf16 or fp32 as measured on this host per model and batch (policies/precision.py), so a resumed
        training and the next iteration's compute as the first did."""
        return self.models / "precision.json"

    def expert_check(self, key: str) -> Path:
        """One task's scripted-expert row measured under a campaign's own randomisation (envs/expert_check.py)."""
        return self.root / "experts" / f"{key}.json"

    @property
    def media(self) -> Path:
        return self.root / "media"

    @property
    def mlflow(self) -> Path:
        return self.root / "mlflow"

    @property
    def tracking_db(self) -> Path:
        return self.mlflow / "mlflow.db"

    @property
    def tracking_uri(self) -> str:
        return f"sqlite:///{self.tracking_db}"

    @property
    def artifact_root(self) -> Path:
        return self.mlflow / "artifacts"

    @property
    def prefect_home(self) -> Path:
        return self.root / "prefect"

    @property
    def run_lock(self) -> Path:
        """Held by the campaign running on this workspace (flows/run_lock.py)."""
        return self.root / "run.lock"

    @property
    def shard_files_lock(self) -> Path:
        """Shared by the commands reading the shard files at length, exclusive to `warehouse compact`
        (flows/run_lock.py)."""
        return self.root / "shard-files.lock"

    @property
    def service(self) -> Path:
        """The local stack's record (`sim2act up`): which processes run, on which ports, their logs."""
        return self.root / "service"

    @property
    def service_state(self) -> Path:
        return self.service / "state.json"

    @property
    def deployment_config(self) -> Path:
        """The campaign config the served deployments take as their default parameters."""
        return self.service / "campaign.json"

    def service_log(self, name: str) -> Path:
        return self.service / f"{name}.log"

    def create(self) -> Workspace:
        for folder in (self.shards, self.models, self.media, self.artifact_root, self.prefect_home):
            folder.mkdir(parents=True, exist_ok=True)
        return self


def write_text_atomically(path: Path, text: str) -> None:
    """A report or record, whole or not at all: written beside, then moved into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    except BaseException:  # a full disk, a folder at `path`: no stray temporary beside it
        tmp.unlink(missing_ok=True)
        raise


def read_json_written(path: Path) -> tuple[object, float] | None:
    """A JSON record and when it was written (epoch seconds), read from one open file (so a writer
    swapping it meanwhile cannot pair one version's words with another's time); None if absent."""
    try:
        with path.open() as file:
            return json.load(file), os.fstat(file.fileno()).st_mtime
    except FileNotFoundError:
        return None
