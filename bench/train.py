"""`sim2act bench train`: training throughput through the real train stage, and the trained
policy's latency, side by side in one run.

- the train stage end to end (`run_train`: SQL selection, Parquet reads, shuffle buffer, frames
  decoded in the DataLoader worker, AdamW steps, checkpoints, registration) on a fresh copy of a
  synthetic warehouse (real Parquet shards, frames stored raw as campaigns store them, decided by the real
  filter stage and indexed by the real index stage), the campaign's default train settings; its own
  `on_metrics` points give samples/s and the fraction of wall time spent waiting for data;
- (reference) the same training steps on batches built once in memory by the same collate, no
  reader and no DataLoader: what the reader costs is the ratio of the two;
- the same stage with `loader_workers: 0`, with the ResNet-18 and the patch-ViT vision encoders, and with the
  language encoder fine-tuned (full size only);
- on a GPU, the default stage case on cuda at batch sizes 256 and 1024;
- `Policy.act` latency at batch 1 on an 84x84 frame, with 1 torch thread (what evaluation and
  explore workers run with) and with 2.

Every stage figure skips the run's first logged window (loader start, warm-up).
"""

from __future__ import annotations

import datetime
import json
import shutil
import statistics
import itertools
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel

from bench.rollout import LoadMeter
from bench.synthetic import TASKS, frame, register_explore_unit
from bench.tables import Ratio, cores, ratio_table, table
from envs.observation import PROPRIO_DIM, Observation
from policies.policy import Policy
from policies.precision import cpu_has_bf16_units
from schemas.config import CampaignConfig, ConfigError, TrainConfig
from schemas.workspace import Workspace
from stages.index import IndexResult
from warehouse.catalog import Catalog

CAMPAIGN = "bench"  # the synthetic units' campaign: the config's name must match it
TASKS_KEY = "bench-tasks"
FAMILY = "robosuite"
LANGUAGE_DIM = 384  # all-MiniLM-L6-v2, the default (frozen) encoder
DATA_WAIT_TARGET = 0.10  # at most
# the bench's cases, as `sim2act bench train --cases` names them
CASES = ("stage", "memory", "precision", "workers0", "resnet18", "vit", "minilm", "cuda", "act")
CUDA_LOADER_WORKERS = 8  # at most: a GPU step outruns one worker reading and decoding frames
LATENCY_P95_TARGET_MS = 20.0  # at most
BF16_SPEEDUP_TARGET = 1.8  # bf16 + channels_last over fp32, samples/s, where the CPU has bf16 units (issue 9)


class TrainSizes(BaseModel):
    units: int = 10  # synthetic explore units of the warehouse
    episodes_per_unit: int = 4
    steps_per_episode: int = 100  # every frame of an episode differs
    steps: int = 300  # training steps per stage case at least: epochs are rounded up to reach it
    log_every: int = 10  # steps per metrics window
    latency_calls: int = 200
    latency_warmup: int = 10
    cuda_batches: list[int] = [256, 1024]
    precision_batch: int = 256  # the precision rows' batch size (the issue's figures are at 256)
    precision_steps: int = 30  # each: emulated bf16 (a CPU without bf16 units) runs ~34 samples/s at batch 256
    cases: list[str] = list(CASES)  # which to run ("stage" always runs: every ratio is against it)


# seconds, for tests and a smoke check; the figures mean little at these sizes
QUICK = TrainSizes(units=2, episodes_per_unit=4, steps_per_episode=50, steps=6, log_every=2, latency_calls=20,
                   precision_batch=16, precision_steps=6, cases=["stage", "memory", "precision", "cuda", "act"])


class TrainRow(BaseModel):
    case: str
    name: str
    device: str | None = None
    batch_size: int | None = None
    loader_workers: int | None = None  # None: no DataLoader
    steps: int | None = None  # training steps run (latency: act() calls timed)
    windows: int | None = None  # metrics windows the figures are over (the first skipped)
    samples_per_s: float | None = None  # median over the windows
    data_wait: float | None = None  # mean over the windows: fraction of wall time waiting for the DataLoader
    threads: int | None = None  # torch threads
    p50_ms: float | None = None
    p95_ms: float | None = None
    wall_s: float | None = None
    other_load: float | None = None  # cores the machine's other processes kept busy meanwhile
    note: str = ""


class TrainBench(BaseModel):
    cpus: int
    torch_threads: int  # torch's threads when the bench started (the stage sets train.threads)
    gpu: str  # its name, or "no GPU"
    triplets: int  # training samples per epoch
    frame_size: int
    rows: list[TrainRow]
    ratios: list[Ratio]


def _config(train: dict[str, Any]) -> CampaignConfig:
    return CampaignConfig.model_validate({"name": CAMPAIGN, "train": train})


def _embeddings() -> dict[str, np.ndarray]:
    return {f"do {task}": np.zeros(LANGUAGE_DIM, np.float32) for task in TASKS}


def _register_tasks(workspace: Workspace) -> None:
    rows = [
        {"campaign": CAMPAIGN, "task_id": t, "spec": t.split("-")[0],
         "family": "metaworld" if t.startswith("mw") else FAMILY, "env_name": "Lift", "instruction": f"do {t}",
         "instructions": [f"do {t}"], "unseen_instructions": [], "object_colours": json.dumps({}), "split": "seen",
         "horizon": 100, "unit_key": TASKS_KEY}
        for t in TASKS
    ]
    Catalog(workspace.catalog).register_unit(unit_key=TASKS_KEY, stage="generate_tasks", campaign=CAMPAIGN,
                                             iteration=0, summary={}, rows={"tasks": rows})


def build_warehouse(workspace: Workspace, sizes: TrainSizes) -> IndexResult:
    """Synthetic explore units, decided by the real filter stage and indexed by the real index stage."""
    from stages.filter import run_filter
    from stages.index import run_index

    Catalog(workspace.catalog).initialise()
    _register_tasks(workspace)
    keys = [f"explore-u{u}" for u in range(sizes.units)]
    for u, key in enumerate(keys):
        register_explore_unit(workspace, key, campaign=CAMPAIGN, seed=u, episodes=sizes.episodes_per_unit,
                              steps=sizes.steps_per_episode, unique_frames=sizes.steps_per_episode)
    config = _config({})
    filtered = run_filter(workspace, config, 0, keys)
    return run_index(workspace, config, 0, keys, filtered.unit_keys, None)


def _batches_per_epoch(catalog: Catalog, dataset: IndexResult, batch_size: int, workers: int) -> int:
    from warehouse.training_reader import StepBatches

    return StepBatches(dataset.selection.rows(catalog), batch_size, 1, 0, 1, workers).batches_per_epoch


def _window_figures(samples_per_s: list[float], data_wait: list[float] | None) -> tuple[float, float | None, int]:
    """(median samples/s, mean data wait, windows) over the windows after the first (warm-up)."""
    skip = 1 if len(samples_per_s) > 1 else 0
    rates = samples_per_s[skip:]
    waits = None if data_wait is None else data_wait[skip:]
    return statistics.median(rates), None if waits is None else statistics.fmean(waits), len(rates)


def _parameters(checkpoint: Path) -> float:
    """Millions of parameters of the checkpoint's (first) model, its buffers (batch-norm statistics) left out."""
    return sum(p.numel() for p in Policy.load(checkpoint).members[0].parameters()) / 1e6


def run_stage_case(source: Workspace, dataset: IndexResult, root: Path, sizes: TrainSizes, case: str, name: str,
                   train: dict[str, Any]) -> tuple[TrainRow, Path]:
    """The train stage on a fresh copy of the warehouse: -> (its row, the checkpoint it wrote)."""
    from stages.train import run_train, training_device, training_epochs

    workspace = Workspace.at(root / case)
    shutil.copytree(source.root, workspace.root)
    defaults = TrainConfig()
    batch_size = train.get("batch_size", defaults.batch_size)
    workers = train.get("loader_workers", defaults.loader_workers)
    per_epoch = _batches_per_epoch(Catalog(workspace.catalog), dataset, batch_size, workers)
    config = _config({**train, "steps": sizes.steps, "log_every": sizes.log_every})
    epochs = training_epochs(config.train, per_epoch)
    device = training_device(config.train.device).type
    points: list[tuple[int, dict[str, float]]] = []
    meter = LoadMeter()
    result = run_train(workspace, config, 0, dataset, TASKS_KEY, _embeddings(),
                       on_metrics=lambda step, metrics: points.append((step, metrics)))
    wall_s = time.perf_counter() - meter.wall
    if result.skipped or not points:
        raise RuntimeError(f"bench train {case}: the stage trained nothing ({len(points)} metrics points)")
    rate, wait, windows = _window_figures([m["samples_per_s"] for _, m in points], [m["data_wait"] for _, m in points])
    checkpoint = Path(result.checkpoint)
    steps = epochs * per_epoch
    row = TrainRow(
        case=case, name=name, device=device, batch_size=batch_size, loader_workers=workers, steps=steps,
        windows=windows, samples_per_s=rate, data_wait=wait, threads=config.train.threads, wall_s=wall_s,
        other_load=meter.other_load(),
        note=f"{epochs} epoch(s) x {per_epoch} steps; {_parameters(checkpoint):.2f}M parameters; "
             f"{steps / wall_s:.1f} steps/s over the whole stage call (loader start, checkpoints included)",
    )
    return row, checkpoint


# The in-memory reference in each precision, side by side (`--cases precision`): (case, what,
# bf16 autocast, channels_last); "memory" itself runs the device's own choice (policies/precision.py).
PRECISIONS = (
    ("memory-fp32", "in-memory steps, fp32, contiguous (NCHW)", False, False),
    ("memory-fp32-cl", "in-memory steps, fp32, channels_last", False, True),
    ("memory-bf16-cl", "in-memory steps, bf16 autocast, channels_last", True, True),
)


def run_in_memory(source: Workspace, dataset: IndexResult, sizes: TrainSizes, steps: int, batch_size: int | None = None,
                  precision: tuple[str, str, bool, bool] | None = None) -> TrainRow:
    """The reference: `steps` training steps as the stage takes them (same model, optimiser, schedule,
    threads, device, batch size, collate), on batches built once in memory; windows as the stage's.
    `precision`: a row of PRECISIONS instead of the device's own choice."""
    from torch.utils.data import default_convert

    from policies.model import VLAModel
    from policies.precision import describe, to_device_layout
    from stages.train import (TrainingCollate, model_dims, normalisers, optimiser_for, train_step, training_device,
                              warmup_cosine)
    from warehouse.training_reader import COLUMNS

    catalog = Catalog(source.catalog)
    config = _config({"log_every": sizes.log_every, **({"batch_size": batch_size} if batch_size else {})})
    cfg = config.train
    device = training_device(cfg.device)
    case, name, bf16, channels_last = precision or (
        "memory", "the same steps on in-memory batches (no reader, no DataLoader)", None, None)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(0)
    action_norm, proprio_norm, state_norm = normalisers(catalog, dataset, cfg)
    rows = dataset.selection.kept_steps(catalog, [*COLUMNS, "episode_id"], cfg.where).to_pylist()  # in step order
    chunk = cfg.model.chunk
    if chunk > 1:  # as the stage's reader attaches them: this step's action and the next chunk-1 of its episode
        for i, row in enumerate(rows):
            ahead = list(itertools.takewhile(lambda r: r["episode_id"] == row["episode_id"], rows[i:i + chunk]))
            row["action_chunk"], row["expert_chunk"] = [r["action"] for r in ahead], [r["expert_action"] for r in ahead]
    collate = TrainingCollate(action_norm, proprio_norm, _embeddings(), cfg.targets, state_norm, chunk=chunk)
    order = np.random.default_rng(0).permutation(len(rows))
    batches = [default_convert(collate([rows[i] for i in order[first : first + cfg.batch_size]]))
               for first in range(0, len(rows), cfg.batch_size)]
    if device.type == "cuda":  # as the stage's DataLoader hands them over (pin_memory)
        batches = [{k: v.pin_memory() if torch.is_tensor(v) else v for k, v in b.items()} for b in batches]
    model = to_device_layout(VLAModel(cfg.model, model_dims(config, state_norm)), device, channels_last)
    optimiser = optimiser_for(model, cfg)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, warmup_cosine(steps))
    model.train()
    rates: list[float] = []
    meter = LoadMeter()
    window_started, samples = time.perf_counter(), 0
    for step in range(1, steps + 1):
        batch = batches[(step - 1) % len(batches)]
        train_step(model, optimiser, schedule, batch, cfg, device, bf16=bf16, channels_last=channels_last)
        samples += len(batch["instruction"])
        if step % cfg.log_every == 0 or step == steps:
            now = time.perf_counter()
            rates.append(samples / (now - window_started))
            window_started, samples = now, 0
    wall_s = time.perf_counter() - meter.wall
    rate, _, windows = _window_figures(rates, None)
    computes = describe(device, cfg.amp) if precision is None else (
        ("bf16 autocast" if bf16 else "fp32") + (", channels_last" if channels_last else ""))
    return TrainRow(
        case=case, name=name, device=device.type,
        batch_size=cfg.batch_size, steps=steps, windows=windows, samples_per_s=rate, threads=cfg.threads,
        wall_s=wall_s, other_load=meter.other_load(),
        note=f"{len(batches)} batches collated once (frames decoded, tensors), cycled; {computes}",
    )


def run_latency(checkpoint: Path, vision: str, threads: int, sizes: TrainSizes, image_size: int) -> TrainRow:
    """`Policy.act` at batch 1 on real-sized frames, as evaluation and explore workers call it."""

    instruction = f"do {TASKS[0]}"
    policy = Policy.load(checkpoint, {instruction: _embeddings()[instruction]})  # embeddings cached, as workers have
    proprio = np.random.default_rng(0).normal(size=(8, PROPRIO_DIM)).astype(np.float32)
    observations = [Observation(frame(image_size, (200, 40, 40), step), proprio[step], {}) for step in range(8)]
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for call in range(sizes.latency_warmup):
            policy.act(observations[call % 8], instruction, FAMILY)
        times = []
        meter = LoadMeter()
        for call in range(sizes.latency_calls):
            started = time.perf_counter()
            decision = policy.act(observations[call % 8], instruction, FAMILY)
            times.append(time.perf_counter() - started)
        wall_s = time.perf_counter() - meter.wall
    finally:
        torch.set_num_threads(previous)
    if decision.action.shape != (7,) or not np.isfinite(decision.uncertainty):
        raise RuntimeError(f"bench train: act() gave {decision}")
    p50, p95 = np.percentile(np.asarray(times) * 1000, [50, 95])
    return TrainRow(
        case=f"act-{vision}-{threads}", name=f"Policy.act, {vision}, batch 1, {threads} thread{'s' * (threads > 1)}",
        device="cpu", batch_size=1, steps=sizes.latency_calls, threads=threads, p50_ms=float(p50), p95_ms=float(p95),
        wall_s=wall_s, other_load=meter.other_load(),
        note=f"{image_size}x{image_size} uint8 frame, {sizes.latency_warmup} warm-up calls; checkpoint loaded on CPU",
    )


def _gpu() -> str:
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"


def _ratio(name: str, value: float, unit: str = "x", target: float | None = None, at_most: bool = False) -> Ratio:
    return Ratio.of(name, value, target, unit, at_most)


def _weights_missing(encoder: str) -> str | None:
    """Why the encoder cannot load here (its weights package absent), or None."""
    from policies.language import ENCODERS

    try:
        ENCODERS[encoder].weights()
    except ImportError as exc:
        return f"skipped: {encoder}'s weights are not installed ({exc})"
    return None


def bench_train(sizes: TrainSizes, scratch: Path | None = None) -> TrainBench:
    unknown = sorted(set(sizes.cases) - set(CASES))
    if unknown:
        raise ConfigError(f"bench train: --cases: expected some of {', '.join(CASES)}, got {', '.join(unknown)}")
    cpus, torch_threads = cores(), torch.get_num_threads()
    image_size = CampaignConfig().render.image_size
    wanted = set(sizes.cases) | {"stage"}
    if scratch is not None:  # --scratch names a folder to use: made if missing, like a workspace
        Path(scratch).mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="sim2act-bench-", dir=scratch))
    try:
        source = Workspace.at(root / "warehouse").create()
        dataset = build_warehouse(source, sizes)
        default, checkpoint = run_stage_case(source, dataset, root, sizes, "stage",
                                             "train stage, default settings (ViT-hybrid, loader_workers 1)", {})
        rows = [default]
        if "memory" in wanted:
            rows.append(run_in_memory(source, dataset, sizes, default.steps))
        if "precision" in wanted and default.device == "cpu":
            rows += [run_in_memory(source, dataset, sizes, sizes.precision_steps, sizes.precision_batch, p)
                     for p in PRECISIONS]
        checkpoints = {"hybrid": checkpoint}
        variants = [
            ("workers0", "train stage, loader_workers 0 (decoding in the training process)", {"loader_workers": 0}),
            ("resnet18", "train stage, ResNet-18 vision encoder (width 16)", {"model": {"vision": "resnet18"}}),
            ("vit", "train stage, ViT over pixel patches (patch 12)", {"model": {"vision": "vit"}}),
            ("minilm", "train stage, language encoder fine-tuned (MiniLM in the model)",
             {"model": {"language_trainable": True}}),
        ]
        for case, name, train in variants:
            if case not in wanted:
                continue
            missing = _weights_missing(TrainConfig().model.language_encoder) if case == "minilm" else None
            if missing:
                rows.append(TrainRow(case=case, name=name, note=missing))
                continue
            row, trained = run_stage_case(source, dataset, root, sizes, case, name, train)
            rows.append(row)
            if case in ("resnet18", "vit"):
                checkpoints[case] = trained
        if "cuda" in wanted and torch.cuda.is_available():
            workers = max(1, min(CUDA_LOADER_WORKERS, cpus // 2))
            for batch_size in sizes.cuda_batches:
                rows.append(run_stage_case(source, dataset, root, sizes, f"cuda{batch_size}",
                                           f"train stage on cuda, batch {batch_size}, {workers} loader workers",
                                           {"device": "cuda", "batch_size": batch_size,
                                            "loader_workers": workers})[0])
        elif "cuda" in wanted:
            rows.append(TrainRow(case="cuda", name="train stage on cuda, batch " +
                                 " and ".join(map(str, sizes.cuda_batches)), note="skipped: torch sees no GPU"))
        if "act" in wanted:
            for vision, trained in checkpoints.items():
                rows += [run_latency(trained, vision, threads, sizes, image_size) for threads in (1, 2)]
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return TrainBench(cpus=cpus, torch_threads=torch_threads, gpu=_gpu(), triplets=dataset.triplets,
                      frame_size=image_size, rows=rows, ratios=_ratios({r.case: r for r in rows}))


def _ratios(rows: dict[str, TrainRow]) -> list[Ratio]:
    stage = rows["stage"]
    ratios = []
    if "memory" in rows:
        ratios.append(_ratio("train stage / in-memory batches, samples/s",
                             stage.samples_per_s / rows["memory"].samples_per_s))
    for row in rows.values():
        if row.data_wait is not None and (row.case == "stage" or row.case.startswith("cuda")):
            ratios.append(_ratio(f"data wait, {row.name}", row.data_wait, "%", DATA_WAIT_TARGET, at_most=True))
    if "memory-fp32" in rows:
        fp32 = rows["memory-fp32"].samples_per_s
        for case in ("memory-fp32-cl", "memory-bf16-cl"):
            # the bf16 target holds where there are bf16 units to use; elsewhere the row shows what emulation costs
            bf16_target = case == "memory-bf16-cl" and (rows[case].device != "cpu" or cpu_has_bf16_units())
            ratios.append(_ratio(f"{rows[case].name} / fp32 NCHW, samples/s", rows[case].samples_per_s / fp32,
                                 target=BF16_SPEEDUP_TARGET if bf16_target else None))
    for case, name in (("workers0", "loader_workers 0 / 1"), ("resnet18", "ResNet-18 / ViT-hybrid"),
                       ("vit", "patch ViT / ViT-hybrid"),
                       ("minilm", "fine-tuned / frozen language encoder")):
        if case in rows and rows[case].samples_per_s is not None:
            ratios.append(_ratio(f"{name}, stage samples/s", rows[case].samples_per_s / stage.samples_per_s))
    for row in rows.values():
        if row.p95_ms is not None:
            ratios.append(_ratio(f"p95 latency, {row.name}", row.p95_ms, "ms", LATENCY_P95_TARGET_MS, at_most=True))
    return ratios


def _figure(value: float | None, digits: int = 0) -> str:
    return "" if value is None else f"{value:,.{digits}f}"


def markdown(bench: TrainBench, command: str) -> str:
    lines = [
        "# Training benchmark: the train stage vs in-memory batches, and the policy's latency",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()}, {bench.cpus} CPUs, torch {bench.torch_threads} "
        f"threads, {bench.gpu}. A synthetic warehouse of {bench.triplets:,} triplets ({bench.frame_size}x"
        f"{bench.frame_size} frames stored raw, real Parquet shards, the real filter and index stages); every stage "
        "case trains on a fresh copy of it through `run_train` with the campaign's default train settings but the "
        "row's, its figures from the stage's own metrics points: samples/s the median and data wait (the share "
        "of wall time blocked on the DataLoader) the mean over the windows after the first (loader start, "
        "warm-up). The in-memory reference runs the same steps on batches collated once. Latency: `Policy.act` "
        "on one frame, cached instruction embedding. Other load = cores the machine's other processes kept busy "
        "meanwhile (above ~0.1, the figures are slowed by them).",
        "",
        *table(["case", "what", "device", "batch", "loader workers", "steps", "samples/s", "data wait", "threads",
                "p50 ms", "p95 ms", "wall s", "other load", "notes"], [
            [r.case, r.name, r.device, _figure(r.batch_size), _figure(r.loader_workers), _figure(r.steps),
             _figure(r.samples_per_s), None if r.data_wait is None else f"{r.data_wait:.1%}", _figure(r.threads),
             _figure(r.p50_ms, 2), _figure(r.p95_ms, 2), _figure(r.wall_s, 2 if (r.wall_s or 0) < 1 else 1),
             _figure(r.other_load, 2), r.note]
            for r in bench.rows]),
    ]
    return "\n".join([*lines, "", *ratio_table(bench.ratios)]) + "\n"
