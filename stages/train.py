"""train: the VLA model on the iteration's selection, lambda*InfoNCE + (1-lambda)*BC plus the auxiliary
state loss (train.state_weight), AdamW with warm-up and cosine decay, gradient clipping, bf16
autocast where the device has bf16 units (policies/precision.py), seeded. One unit = one training run; it checkpoints every
`train.checkpoint_every` steps and a killed run resumes from the last checkpoint (weights,
optimiser, schedule, step and data position) to the same result."""

from __future__ import annotations

import hashlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from envs.observation import ACTION_DIM, NAVIGATION_ACTIONS, PROPRIO_DIM
from envs.pool import Progress
from policies.ema import WeightAverage
from policies.language import ENCODERS
from policies.model import ModelDims, VLAModel, join_views, pixels, split_views, vla_loss
from policies.policy import Normaliser, checkpoint_members, policy_state, save_atomically
from policies.precision import (PROBE_MIN_SAMPLES, autocast, cpu_bf16_may_pay, describe, image_layout, known_bf16,
                                measured_bf16, probe_key, to_device_layout, uses_bf16)
from schemas.config import MODEL_LEGACY_VALUES, CampaignConfig, TrainConfig
from schemas.keys import derive_seed, digest_of, key_fields, unit_key
from schemas.wordings import training_variants
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from stages.index import IndexResult
from warehouse.catalog import Catalog
from warehouse.training_reader import SelectionError, StepBatches, check_where, decode_rows, training_loader

STAGE, VERSION = "train", 2
WARMUP_FRACTION = 0.05
# How a run computes, not what it learns: left out of the unit key (a GPU re-run of a CPU-trained
# config finds the CPU model).
EXECUTION_FIELDS = {"threads", "checkpoint_every", "log_every", "device", "amp"}
# Fields added after the stage's version, each with the value that does what the stage did before it
# existed: at that value a field stays out of the key, so a model trained before it keeps its key.
LEGACY_VALUES = {"state_weight": 0.0, "init_from": None, "steps": None, "seed": 0, "ema": None, "language_augment": 0.0,
                 "proprio_dropout": 0.0, "model": MODEL_LEGACY_VALUES}
log = logging.getLogger("sim2act.stages.train")

# (step, metrics) every train.log_every steps; a sink with a `resumed_at(step)` method is also told the step a
# resumed training goes on from (the steps a kill cut after it come again: flows.tracking.StepLogger logs them once)
OnMetrics = Callable[[int, dict[str, float]], None]


class TrainResult(StageResult):
    model_key: str
    checkpoint: str
    dataset_digest: str  # of the training selection: the iteration's dataset narrowed by train.where
    samples: int
    dataset_shards: list[str]  # relative to the warehouse
    history: list[dict[str, float]]  # one entry per epoch (empty when skipped)
    resumed_at_step: int  # 0: trained from the start
    skipped: bool

    def did_work(self) -> bool:
        return not self.skipped


def train_unit_key(config: CampaignConfig, dataset: IndexResult, tasks_key: str) -> str:
    reads = {"train": key_fields(config.train, EXECUTION_FIELDS, LEGACY_VALUES), "seed": config.seed,
             "image": config.render.image_size, "depth": config.render.depth,
             **({"views": config.render.views} if config.render.views > 1 else {})}  # one view: keys as before
    return unit_key(STAGE, VERSION, reads, [dataset.dataset_digest, tasks_key])


def training_recipe(config: CampaignConfig) -> dict:
    """What a training computes, less its seed (the train key's settings): trainings of one dataset with
    equal recipes differ only in train.seed, and the results protocol pools exactly those
    (dashboards/protocol.py), so an ablation (train.targets, train.where, ...) never joins the recipe it ablates."""
    return key_fields(config.train, EXECUTION_FIELDS | {"seed"}, LEGACY_VALUES)


def training_epochs(cfg: TrainConfig, batches_per_epoch: int) -> int:
    """train.epochs, or the fewest epochs that give train.steps optimiser steps."""
    return cfg.epochs if cfg.steps is None else math.ceil(cfg.steps / batches_per_epoch)


def selection_digest(dataset: IndexResult, where: str | None) -> str:
    return dataset.dataset_digest if where is None else digest_of([dataset.dataset_digest, where])


def model_dims(config: CampaignConfig, state: Normaliser | None = None) -> ModelDims:
    """What the model reads and writes; `state`: the statistics of the simulator states an auxiliary
    head predicts (train.state_weight), None for none."""
    return ModelDims(config.render.image_size, PROPRIO_DIM, ACTION_DIM, len(NAVIGATION_ACTIONS),
                     ENCODERS[config.train.model.language_encoder].dim, channels=4 if config.render.depth else 3,
                     state_dim=0 if state is None else len(state.mean), views=config.render.views)


def split_actions(actions: list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    """Stored actions -> (continuous (n, ACTION_DIM), zero where discrete; discrete index (n,), -1
    where continuous). A discrete action is stored as [index] (envs.observation.DISCRETE_FAMILIES)."""
    continuous = np.zeros((len(actions), ACTION_DIM), np.float32)
    index = np.full(len(actions), -1, np.int64)
    for i, action in enumerate(actions):
        if len(action) == 1:
            index[i] = int(action[0])
        elif len(action) == ACTION_DIM:
            continuous[i] = action
        else:
            raise ValueError(f"a stored action of {len(action)} components: neither [index] nor {ACTION_DIM}")
    return continuous, index


def action_targets(actions: list[list[float]], expert_actions: list[list[float] | None],
                   targets: str) -> list[list[float]]:
    """What the policy learns to output per step (train.targets): the expert's noiseless action
    where the step recorded one, else the executed action; or always the executed action."""
    if targets == "executed":
        return actions
    return [action if label is None else label for action, label in zip(actions, expert_actions)]


def padded_states(qpos: list[list[float]], width: int) -> np.ndarray:
    """Stored simulator states, one length per scene -> (n, width), NaN past each state's end; a state
    longer than `width` (a fine-tuned model's head, sized by its source's data) is cut to it."""
    states = np.full((len(qpos), width), np.nan, np.float64)
    for i, state in enumerate(qpos):
        states[i, : min(len(state), width)] = state[:width]
    return states


def chunk_targets(action_chunks: list[list[list[float]]], expert_chunks: list[list[list[float] | None]],
                  targets: str, chunk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, the targets of its step and the next chunk-1 of its episode -> (continuous (n, chunk,
    ACTION_DIM), discrete index (n, chunk), mask (n, chunk): 1 where the episode has the step). Past
    the episode's end the last target repeats, masked out of the loss (it still feeds z_a's encoder)."""
    continuous = np.zeros((len(action_chunks), chunk, ACTION_DIM), np.float32)
    index = np.full((len(action_chunks), chunk), -1, np.int64)
    mask = np.zeros((len(action_chunks), chunk), np.float32)
    for row, (actions, labels) in enumerate(zip(action_chunks, expert_chunks)):
        values, indices = split_actions(action_targets(actions, labels, targets))
        n = len(values)
        continuous[row, :n], index[row, :n], mask[row, :n] = values, indices, 1.0
        continuous[row, n:], index[row, n:] = values[-1], indices[-1]
    return continuous, index, mask


class TrainingCollate:
    """Rows -> a ready batch, in the loader workers: frames (and depth maps) decoded, the action targets chosen,
    split by kind and normalised, proprio normalised, the frozen encoder's embeddings looked up; with a
    `state` normaliser, the simulator states normalised as `state` and which components each has as `state_mask`.
    For a chunked model (`chunk` > 1) the targets are (B, chunk, ...) with `action_mask` (chunk_targets)."""

    def __init__(self, action: Normaliser, proprio: Normaliser, embeddings: dict[str, np.ndarray] | None,
                 targets: str, state: Normaliser | None = None, chunk: int = 1,
                 rewordings: dict[str, list[str]] | None = None, augment: float = 0.0):
        self.action, self.proprio, self.embeddings, self.targets = action, proprio, embeddings, targets
        self.state, self.chunk = state, chunk
        self.rewordings, self.augment = rewordings or {}, augment  # train.language_augment

    def _reworded(self, rows: list[dict], instructions: list[str]) -> list[str]:
        """Each instruction, replaced by one of its rewordings with probability `augment`. The draws are
        seeded by the batch's own rows, so a resumed training draws the same."""
        seed = hashlib.blake2b(b"".join(r["image"] for r in rows), digest_size=8).digest()
        rng = np.random.default_rng(int.from_bytes(seed, "little"))
        said = []
        for text in instructions:
            options = self.rewordings.get(text)
            said.append(options[rng.integers(len(options))] if options and rng.random() < self.augment else text)
        return said

    def __call__(self, rows: list[dict]) -> dict:
        batch = decode_rows(rows)
        if self.augment > 0:
            batch["instruction"] = self._reworded(rows, batch["instruction"])
        if self.chunk > 1:
            batch.pop("action"), batch.pop("expert_action")
            continuous, index, batch["action_mask"] = chunk_targets(
                batch.pop("action_chunk"), batch.pop("expert_chunk"), self.targets, self.chunk)
            discrete = (index >= 0)[..., None]
        else:
            continuous, index = split_actions(action_targets(batch.pop("action"), batch.pop("expert_action"), self.targets))
            discrete = (index >= 0)[:, None]
        batch["action"] = np.where(discrete, 0.0, self.action.encode(continuous)).astype(np.float32)
        batch["action_index"] = index
        batch["proprio"] = self.proprio.encode(batch["proprio"])
        qpos = batch.pop("qpos")
        if self.state is not None:
            states = self.state.encode(padded_states(qpos, len(self.state.mean)))
            batch["state_mask"] = np.isfinite(states).astype(np.float32)
            batch["state"] = np.nan_to_num(states, nan=0.0)
        if self.embeddings is not None:
            batch["language"] = np.stack([self.embeddings[text] for text in batch["instruction"]])
        return batch


def normalisers(catalog: Catalog, dataset: IndexResult, cfg: TrainConfig,
                state_width: int | None = None) -> tuple[Normaliser, Normaliser, Normaliser | None]:
    """Statistics over exactly the training selection, in one read: of the action targets (continuous
    actions only), of proprio, and of the simulator states where an auxiliary state loss asks for
    them (per component as long as the longest state, or `state_width`: a fine-tuning's source's
    head; None at train.state_weight 0 or a width of 0)."""
    with_state = cfg.state_weight > 0 and state_width != 0
    columns = ["action", "expert_action", "proprio", *(["qpos"] if with_state else [])]
    table = dataset.selection.kept_steps(catalog, columns, cfg.where)
    continuous, index = split_actions(
        action_targets(table["action"].to_pylist(), table["expert_action"].to_pylist(), cfg.targets))
    proprio = np.asarray(table["proprio"].to_pylist(), dtype=np.float32)
    state = None
    if with_state:
        qpos = table["qpos"].to_pylist()
        state = Normaliser.fit(padded_states(qpos, state_width or max(map(len, qpos))), 0)
    return Normaliser.fit(continuous[index < 0], ACTION_DIM), Normaliser.fit(proprio, PROPRIO_DIM), state


REWORDINGS_PER_INSTRUCTION = 8


def reworded_instructions(embeddings: dict[str, np.ndarray], encoder: str,
                          encode_them: bool) -> tuple[dict[str, list[str]], dict[str, np.ndarray]]:
    """(instruction -> its rewordings for augmentation, the embeddings with theirs added where the
    frozen encoder's are read)."""
    rewordings = {text: training_variants(text, REWORDINGS_PER_INSTRUCTION) for text in embeddings}
    if not encode_them:
        return rewordings, embeddings
    from policies.language import encode

    new = sorted({v for options in rewordings.values() for v in options} - set(embeddings))
    return rewordings, {**embeddings, **dict(zip(new, encode(encoder, new)))} if new else embeddings


def initial_policy(catalog: Catalog, workspace: Workspace, model_key: str | None) -> dict | None:
    """The checkpoint a fine-tuning starts from (train.init_from), None from scratch."""
    if model_key is None:
        return None
    found = catalog.query("SELECT checkpoint_path FROM models WHERE model_key = ?", [model_key])
    if not found:
        raise SelectionError(f"train.init_from: no model {model_key!r} in the workspace {workspace.root}")
    return torch.load(workspace.root / found[0][0], map_location="cpu", weights_only=False)


def training_device(choice: str) -> torch.device:
    if choice == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("train.device: cuda asked for, and torch sees no GPU")
    return torch.device("cuda" if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()) else "cpu")


def warmup_cosine(total_steps: int) -> Callable[[int], float]:
    warmup = max(1, int(WARMUP_FRACTION * total_steps))
    return lambda s: min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(1.0, s / total_steps)))


def optimiser_for(model: VLAModel, cfg: TrainConfig) -> torch.optim.AdamW:
    """AdamW; a fine-tuned language encoder gets its own, smaller learning rate."""
    text = {id(p) for p in model.text.parameters()} if model.text is not None else set()
    groups = [{"params": [p for p in model.parameters() if id(p) not in text], "lr": cfg.lr}]
    if text:
        groups.append({"params": list(model.text.parameters()), "lr": cfg.language_lr})
    return torch.optim.AdamW(groups, weight_decay=cfg.weight_decay)


class _Means:
    """Sample-weighted means of the loss terms (each term over the samples it applies to). Sums
    stay on the training device, read only when reported: a read per step would make the CPU wait
    for the GPU at every step."""

    def __init__(self, state: dict | None = None):
        self.sums: dict[str, list] = {name: list(total) for name, total in (state or {}).items()}

    def add(self, terms: dict[str, torch.Tensor], counts: dict[str, int]) -> None:
        for name, value in terms.items():
            total = self.sums.setdefault(name, [0.0, 0])
            total[0] = total[0] + value * counts[name]
            total[1] += counts[name]

    def means(self) -> dict[str, float]:
        return {name: float(total) / count for name, (total, count) in self.sums.items() if count}

    def state(self) -> dict[str, list]:
        return {name: [float(total), count] for name, (total, count) in self.sums.items()}


def random_shift(image: torch.Tensor, pad: int, generator: torch.Generator | None = None,
                 views: int = 1) -> torch.Tensor:
    """Each frame moved by up to `pad` pixels each way, edges repeated (DrQ's augmentation: with few
    demonstrations it keeps a from-scratch encoder from memorising where things are on screen).
    The shifts are drawn on the CPU from `generator` (the training's own, which its checkpoints
    save: the DataLoader draws from torch's global one when it starts, so a resume would shift it).
    A frame of `views` square views side by side: each view moved on its own, none into another."""
    if pad == 0:
        return image
    if views > 1:
        return join_views(random_shift(split_views(image, views), pad, generator), views)
    b, c, h, w = image.shape
    shifts = torch.randint(0, 2 * pad + 1, (b, 2), generator=generator).to(image.device)
    padded = F.pad(image, (pad, pad, pad, pad), mode="replicate")
    rows = torch.arange(h, device=image.device)[None, :] + shifts[:, :1]
    cols = torch.arange(w, device=image.device)[None, :] + shifts[:, 1:]
    padded = padded.gather(2, rows[:, None, :, None].expand(b, c, h, w + 2 * pad))
    return padded.gather(3, cols[:, None, None, :].expand(b, c, h, w))


def drop_proprio(proprio: torch.Tensor, share: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """`proprio` (B, D), normalised, with about `share` of its rows set to zero, the dataset's mean
    (train.proprio_dropout). Drawn on the CPU from `generator`, the training's own like the shifts'; at
    share 0 nothing is drawn, so a training without it draws the shifts it drew before the field existed."""
    if share == 0:
        return proprio
    keep = torch.rand(len(proprio), generator=generator) >= share
    return proprio * keep.to(proprio.device, proprio.dtype).unsqueeze(-1)


def train_step(model, optimiser, schedule, batch: dict, cfg: TrainConfig, device: torch.device,
               shifts: torch.Generator | None = None, bf16: bool | None = None, channels_last: bool | None = None):
    """One optimiser step. `bf16`, `channels_last`: None for this device's choice (policies/precision.py);
    the benchmark sets them to compare."""
    depth = batch["depth"].to(device, non_blocking=True) if "depth" in batch else None
    image = random_shift(pixels(batch["image"].to(device, non_blocking=True), depth), cfg.augment_shift, shifts,
                         model.dims.views)
    image = image_layout(image, device, channels_last)
    bf16 = uses_bf16(device, cfg.amp) if bf16 is None else bf16
    cached = batch["language"].to(device, non_blocking=True) if "language" in batch else None
    state = (batch["state"].to(device, non_blocking=True), batch["state_mask"].to(device, non_blocking=True)) \
        if "state" in batch else None
    with autocast(device, bf16):
        losses = vla_loss(
            model, image, model.language_input(batch["instruction"], cached),
            drop_proprio(batch["proprio"].to(device, non_blocking=True), cfg.proprio_dropout, shifts),
            batch["action"].to(device, non_blocking=True),
            batch["action_index"].to(device, non_blocking=True), cfg.contrastive_weight, cfg.temperature,
            state, cfg.state_weight,
            batch["action_mask"].to(device, non_blocking=True) if "action_mask" in batch else None,
        )
    optimiser.zero_grad(set_to_none=True)
    losses.total.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    optimiser.step()
    schedule.step()
    return losses


@dataclass
class _Run:
    """What every member of a training shares: its data, device, schedule length and reporting."""

    workspace: Workspace
    config: CampaignConfig
    iteration: int
    key: str
    batches: StepBatches  # each member reads them in its own shuffled order
    device: torch.device
    state: Normaliser | None  # the statistics of the states an auxiliary head predicts
    start: list[dict] | None  # fine-tuning: the source model's members' weights
    on_metrics: OnMetrics | None
    progress: Progress
    bf16: bool  # autocast: the device's rule, or measured on this CPU (training_precision)


@dataclass
class _Member:
    model: VLAModel
    average: WeightAverage | None  # train.ema: the weights registered
    history: list[dict[str, float]]
    resumed_at_step: int
    earlier_wall_s: float  # spent on this member by the runs a kill interrupted: the compute it took counts them


def _train_member(run: _Run, member: int) -> _Member:
    """One model, seeded by its member index, from its last checkpoint if a kill interrupted it. A
    finished member keeps its final state until the training registers: a kill during the next
    member does not lose it."""
    cfg, key = run.config.train, run.key
    which = f"member {member + 1}/{cfg.ensemble}, " if cfg.ensemble > 1 else ""  # log lines of a single model as before
    state_path = run.workspace.train_state(key, member)
    torch.manual_seed(derive_seed(run.config.name, run.config.seed, "train", key, member))
    model = VLAModel(cfg.model, model_dims(run.config, run.state))
    if run.start is not None:
        try:
            model.load_state_dict(run.start[member % len(run.start)])
        except RuntimeError as exc:
            raise SelectionError(f"train.init_from: {cfg.init_from} is another architecture than train.model over "
                                 f"this dataset: {str(exc).splitlines()[0]}") from None
    model = to_device_layout(model, run.device)
    average = None if cfg.ema is None else WeightAverage(model, cfg.ema)
    optimiser = optimiser_for(model, cfg)
    batches = run.batches
    batches.seed = derive_seed(run.config.seed, key, "shuffle", member)
    total_steps = batches.epochs * batches.batches_per_epoch
    offset = member * total_steps  # of this member's steps in the training's (MLflow steps, progress)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, warmup_cosine(total_steps))
    step, history, epoch_means, earlier_wall_s = 0, [], _Means(), 0.0
    member_started = time.monotonic()
    shifts = torch.Generator().manual_seed(derive_seed(run.config.seed, key, "augment", member))
    if state_path.exists():
        state = torch.load(state_path, map_location="cpu", weights_only=False)
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        schedule.load_state_dict(state["schedule"])
        torch.set_rng_state(state["rng"])
        shifts.set_state(state["shifts"])
        step, history, epoch_means = state["step"], state["history"], _Means(state["epoch_means"])
        if average is not None:
            average = WeightAverage(model, cfg.ema, state["ema"])
        earlier_wall_s = state.get("wall_s", 0.0)  # states saved before it was recorded: unknown, not counted
        log.info("train it%d: resuming %s, %sat step %d/%d", run.iteration, key, which, step, total_steps)
        if (resumed_at := getattr(run.on_metrics, "resumed_at", None)) is not None:
            resumed_at(offset + step)
        if state.get("bf16", run.bf16) != run.bf16:  # precision is how a unit runs, not in its key: said, not refused
            log.warning("train it%d: %s ran its first %d steps in %s and goes on in %s (train.amp or this host's "
                        "bf16 choice differs): the training mixes precisions", run.iteration, key, step,
                        "bf16" if state["bf16"] else "fp32", "bf16" if run.bf16 else "fp32")
    resumed_at = step
    run.progress.resume_at(offset + step)
    log.info("train it%d: %s%.2fM parameters", run.iteration, which, sum(p.numel() for p in model.parameters()) / 1e6)
    if step == total_steps:
        return _Member(model, average, history, resumed_at, earlier_wall_s)

    def save_state() -> None:
        save_atomically(state_path, {
            "model": model.state_dict(), "optimiser": optimiser.state_dict(),
            "schedule": schedule.state_dict(), "rng": torch.get_rng_state(),
            "shifts": shifts.get_state(), "step": step,
            "history": history, "epoch_means": epoch_means.state(),
            "wall_s": earlier_wall_s + time.monotonic() - member_started, "bf16": run.bf16,
            **({} if average is None else {"ema": average.weights}),
        })

    batches.start_batch = step
    loader = training_loader(batches, cfg.loader_workers, pin_memory=run.device.type == "cuda")
    window, window_started, waited = _Means(), time.monotonic(), 0.0
    epoch_started, epoch_samples = time.monotonic(), 0
    model.train()
    wait_started = time.monotonic()
    for batch in loader:
        waited += time.monotonic() - wait_started
        if int(batch["batch"]) != step:
            raise RuntimeError(f"data out of order: batch {int(batch['batch'])} at step {step}")
        losses = train_step(model, optimiser, schedule, batch, cfg, run.device, shifts, bf16=run.bf16)
        step += 1
        if average is not None:
            average.update(model, step)
        size = len(batch["instruction"])
        window.add(losses.terms, losses.counts)
        epoch_means.add(losses.terms, losses.counts)
        epoch_samples += size
        run.progress.advance(1, size, log=step % cfg.log_every == 0)
        if step % cfg.log_every == 0 or step == total_steps:
            elapsed = time.monotonic() - window_started
            metrics = {**window.means(), "lr": schedule.get_last_lr()[0],
                       "samples_per_s": window.sums["loss"][1] / elapsed,
                       "data_wait": waited / elapsed}
            if run.on_metrics is not None:
                run.on_metrics(offset + step, metrics)
            window, window_started, waited = _Means(), time.monotonic(), 0.0
        if step % batches.batches_per_epoch == 0:
            record = {**epoch_means.means(), "lr": schedule.get_last_lr()[0],
                      "samples_per_s": epoch_samples / (time.monotonic() - epoch_started)}
            history.append(record)
            log.info("train it%d: %sepoch %d/%d %s", run.iteration, which, len(history), batches.epochs,
                     ", ".join(f"{k} {v:.3g}" for k, v in record.items()))
            epoch_means, epoch_started, epoch_samples = _Means(), time.monotonic(), 0
        if step < total_steps and step % cfg.checkpoint_every == 0 or step == total_steps and member + 1 < cfg.ensemble:
            save_state()
        wait_started = time.monotonic()
    return _Member(model, average, history, resumed_at, earlier_wall_s)


def training_precision(workspace: Workspace, config: CampaignConfig, batches: StepBatches, device: torch.device,
                       state: Normaliser | None) -> tuple[bool, str]:
    """bf16 autocast or fp32 for this training, and the log line's why: the device's rule (policies/precision.py);
    on a CPU where bf16 may pay (AVX-512 BF16, no AMX), a training of at least PROBE_MIN_SAMPLES measures a
    step of its own model on its own first batch both ways, once per host, model and batch
    (Workspace.precision_choices); a shorter one (an adaptation's fine-tuning) takes that choice where it
    was measured, else fp32."""
    cfg = config.train
    if not (cfg.amp and cpu_bf16_may_pay(device)):
        return uses_bf16(device, cfg.amp), describe(device, cfg.amp)
    dims = model_dims(config, state)
    key = probe_key(digest_of([cfg.model.model_dump_json(), repr(dims)]), cfg.batch_size)
    samples = cfg.ensemble * batches.epochs * batches.batches_per_epoch * cfg.batch_size
    if samples < PROBE_MIN_SAMPLES and not known_bf16(workspace.precision_choices, key):
        return uses_bf16(device, cfg.amp), describe(device, cfg.amp)
    bf16, speedup = measured_bf16(_step_timer(cfg, dims, batches.first_batch(), device),
                                  workspace.precision_choices, key)
    return bf16, (f"{'bf16 autocast' if bf16 else 'fp32'}, channels_last: bf16 measured at {speedup:.2f}x fp32's "
                  f"speed on this CPU at batch {cfg.batch_size}")


def _step_timer(cfg: TrainConfig, dims: ModelDims, batch: dict, device: torch.device) -> Callable[[bool], float]:
    """Seconds of one training step of a throwaway model on `batch`, in bf16 or fp32; the global RNG as it was."""
    rng = torch.get_rng_state()
    model = to_device_layout(VLAModel(cfg.model, dims), device)
    torch.set_rng_state(rng)
    optimiser = optimiser_for(model, cfg)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda _: 1.0)
    shifts = torch.Generator().manual_seed(0)

    def seconds(bf16: bool) -> float:
        rng = torch.get_rng_state()
        started = time.perf_counter()
        train_step(model, optimiser, schedule, batch, cfg, device, shifts, bf16=bf16)
        elapsed = time.perf_counter() - started
        torch.set_rng_state(rng)
        return elapsed

    return seconds


def run_train(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    dataset: IndexResult,
    tasks_key: str,
    embeddings: dict[str, np.ndarray],
    on_metrics: OnMetrics | None = None,
) -> TrainResult:
    """Unit of work: one model, keyed by the train settings that change what it computes
    (train_unit_key: the train config less its execution fields, the campaign seed, the frame size,
    depth, the dataset digest and the tasks unit). Trains it (resuming from its last train state),
    writes models/<key>/policy.pt and registers a `models` row."""
    catalog = Catalog(workspace.catalog)
    cfg = config.train
    key = train_unit_key(config, dataset, tasks_key)
    checkpoint = workspace.checkpoint(key)
    digest = selection_digest(dataset, cfg.where)
    existing = catalog.query("SELECT train_samples, dataset_shards FROM models WHERE model_key = ?", [key])
    if existing:
        log.info("train it%d: model %s already trained on dataset %s, skipped", iteration, key, digest[:12])
        return TrainResult(model_key=key, checkpoint=str(checkpoint), dataset_digest=digest, samples=existing[0][0],
                           dataset_shards=existing[0][1], history=[], resumed_at_step=0, skipped=True)

    check_where(cfg.where)
    units = [*dataset.explore_units, *dataset.filter_units]
    missing = len(set(units) - catalog.registered_keys(units))
    if missing:  # quarantined since it was indexed: it would train on less than its key says (a run makes them again)
        raise SelectionError(f"iteration {iteration}'s dataset {dataset.dataset_digest[:12]} has changed since it was "
                             f"indexed: {missing} of its units quarantined (`sim2act sql \"SELECT * FROM quarantine\"`); "
                             "run `sim2act run` with this config to make them again, then train")
    source = initial_policy(catalog, workspace, cfg.init_from)
    started = time.monotonic()
    device = training_device(cfg.device)
    threads_before = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    rows = dataset.selection.rows(catalog, cfg.where)
    if not rows:
        raise SelectionError(f"train.where: {cfg.where!r} leaves no step of iteration {iteration}'s dataset to train on")
    # a fine-tuning keeps its source's heads: the state head as wide as the source's data made it (the generalist's
    # million holds longer simulator states than the five tasks its adaptation trains on)
    state_width = None if source is None else source.get("dims", {}).get("state_dim")
    if state_width and cfg.state_weight == 0:  # else a strict load fails naming an "architecture"
        raise SelectionError(f"train.state_weight: {cfg.init_from} has a state head (it trained with "
                             "train.state_weight > 0); expected train.state_weight > 0 to fine-tune it, got 0")
    if state_width == 0 and cfg.state_weight > 0:
        log.warning("train.state_weight %g: %s has no state head, so this fine-tuning has no state loss",
                    cfg.state_weight, cfg.init_from)
    action_norm, proprio_norm, state_norm = normalisers(catalog, dataset, cfg, state_width)
    if source is not None:  # the source's heads speak in its own units
        action_norm, proprio_norm = Normaliser(*source["action"]), Normaliser(*source["proprio"])
    shards_read = sorted({catalog.store.rel_of(r.path) for r in rows})
    frozen_language = not cfg.model.language_trainable
    rewordings = None
    if cfg.language_augment > 0:
        rewordings, embeddings = reworded_instructions(embeddings, cfg.model.language_encoder, frozen_language)
    batches = StepBatches(
        rows, cfg.batch_size, cfg.shuffle_buffer, 0, 1, cfg.loader_workers,  # seeded per member; epochs set below
        TrainingCollate(action_norm, proprio_norm, embeddings if frozen_language else None, cfg.targets, state_norm,
                        cfg.model.chunk, rewordings, cfg.language_augment),
        chunk=cfg.model.chunk, store=catalog.store,
    )
    batches.epochs = training_epochs(cfg, batches.batches_per_epoch)
    samples, steps_per_member = batches.rows_per_epoch, batches.epochs * batches.batches_per_epoch
    bf16, precision = training_precision(workspace, config, batches, device, state_norm)
    log.info(
        "train it%d: %d triplets (%s), %s%d epochs x %d steps on %s (%s), dataset %s", iteration, samples,
        cfg.where or "all kept", f"{cfg.ensemble} members x " if cfg.ensemble > 1 else "", batches.epochs,
        batches.batches_per_epoch, device, precision, digest[:12],
    )
    progress = Progress(log, f"train it{iteration}", cfg.ensemble * steps_per_member, "steps", "samples")
    run = _Run(workspace, config, iteration, key, batches, device, state_norm,
               None if source is None else checkpoint_members(source), on_metrics, progress, bf16)
    try:
        members = [_train_member(run, member) for member in range(cfg.ensemble)]
    finally:
        progress.close()
        torch.set_num_threads(threads_before)
    history = [record for member in members for record in member.history]
    resumed_at = max((i * steps_per_member + m.resumed_at_step for i, m in enumerate(members) if m.resumed_at_step), default=0)
    averages = None if cfg.ema is None else [m.average.weights for m in members]
    save_atomically(checkpoint, policy_state([m.model for m in members], action_norm, proprio_norm, averages, cfg.ema))
    StageUnits(catalog, STAGE, config.name, iteration).register(key, UnitOutput(
        summary={"final_loss": history[-1]["loss"], "epochs": batches.epochs, "steps": cfg.ensemble * steps_per_member,
                 "members": cfg.ensemble, "resumed_at_step": resumed_at, "where": cfg.where,
                 "weights": "final" if cfg.ema is None else f"ema {cfg.ema}", "chunk": cfg.model.chunk,
                 "seed": cfg.seed, "recipe": training_recipe(config),
                 "precision": "bf16" if bf16 else "fp32"},  # the device's or the probe's choice, not the recipe's
        earlier_wall_s=sum(m.earlier_wall_s for m in members),
        rows={"models": [{
            "model_key": key, "campaign": config.name, "iteration": iteration,
            "checkpoint_path": str(checkpoint.relative_to(workspace.root)), "dataset_digest": digest,
            "dataset_shards": shards_read, "train_samples": samples,
            "final_loss": history[-1]["loss"], "unit_key": key,
        }]},
    ), time.monotonic() - started)
    for member in range(cfg.ensemble):
        workspace.train_state(key, member).unlink(missing_ok=True)
    return TrainResult(model_key=key, checkpoint=str(checkpoint), dataset_digest=digest, samples=samples,
                       dataset_shards=shards_read, history=history, resumed_at_step=resumed_at, skipped=False)
