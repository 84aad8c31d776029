"""`sim2act bench train` runs the real train stage and the in-memory reference side by side, then
times the trained policy's act()."""

import json
import os

import numpy as np
import pytest
import torch

from flows.cli import main
from policies.model import VLAModel
from policies.policy import Normaliser
from policies.precision import cpu_has_bf16_units
from schemas.config import CampaignConfig, ModelConfig
from stages.train import model_dims


def test_bench_train_reports_the_stage_the_reference_the_latency_and_the_ratios(tmp_path, capsys):
    out = tmp_path / "docs" / "bench-train.md"
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    assert main(["bench", "train", "--quick", "--json", "--scratch", str(scratch), "--out", str(out)]) == 0
    bench = json.loads(capsys.readouterr().out)
    gpu = torch.cuda.is_available()
    assert bench["cpus"] == os.cpu_count() and (bench["gpu"] == "no GPU") == (not gpu)
    assert bench["triplets"] == 2 * 4 * 50 and bench["frame_size"] == 84  # QUICK's warehouse, every episode kept
    rows = {r["case"]: r for r in bench["rows"]}
    precision = [] if gpu else ["memory-fp32", "memory-fp32-cl", "memory-bf16-cl"]  # CPU only
    assert list(rows) == ["stage", "memory", *precision, *(["cuda256", "cuda1024"] if gpu else ["cuda"]),
                          "act-hybrid-1", "act-hybrid-2"]

    stage, memory = rows["stage"], rows["memory"]
    # the default train settings, epochs rounded up past QUICK's 6 steps: one epoch of ceil(400 / 64) batches
    assert (stage["batch_size"], stage["loader_workers"], stage["steps"], stage["threads"]) == (64, 1, 7, 2)
    assert stage["device"] == ("cuda" if gpu else "cpu")
    assert stage["windows"] == 3  # metrics at steps 2, 4, 6 and 7; the first window (loader start) skipped
    assert stage["samples_per_s"] > 0 and 0 <= stage["data_wait"] <= 1
    # the figures are the training windows', not the whole call's (spawning the loader worker alone takes seconds)
    assert stage["samples_per_s"] > bench["triplets"] / stage["wall_s"]
    synthetic_state = Normaliser.fit(np.zeros((1, 16)), 16)  # the synthetic steps' qpos: the auxiliary state head's width
    default_model = VLAModel(ModelConfig(), model_dims(CampaignConfig(), synthetic_state))
    parameters = sum(p.numel() for p in default_model.parameters()) / 1e6
    assert f"; {parameters:.2f}M parameters;" in stage["note"]  # the default model, as the stage saved it
    assert memory["loader_workers"] is None and memory["data_wait"] is None
    assert (memory["batch_size"], memory["steps"], memory["windows"]) == (64, 7, 3) and memory["samples_per_s"] > 0
    if not gpu:
        assert rows["cuda"]["samples_per_s"] is None and "no GPU" in rows["cuda"]["note"]

    for threads in (1, 2):
        act = rows[f"act-hybrid-{threads}"]
        assert (act["threads"], act["steps"], act["batch_size"], act["device"]) == (threads, 20, 1, "cpu")
        assert 0 < act["p50_ms"] <= act["p95_ms"] and act["samples_per_s"] is None

    ratios = {r["name"]: r for r in bench["ratios"]}
    if not gpu:  # fp32 and bf16 side by side, at QUICK's precision batch and steps
        for case, note in (("memory-fp32", "; fp32"), ("memory-fp32-cl", "; fp32, channels_last"),
                           ("memory-bf16-cl", "; bf16 autocast, channels_last")):
            assert (rows[case]["batch_size"], rows[case]["steps"]) == (16, 6) and rows[case]["note"].endswith(note)
        bf16 = ratios["in-memory steps, bf16 autocast, channels_last / fp32 NCHW, samples/s"]
        assert bf16["value"] == pytest.approx(rows["memory-bf16-cl"]["samples_per_s"] / rows["memory-fp32"]["samples_per_s"])
        assert bf16["target"] == (1.8 if cpu_has_bf16_units() else None)  # a target only where there are units
    reader = ratios["train stage / in-memory batches, samples/s"]
    assert reader["value"] == pytest.approx(stage["samples_per_s"] / memory["samples_per_s"]) and reader["met"] is None
    wait = ratios["data wait, train stage, default settings (ViT-hybrid, loader_workers 1)"]
    assert wait["value"] == stage["data_wait"] and wait["target"] == 0.1 and wait["at_most"]
    assert wait["met"] == (wait["value"] <= 0.1)
    for threads in (1, 2):
        act = rows[f"act-hybrid-{threads}"]
        latency = ratios[f"p95 latency, {act['name']}"]
        assert latency["value"] == act["p95_ms"] and latency["target"] == 20.0 and latency["unit"] == "ms"
        assert latency["met"] == (act["p95_ms"] <= 20.0)

    table = out.read_text()
    assert "`sim2act bench train --quick --json" in table and f"{os.cpu_count()} CPUs" in table
    assert all(f"\n| {case} | " in table for case in rows) and "| data wait, train stage" in table
    assert list(scratch.iterdir()) == []  # the throwaway workspaces are gone
