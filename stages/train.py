"""train: the VLA model on the iteration's selection, lambda*InfoNCE + (1-lambda)*BC, AdamW with
warm-up and cosine decay, gradient clipping, seeded. One unit = one training run."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel
from torch.utils.data import DataLoader

from envs.observation import ACTION_DIM, PROPRIO_DIM
from policies.language import ENCODER_DIMS
from policies.model import ModelDims, VLAModel, vla_loss
from policies.policy import Normaliser, save_checkpoint
from schemas.config import CampaignConfig, ConfigError
from schemas.keys import derive_seed, unit_key
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages.index import IndexResult
from warehouse.catalog import Catalog
from warehouse.training_reader import Sample, StepStream

STAGE, VERSION = "train", 1
WARMUP_FRACTION = 0.05
log = logging.getLogger("sim2act.stages.train")


class TrainResult(BaseModel):
    model_key: str
    checkpoint: str
    dataset_digest: str
    samples: int
    dataset_shards: list[str]  # relative to the warehouse
    history: list[dict[str, float]]  # one entry per epoch (empty when skipped)
    skipped: bool


def check_trainable(tasks: list[TaskRecord]) -> None:
    """The model has the continuous (Gaussian) head only; discrete actions wait for the softmax head."""
    discrete = sorted({t.spec for t in tasks if t.family == "navigation"})
    if discrete:
        raise ConfigError(
            f"tasks.specs: {discrete[0]} is a navigation task with discrete actions, which campaigns cannot "
            "train on yet (the softmax head is to come); explore its tasks with `sim2act tasks experts`"
        )


def train_unit_key(config: CampaignConfig, dataset: IndexResult, tasks_key: str) -> str:
    reads = {"train": config.train.model_dump(exclude={"threads"}), "seed": config.seed, "image": config.render.image_size}
    return unit_key(STAGE, VERSION, reads, [dataset.dataset_digest, tasks_key])


def _collate(samples: list[Sample]) -> dict[str, np.ndarray]:
    return {
        "image": np.stack([s.image for s in samples]),
        "language": np.stack([s.language for s in samples]),
        "proprio": np.stack([s.proprio for s in samples]),
        "action": np.stack([s.action for s in samples]),
    }


def _normalisers(catalog: Catalog, dataset: IndexResult) -> tuple[Normaliser, Normaliser]:
    """Action and proprio statistics over exactly the kept steps of the selection."""
    table = dataset.selection.kept_steps(catalog, ["action", "proprio"])
    actions = np.asarray(table["action"].to_pylist(), dtype=np.float32)
    proprio = np.asarray(table["proprio"].to_pylist(), dtype=np.float32)
    return Normaliser.fit(actions), Normaliser.fit(proprio)


def run_train(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    dataset: IndexResult,
    tasks_key: str,
    embeddings: dict[str, np.ndarray],
) -> TrainResult:
    catalog = Catalog(workspace.catalog)
    key = train_unit_key(config, dataset, tasks_key)
    checkpoint = workspace.checkpoint(key)
    existing = catalog.query("SELECT train_samples, dataset_shards FROM models WHERE model_key = ?", [key])
    if existing:
        log.info("train it%d: model %s already trained on dataset %s, skipped", iteration, key, dataset.dataset_digest[:12])
        return TrainResult(model_key=key, checkpoint=str(checkpoint), dataset_digest=dataset.dataset_digest,
                           samples=existing[0][0], dataset_shards=existing[0][1], history=[], skipped=True)

    cfg = config.train
    started = time.monotonic()
    torch.manual_seed(derive_seed(config.name, config.seed, "train", key))
    torch.set_num_threads(cfg.threads)
    action_norm, proprio_norm = _normalisers(catalog, dataset)
    rows = dataset.selection.rows(catalog)
    shards_read = sorted({Path(r.path).relative_to(catalog.warehouse).as_posix() for r in rows})
    stream = StepStream(
        rows, embeddings, cfg.shuffle_buffer, derive_seed(config.seed, key, "shuffle"),
    )
    dims = ModelDims(config.render.image_size, PROPRIO_DIM, ACTION_DIM, ENCODER_DIMS[cfg.model.language_encoder])
    model = VLAModel(cfg.model, dims)
    optimiser = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    total_steps = cfg.epochs * math.ceil(dataset.triplets / cfg.batch_size)
    warmup = max(1, int(WARMUP_FRACTION * total_steps))
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser,
        lambda s: min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(1.0, s / total_steps))),
    )
    loader = DataLoader(stream, batch_size=cfg.batch_size, collate_fn=_collate, num_workers=0)
    log.info(
        "train it%d: %d triplets, %d epochs x %d steps, %.2fM parameters, dataset %s",
        iteration, dataset.triplets, cfg.epochs, total_steps // cfg.epochs,
        sum(p.numel() for p in model.parameters()) / 1e6, dataset.dataset_digest[:12],
    )
    history = []
    for epoch in range(cfg.epochs):
        stream.set_epoch(epoch)
        epoch_started, totals, seen = time.monotonic(), {}, 0
        model.train()
        for batch in loader:
            losses = vla_loss(
                model,
                torch.from_numpy(batch["image"]).permute(0, 3, 1, 2).float() / 255.0,
                torch.from_numpy(batch["language"]),
                torch.from_numpy(proprio_norm.encode(batch["proprio"])),
                torch.from_numpy(action_norm.encode(batch["action"])),
                cfg.contrastive_weight,
                cfg.temperature,
            )
            optimiser.zero_grad(set_to_none=True)
            losses["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimiser.step()
            schedule.step()
            size = len(batch["action"])
            seen += size
            for name, value in losses.items():
                totals[name] = totals.get(name, 0.0) + value.item() * size
        elapsed = time.monotonic() - epoch_started
        record = {name: total / max(seen, 1) for name, total in totals.items()}
        record.update(samples_per_s=seen / elapsed, lr=schedule.get_last_lr()[0])
        history.append(record)
        log.info(
            "train it%d: epoch %d/%d loss %.3f (infonce %.3f, bc %.3f, action mse %.3f), %.0f samples/s",
            iteration, epoch + 1, cfg.epochs, record["loss"], record["infonce"], record["bc"],
            record["action_mse"], record["samples_per_s"],
        )
    save_checkpoint(checkpoint, model, action_norm, proprio_norm, cfg.model.language_encoder)
    catalog.register_unit(
        unit_key=key, stage=STAGE, campaign=config.name, iteration=iteration,
        summary={"final_loss": history[-1]["loss"], "epochs": cfg.epochs}, wall_s=time.monotonic() - started,
        rows={"models": [{
            "model_key": key, "campaign": config.name, "iteration": iteration,
            "checkpoint_path": str(checkpoint.relative_to(workspace.root)), "dataset_digest": dataset.dataset_digest,
            "dataset_shards": shards_read, "train_samples": dataset.triplets, "final_loss": history[-1]["loss"], "unit_key": key,
        }]},
    )
    return TrainResult(model_key=key, checkpoint=str(checkpoint), dataset_digest=dataset.dataset_digest,
                       samples=dataset.triplets, dataset_shards=shards_read, history=history, skipped=False)
